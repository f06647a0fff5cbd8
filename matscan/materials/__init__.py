"""Material priors: procedural generators and readers of map libraries users own."""

from matscan.materials.procedural import FAMILIES, generate, random_material

__all__ = ["FAMILIES", "generate", "random_material"]
