"""Built-in samples shipped with matscan: a map set and its simulated dome24 capture.

``sample``: a 256 × 256 procedural swatch of grained leather with a hot-stamped gold
foil ring, covering the dome24 field (120 × 120 mm). Built by
``tools/make_sample.py`` (deterministic); its capture was simulated with
``matscan simulate @sample --out … --noise 0.002`` (8-bit sRGB, 24 lights).
"""

from __future__ import annotations

from pathlib import Path

from matscan.errors import MatscanError

ROOT = Path(__file__).parent
SAMPLES = ("sample",)


def _check(name: str) -> Path:
    if name not in SAMPLES:
        raise MatscanError(f"@{name}: not a built-in sample (one of {', '.join('@' + s for s in SAMPLES)})")
    return ROOT / name


def sample_maps_path(name: str = "sample") -> Path:
    """Folder of a built-in sample's map set."""
    return _check(name) / "maps"


def sample_capture_path(name: str = "sample") -> Path:
    """Folder of a built-in sample's simulated dome24 capture."""
    return _check(name) / "capture"
