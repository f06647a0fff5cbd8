"""matscan: photographs of a flat material under known lights → physically based material maps."""

__version__ = "0.1.0"
