"""Light directions from the highlight on a chrome sphere in the frame (the RTI standard).

A mirror-like sphere photographed from far above (an orthographic view, v = +z) shows
each light as a small highlight where its normal bisects the light and the view:
n = normalize(l + v), so l = 2 (n·v) n − v. The sphere's outline in the photos (centre
and radius, in pixels) is given; in each photo the highlight is found as the brightest
spot inside the outline, grown to the connected region brighter than halfway between the
sphere's median and that peak (a saturated highlight is a plateau), and its normal as
the brightness-weighted mean of the sphere's normals over that region (weighted in
normal space, so a highlight near the outline is not pulled by the outline's
foreshortening).

Pixel coordinates: x is the column and y the row of a pixel's centre (the values an image
viewer shows), as in ``--sphere CX,CY,R``. The directions are in matscan's frame (+y
toward the image's top), as :mod:`matscan.capture.rti` writes them with ``y="up"``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from matscan.color import srgb_to_linear
from matscan.errors import MatscanError, input_error
from matscan.imagefile import read_image

#: Only the sphere's inner part is searched: at its outline the normal is grazing and the
#: photos show the background's reflection.
INNER = 0.97
#: Pixels brighter than this fraction of the highlight's peak (above the sphere's median)
#: make up the highlight.
HIGHLIGHT_FRACTION = 0.5
#: A highlight this close (in peak brightness) to the sphere's median is not a highlight.
MIN_CONTRAST = 0.05


def sphere_normals(size: tuple[int, int], centre: tuple[float, float], radius: float) -> tuple[Tensor, Tensor]:
    """Normals (3, H, W) of a sphere seen from above (+y up: rows grow with −y) and the mask
    (H, W) of pixels whose centres lie inside ``INNER`` of its radius."""
    h, w = size
    cx, cy = centre
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    nx = (xs - cx) / radius
    ny = -(ys - cy) / radius
    r2 = nx * nx + ny * ny
    mask = r2 < INNER * INNER
    nz = (1 - r2).clamp_min(0).sqrt()
    return torch.stack([nx, ny, nz]), mask


def highlight_direction(image: Tensor, centre: tuple[float, float], radius: float, where: str = "photo") -> Tensor:
    """The light direction (3,) shown by the highlight on the sphere in a linear image
    (H, W) or (C, H, W) (module doc)."""
    grey = image.double().mean(0) if image.ndim == 3 else image.double()
    normals, mask = sphere_normals(tuple(grey.shape), centre, radius)
    if int(mask.sum()) < 9:
        raise MatscanError(f"{where}: the sphere ({centre[0]:g}, {centre[1]:g}, r {radius:g}) is not inside the photo")
    inside = grey[mask]
    floor = float(inside.median())
    peak = float(inside.max())
    if peak - floor < MIN_CONTRAST * max(peak, 1e-12):
        raise MatscanError(f"{where}: no highlight on the sphere (is the sphere where --sphere says?)")
    flat = torch.where(mask, grey, torch.full_like(grey, -math.inf))
    row, col = divmod(int(flat.argmax()), grey.shape[1])
    # the highlight: the connected bright region holding the peak (a saturated highlight is
    # a plateau, and the first maximum lies on its edge)
    level = floor + HIGHLIGHT_FRACTION * (peak - floor)
    bright = ((grey > level) & mask).numpy().astype(np.uint8)
    _, labels = cv2.connectedComponents(bright, connectivity=8)
    region = torch.from_numpy(labels == labels[row, col])
    weights = (grey - level).clamp_min(0) * region
    n = (normals * weights).sum(dim=(1, 2))
    n = n / n.norm()
    light = 2 * n[2] * n - torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype)
    return (light / light.norm()).float()


def directions_from_sphere(
    photos: Sequence[str | Path], centre: tuple[float, float], radius: float, encoding: str = "srgb"
) -> list[tuple[float, float, float]]:
    """Light directions (matscan's frame) from the sphere's highlight in each photo."""
    if not (radius > 0 and math.isfinite(radius)):
        raise MatscanError(f"--sphere: radius {radius!r} must be a positive number of pixels")
    out = []
    for path in photos:
        data = read_image(path)
        px = torch.from_numpy(np.ascontiguousarray(data.pixels)).permute(2, 0, 1)[:3]
        linear = srgb_to_linear(px) if data.kind == "int" and encoding == "srgb" else px
        d = highlight_direction(linear, centre, radius, str(path))
        if float(d[2]) <= 0:
            raise input_error(path, "the highlight is at the sphere's outline: the light is at or below the horizon")
        out.append((float(d[0]), float(d[1]), float(d[2])))
    return out
