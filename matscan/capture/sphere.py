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
    sphere = f"the sphere ({centre[0]:g}, {centre[1]:g}, r {radius:g})"
    weights = highlight_weights(grey, mask, where, sphere)
    n = (normals * weights).sum(dim=(1, 2))
    n = n / n.norm()
    light = 2 * n[2] * n - torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype)
    return (light / light.norm()).float()


def highlight_weights(grey: Tensor, mask: Tensor, where: str, sphere: str) -> Tensor:
    """Weights (H, W) of a highlight's pixels among those of ``mask`` (the sphere's usable
    part) in a grey image: the connected region brighter than halfway between the
    sphere's median and its peak that holds the peak (a saturated highlight is a plateau,
    and its first maximum lies on its edge), each pixel by how far it rises above that."""
    if int(mask.sum()) < 9:
        raise MatscanError(f"{where}: {sphere} is not inside the photo")
    inside = grey[mask]
    floor, peak = float(inside.median()), float(inside.max())
    if peak - floor < MIN_CONTRAST * max(peak, 1e-12):
        raise MatscanError(f"{where}: no highlight on {sphere} (is the sphere where --sphere says?)")
    flat = torch.where(mask, grey, torch.full_like(grey, -math.inf))
    row, col = divmod(int(flat.argmax()), grey.shape[1])
    level = floor + HIGHLIGHT_FRACTION * (peak - floor)
    bright = ((grey > level) & mask).numpy().astype(np.uint8)
    _, labels = cv2.connectedComponents(bright, connectivity=8)
    region = torch.from_numpy(labels == labels[row, col])
    return (grey - level).clamp_min(0) * region


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


# --- near lights: positions from two (or more) spheres at known places ---------------------


def _sphere_hits(size, field_mm, camera_mm, centre, radius):
    """Where the camera's rays through each pixel first meet a sphere: points (H, W, 3),
    normals (H, W, 3) and a mask (H, W), for images rectified to the sample field (a pixel
    sees along the ray from the camera centre through its point on the plane z = 0)."""
    from matscan.render import surface_points

    q = surface_points(field_mm, size, dtype=torch.float64)
    c = torch.tensor(camera_mm, dtype=torch.float64)
    s = torch.tensor(centre, dtype=torch.float64)
    d = q - c
    d = d / d.norm(dim=-1, keepdim=True)
    oc = c - s
    b = (d * oc).sum(-1)
    disc = b * b - ((oc * oc).sum() - radius * radius)
    t = -b - disc.clamp_min(0).sqrt()
    p = c + t[..., None] * d
    n = (p - s) / radius
    return p, n, disc > 0


def highlight_ray(
    image: Tensor, field_mm, camera_mm, centre, radius: float, where: str = "photo"
) -> tuple[Tensor, Tensor]:
    """The ray (origin, unit direction) toward a point light from its highlight on a
    mirror-like sphere (``centre`` in mm, ``radius`` in mm) in a linear image (C, H, W)
    rectified to the field: each pixel's camera ray is met with the sphere, the
    highlight's normal is the brightness-weighted mean of the normals there, and the ray
    leaves the sphere's point with that normal along the view mirrored about it."""
    grey = image.double().mean(0) if image.ndim == 3 else image.double()
    p, n, hit = _sphere_hits(tuple(grey.shape), field_mm, camera_mm, centre, radius)
    c = torch.tensor(camera_mm, dtype=torch.float64)
    v = c - p
    v = v / v.norm(dim=-1, keepdim=True)
    facing = hit & ((n * v).sum(-1) > 0.2)  # not the rim, where normals graze the view
    # the highlight's normal, weighted in normal space (its lobe is round there, while on
    # the image a near light stretches it), then the view mirrored about it at that point
    w = highlight_weights(grey, facing, where, f"the sphere at {list(centre)} mm")[..., None]
    normal = (n * w).sum((0, 1))
    normal = normal / normal.norm()
    origin = torch.tensor(centre, dtype=torch.float64) + radius * normal
    view = c - origin
    view = view / view.norm()
    direction = 2 * (normal @ view) * normal - view
    return origin, direction / direction.norm()


def nearest_point(rays: Sequence[tuple[Tensor, Tensor]]) -> tuple[Tensor, float]:
    """The point nearest to two or more rays in the least-squares sense, and its mean
    distance to them (mm)."""
    eye = torch.eye(3, dtype=torch.float64)
    a = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for o, d in rays:
        m = eye - torch.outer(d, d)
        a += m
        b += m @ o
    x = torch.linalg.solve(a, b)
    spread = sum(float(((eye - torch.outer(d, d)) @ (x - o)).norm()) for o, d in rays) / len(rays)
    return x, spread


def light_position_from_spheres(
    image: Tensor, field_mm, camera_mm, spheres: Sequence[tuple[Sequence[float], float]], where: str = "photo"
) -> tuple[tuple[float, float, float], float]:
    """A near light's position (mm) from its highlights on two or more mirror-like spheres
    whose centres (mm) and radii (mm) are known: the point nearest to the rays the
    highlights send back (:func:`highlight_ray`), and the rays' mean distance from it."""
    if len(spheres) < 2:
        raise MatscanError("--sphere: a light's position needs two spheres or more (one gives only its direction)")
    rays = [highlight_ray(image, field_mm, camera_mm, c, r, where) for c, r in spheres]
    x, spread = nearest_point(rays)
    return (float(x[0]), float(x[1]), float(x[2])), spread


def rig_from_spheres(capture, spheres: Sequence[tuple[Sequence[float], float]]):
    """The capture's rig with each photographed light moved to where its highlights on the
    spheres place it (:func:`light_position_from_spheres`); lights not photographed keep
    their place. Returns the rig and each moved light's ray spread (mm)."""
    import dataclasses

    rig = capture.rig
    if rig.per_image_geometry or rig.camera.orthographic:
        raise MatscanError(f"rig {rig.name}: light positions need a fixed rig with a camera centre")
    lights = list(rig.lights)
    spreads = {}
    for i, k in enumerate(capture.light_indices):
        if k is None or lights[k].directional:
            continue
        pos, spread = light_position_from_spheres(
            capture.linear([i])[0], capture.field_mm, rig.camera.position_mm, spheres, capture.files[i]
        )
        lights[k] = dataclasses.replace(lights[k], position_mm=pos)
        spreads[k] = spread
    return dataclasses.replace(rig, lights=tuple(lights)), spreads
