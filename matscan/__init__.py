"""matscan: photographs of a flat material under known lights → physically based material maps.

The Python API (docs/api.md) is importable from here::

    import matscan

    matscan.reconstruct("@sample", "out")        # capture folder → maps, exports, report
    maps = matscan.read_mapset("out")

Each name is imported on first use (PEP 562), so ``import matscan`` stays cheap: it
loads neither torch nor any other heavy dependency.

``matscan.reconstruct`` and ``matscan.calibrate`` are the functions, although
``matscan/reconstruct/`` and ``matscan/calibrate.py`` are also modules: reach the
modules with ``from matscan.reconstruct import job`` or ``from matscan.calibrate
import light_scales`` (``import matscan.reconstruct.job as job`` does not work).
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: The public API: each name, and the module that defines it.
_API = {
    "Calibration": "matscan.calibrate",
    "CameraModel": "matscan.capture.virtual",
    "Capture": "matscan.capture.folder",
    "LightSet": "matscan.rig",
    "MapSet": "matscan.mapset",
    "MatscanError": "matscan.errors",
    "ReconstructConfig": "matscan.reconstruct.job",
    "builtin_rig": "matscan.rig",
    "calibrate": "matscan.calibrate",
    "export_maps": "matscan.export",
    "import_rti": "matscan.capture.rti",
    "load_capture": "matscan.capture.folder",
    "read_mapset": "matscan.mapset",
    "reconstruct": "matscan.reconstruct.job",
    "reconstruct_capture": "matscan.reconstruct.job",
    "render_maps": "matscan.render",
    "simulate": "matscan.capture.virtual",
    "write_mapset": "matscan.mapset",
    "write_maps": "matscan.mapset",
}

__all__ = [
    "Calibration",
    "CameraModel",
    "Capture",
    "LightSet",
    "MapSet",
    "MatscanError",
    "ReconstructConfig",
    "builtin_rig",
    "calibrate",
    "export_maps",
    "import_rti",
    "load_capture",
    "read_mapset",
    "reconstruct",
    "reconstruct_capture",
    "render_maps",
    "simulate",
    "write_mapset",
    "write_maps",
]


def __getattr__(name: str) -> Any:
    """Import an API name on first use, and keep it (later look-ups do not come here)."""
    try:
        module = _API[name]
    except KeyError:
        raise AttributeError(f"module 'matscan' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*__all__, "__version__"])


class _Package(types.ModuleType):
    """The type of the ``matscan`` module: loading a submodule sets the package's attribute
    of that name to it (``matscan.calibrate`` = the module), which would hide the API
    function of the same name; such an assignment is dropped, so the name always means the
    function. The submodule stays in ``sys.modules`` (``from matscan.calibrate import …``)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _API and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package

if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from matscan.calibrate import Calibration, calibrate
    from matscan.capture.folder import Capture, load_capture
    from matscan.capture.virtual import CameraModel, simulate
    from matscan.errors import MatscanError
    from matscan.export import export_maps
    from matscan.mapset import MapSet, read_mapset, write_maps, write_mapset
    from matscan.reconstruct.job import ReconstructConfig, reconstruct, reconstruct_capture
    from matscan.render import render_maps
    from matscan.rig import LightSet, builtin_rig
