"""Built-in samples shipped with matscan: a map set and its simulated dome24 capture.

``sample``: a 256 × 256 procedural swatch of grained leather with a hot-stamped gold
foil ring, covering the dome24 field (120 × 120 mm). Built by
``tools/make_sample.py`` (deterministic); its capture was simulated with
``matscan simulate @sample --out … --noise 0.002`` (8-bit sRGB, 24 lights).

Wherever matscan takes a capture or map set folder (the library and the CLI alike),
the text ``@name`` names a built-in sample instead (:func:`capture_folder`,
:func:`maps_folder`).
"""

from __future__ import annotations

from pathlib import Path

from matscan.errors import MatscanError

ROOT = Path(__file__).parent
SAMPLES = ("sample",)
#: A capture or map set argument starting with this names a built-in sample (``@sample``).
SAMPLE_PREFIX = "@"


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


def capture_folder(spec: str | Path) -> Path:
    """The capture folder ``spec`` names: ``"@name"`` (text) is a built-in sample's
    capture (:func:`sample_capture_path`), anything else a path. An unknown sample
    name is a :class:`~matscan.errors.MatscanError` listing the samples."""
    if isinstance(spec, str) and spec.startswith(SAMPLE_PREFIX):
        return sample_capture_path(spec[len(SAMPLE_PREFIX) :])
    return Path(spec)


def maps_folder(spec: str | Path) -> Path:
    """The map set folder ``spec`` names: ``"@name"`` (text) is a built-in sample's
    map set (:func:`sample_maps_path`), anything else a path."""
    if isinstance(spec, str) and spec.startswith(SAMPLE_PREFIX):
        return sample_maps_path(spec[len(SAMPLE_PREFIX) :])
    return Path(spec)
