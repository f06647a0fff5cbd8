"""Capture → maps: network inference at any size, then refinement by inverse rendering.

One file per stage: :mod:`~matscan.reconstruct.networks` (tiled inference),
:mod:`~matscan.reconstruct.solver` (start and fit), :mod:`~matscan.reconstruct.surface`
(alpha, height), :mod:`~matscan.reconstruct.job` (the command: checks, run, write,
record). The names below are the public API.
"""

from matscan.reconstruct.job import (
    REFINE_AUTO_PHOTOS,
    ReconstructConfig,
    Result,
    check_capture,
    leave_out_validation,
    reconstruct,
    reconstruct_capture,
    subset_capture,
    with_special_maps,
)
from matscan.reconstruct.networks import predict_maps
from matscan.reconstruct.solver import LOG_EPS, flat_start, refine_maps, rerender_error
from matscan.reconstruct.surface import alpha_from_backlight, height_from_normals

__all__ = [
    "LOG_EPS",
    "REFINE_AUTO_PHOTOS",
    "ReconstructConfig",
    "Result",
    "alpha_from_backlight",
    "check_capture",
    "flat_start",
    "height_from_normals",
    "leave_out_validation",
    "predict_maps",
    "reconstruct",
    "reconstruct_capture",
    "refine_maps",
    "rerender_error",
    "subset_capture",
    "with_special_maps",
]
