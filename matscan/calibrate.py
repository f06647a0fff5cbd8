"""Calibration (paper §3.2): a colour matrix from a ColorChecker, and per-light
intensity scales (and optional flat fields) from a grey card.

``calibration.json`` (``matscan-calibration/1``)::

    {"format": "matscan-calibration/1",
     "colour_matrix": [[…], […], […]],        # linear camera RGB → linear sRGB
     "light_scales": {"0": 1.02, "1": 0.97, …},  # per rig light: photo = scale × model
     "flat_fields": {"0": "flat_00.exr", …},   # optional: per light, mean 1
     "grey_albedo": 0.18}

A capture that names it is corrected on reading for reconstruction
(:func:`apply_calibration`): colour matrix first, then each photo divided by its
light's scale and flat field.

The ColorChecker is located by the user (the chart's four outer corners in pixel
coordinates, or the whole photo when the chart fills it): an automatic detector
would need a second OpenCV build beside ours.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from matscan.capture import Capture
from matscan.color import srgb_to_linear
from matscan.errors import MatscanError, input_error
from matscan.materials.noise import blur
from matscan.render import render, surface_points

CALIBRATION_FORMAT = "matscan-calibration/1"
GREY_CARD = 0.18

#: ColorChecker Classic patches, row by row from dark skin to black, as the 8-bit
#: sRGB values X-Rite publishes for the chart (post-November-2014 formulation).
COLORCHECKER_SRGB8 = [
    (115, 82, 68),
    (194, 150, 130),
    (98, 122, 157),
    (87, 108, 67),
    (133, 128, 177),
    (103, 189, 170),
    (214, 126, 44),
    (80, 91, 166),
    (193, 90, 99),
    (94, 60, 108),
    (157, 188, 64),
    (224, 163, 46),
    (56, 61, 150),
    (70, 148, 73),
    (175, 54, 60),
    (231, 199, 31),
    (187, 86, 149),
    (8, 133, 161),
    (243, 243, 242),
    (200, 200, 200),
    (160, 160, 160),
    (122, 122, 121),
    (85, 85, 85),
    (52, 52, 52),
]


def colorchecker_linear() -> Tensor:
    """(24, 3) linear sRGB reference values of the chart's patches."""
    return srgb_to_linear(torch.tensor(COLORCHECKER_SRGB8, dtype=torch.float64) / 255).float()


def sample_patches(
    photo: Tensor, corners: list[tuple[float, float]] | None = None, rows: int = 4, cols: int = 6, fraction: float = 0.5
) -> Tensor:
    """Mean colour (rows·cols, 3) of each patch of a chart in a linear photo (3, H, W).

    ``corners``: the chart's outer corners (x = column, y = row) in the order
    top-left, top-right, bottom-right, bottom-left; the whole photo by default.
    The central ``fraction`` of each patch is averaged.
    """
    _, h, w = photo.shape
    if corners is None:
        corners = [(0, 0), (w, 0), (w, h), (0, h)]
    if len(corners) != 4:
        raise MatscanError(f"corners: expected 4 (x, y) points, got {len(corners)}")
    tl, tr, br, bl = (np.array(c, dtype=np.float64) for c in corners)
    out = []
    for r in range(rows):
        for c in range(cols):
            samples = []
            for dv in np.linspace(-fraction / 2, fraction / 2, 5):
                for du in np.linspace(-fraction / 2, fraction / 2, 5):
                    u, v = (c + 0.5 + du) / cols, (r + 0.5 + dv) / rows
                    top = tl + (tr - tl) * u
                    bottom = bl + (br - bl) * u
                    x, y = top + (bottom - top) * v
                    xi, yi = int(np.clip(x, 0, w - 1)), int(np.clip(y, 0, h - 1))
                    samples.append(photo[:, yi, xi])
            out.append(torch.stack(samples).mean(0))
    return torch.stack(out)


def colour_matrix(measured: Tensor, reference: Tensor) -> Tensor:
    """3 × 3 M minimising Σ ‖M·measured_i − reference_i‖² (linear least squares)."""
    sol = torch.linalg.lstsq(measured.double(), reference.double()).solution  # measured @ X ≈ reference
    return sol.T.float()


def weighted_median(values: Tensor, weights: Tensor) -> float:
    """The minimiser s of Σ w_i |v_i − s| (for v = p/r, w = r: of Σ |p_i − s r_i|)."""
    order = torch.argsort(values)
    v, w = values[order], weights[order]
    cum = torch.cumsum(w, 0)
    idx = int(torch.searchsorted(cum, cum[-1] / 2))
    return float(v[min(idx, len(v) - 1)])


def light_scales(
    grey: Capture, albedo: float = GREY_CARD, flat_fields: bool = False, flat_sigma_px: float = 8.0
) -> tuple[dict[str, float], dict[str, Tensor]]:
    """Per-light intensity scale from photos of a grey card (a flat Lambertian of
    ``albedo``) under each light: the scale minimising the L1 distance between the
    photo and the rendering (the paper's 24 parameters); optionally the remaining
    smooth spatial ratio as a flat field of mean 1."""
    h, w = grey.size
    pts = surface_points(grey.field_mm, (h, w))
    n = torch.zeros(3, h, w)
    n[2] = 1
    scales, flats = {}, {}
    for i, k in enumerate(grey.light_indices):
        if k is None:
            raise MatscanError("calibrate: grey-card photos must come from a rig with fixed lights")
        with torch.no_grad():
            model = render(
                torch.full((3, h, w), albedo),
                torch.zeros(3, h, w),
                torch.ones(1, h, w),
                n,
                grey.lights.select([i]),
                pts,
            )[0]
        ok = (~grey.saturated[i]).expand_as(model) & (model > 1e-4)
        photo = grey.images[i]
        s = weighted_median((photo[ok] / model[ok]), model[ok])
        scales[str(k)] = s
        if flat_fields:
            ratio = (photo / (s * model).clamp_min(1e-4)).mean(0)
            ratio = blur(ratio, flat_sigma_px)
            flats[str(k)] = (ratio / ratio.mean())[None]
    return scales, flats


def write_calibration(
    path: Path, matrix: Tensor | None, scales: dict[str, float] | None, flats: dict[str, Tensor] | None = None
) -> dict[str, Any]:
    """Write ``calibration.json`` (and flat-field EXRs beside it)."""
    from matscan.imagefile import write_image

    doc: dict[str, Any] = {"format": CALIBRATION_FORMAT, "grey_albedo": GREY_CARD}
    if matrix is not None:
        doc["colour_matrix"] = [[round(float(v), 6) for v in row] for row in matrix]
    if scales:
        doc["light_scales"] = {k: round(v, 6) for k, v in scales.items()}
    if flats:
        doc["flat_fields"] = {}
        for k, t in flats.items():
            file = f"flat_{int(k):02d}.exr"
            write_image(path.parent / file, t.permute(1, 2, 0).numpy(), bits=32)
            doc["flat_fields"][k] = file
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
    return doc


def apply_calibration(capture: Capture) -> Capture:
    """The capture with its calibration applied (colour matrix, then per-light scale
    and flat field); unchanged when it has none."""
    cal = capture.calibration
    if not cal:
        return capture
    where = (capture.folder / "capture.json") if capture.folder else "calibration"
    if cal.get("format") != CALIBRATION_FORMAT:
        raise input_error(where, f"calibration: format must be {CALIBRATION_FORMAT!r}")
    images = capture.images
    if "colour_matrix" in cal:
        m = torch.tensor(cal["colour_matrix"], dtype=torch.float32)
        if m.shape != (3, 3):
            raise input_error(where, "calibration: colour_matrix must be 3 × 3")
        images = torch.einsum("ij,njhw->nihw", m, images)
    scales = cal.get("light_scales", {})
    flats = cal.get("flat_fields", {})
    out = []
    for img, k in zip(images, capture.light_indices, strict=True):
        if k is not None and str(k) in scales:
            img = img / float(scales[str(k)])
        if k is not None and str(k) in flats and capture.folder is not None:
            from matscan.imagefile import read_image

            flat = torch.from_numpy(read_image(capture.folder / flats[str(k)]).pixels).permute(2, 0, 1)
            if flat.shape[-2:] != img.shape[-2:]:
                raise input_error(capture.folder / flats[str(k)], "flat field size differs from the photos")
            img = img / flat.clamp_min(1e-3)
        out.append(img)
    return replace(capture, images=torch.stack(out).clamp_min(0))
