"""Light directions from the highlight on a chrome sphere in the frame (the RTI standard).

A mirror-like sphere photographed from far above (an orthographic view, v = +z) shows
each light as a small highlight where its normal bisects the light and the view:
n = normalize(l + v), so l = 2 (n·v) n − v. Given the camera (:class:`Pinhole`: its angle
of view, and where known its principal point and radial distortion), the view is that
camera's instead (:func:`perspective_sphere`): a sphere off the optical axis
is seen obliquely, v tilts by the angle it lies off the axis, and the orthographic
reading errs by about that much. The sphere's outline in the photos (centre
and radius, in pixels) is given; in each photo the highlight is found as the brightest
spot inside the outline, grown to the connected region brighter than halfway between the
sphere's median and that peak (a saturated highlight is a plateau), and its normal as
the brightness-weighted mean of the sphere's normals over that region (weighted in
normal space, so a highlight near the outline is not pulled by the outline's
foreshortening).

Without ``--sphere`` the outline is found in the photos (:func:`find_sphere`): circles
in the mean of the photos are candidates, a candidate is a chrome sphere only if most
photos show a small highlight inside it where a mirror-like sphere would (nearer its
centre than sin 45° of its radius, for a light above the sample), and the outline is
then fitted to a fraction of a pixel.

Pixel coordinates: x is the column and y the row of a pixel's centre (the values an image
viewer shows), as in ``--sphere CX,CY,R``. The directions are in matscan's frame (+y
toward the image's top), as :mod:`matscan.capture.rti` writes them with ``y="up"``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
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


#: OpenCV's distortion coefficients, in its order.
DISTORTION = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Pinhole:
    """The camera of the photos as a pinhole with OpenCV's lens distortion.

    ``fov_deg``: the angle of view across the photos' width (of the undistorted image),
    which sets the focal length f = (W/2) / tan(fov/2) in pixels; ``principal``: the
    principal point (column, row; pixels), None for the photo's centre; ``k1``, ``k2``,
    ``p1``, ``p2``, ``k3``: distortion as OpenCV's coefficients in its order (what
    ``cv2.calibrateCamera`` returns as ``distCoeffs``): a point (x, y) of the ideal
    pinhole's image, normalised by f in OpenCV's frame (y down), with r² = x² + y², lies in
    the photo at x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²), and y (…) +
    p1 (r² + 2 y²) + 2 p2 x y (k1 < 0: barrel). The camera looks down −z, +y toward the
    image's top."""

    fov_deg: float
    principal: tuple[float, float] | None = None
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.fov_deg, (int, float)) and 0 < self.fov_deg < 180):
            raise MatscanError(f"--fov: {self.fov_deg!r} must be an angle of view between 0 and 180 degrees")
        for name in DISTORTION:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise MatscanError(f"--distortion: {name} = {value!r} must be a finite number")
        if self.principal is not None and not all(math.isfinite(float(v)) for v in self.principal):
            raise MatscanError(f"--principal-point: {self.principal!r} must be two finite numbers of pixels")

    @property
    def distorts(self) -> bool:
        return any(getattr(self, name) != 0 for name in DISTORTION)

    @property
    def tangential(self) -> bool:
        return self.p1 != 0 or self.p2 != 0

    def focal(self, size: tuple[int, int]) -> float:
        return (size[1] / 2) / math.tan(math.radians(self.fov_deg) / 2)

    def centre(self, size: tuple[int, int]) -> tuple[float, float]:
        h, w = size
        return self.principal if self.principal is not None else ((w - 1) / 2, (h - 1) / 2)

    def distort(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """Ideal normalised points (OpenCV's frame, y down) to where the lens puts them."""
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        return (
            x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x),
            y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y,
        )

    def _jacobian(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`distort`'s Jacobian at (x, y): its entries ∂x_d/∂x, ∂x_d/∂y = ∂y_d/∂x and
        ∂y_d/∂y (it is symmetric)."""
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        slope = self.k1 + r2 * (2 * self.k2 + 3 * self.k3 * r2)  # d radial / d r²
        cross = 2 * x * y * slope + 2 * self.p1 * x + 2 * self.p2 * y
        return (
            radial + 2 * x * x * slope + 2 * self.p1 * y + 6 * self.p2 * x,
            cross,
            radial + 2 * y * y * slope + 6 * self.p1 * y + 2 * self.p2 * x,
        )

    def undistort(self, xd: Tensor, yd: Tensor) -> tuple[Tensor, Tensor]:
        """The inverse of :meth:`distort` by Newton's method on both coordinates at once; a
        one-line error where the distortion folds the image over (its Jacobian's
        determinant is not positive there) or no ideal point maps to a photo's point."""
        if not self.distorts:
            return xd, yd
        x, y = xd.clone(), yd.clone()
        for _ in range(50):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            if float(torch.maximum(ex.abs(), ey.abs()).max()) < 1e-14:
                break
            a, b, d = self._jacobian(x, y)
            det = a * d - b * b
            if bool((det <= 0).any()):
                break
            x, y = x - (d * ex - b * ey) / det, y - (a * ey - b * ex) / det
        fx, fy = self.distort(x, y)
        a, b, d = self._jacobian(x, y)
        miss = torch.maximum((fx - xd).abs(), (fy - yd).abs())
        if bool(((a * d - b * b <= 0) | (miss > 1e-7 * (1 + xd.abs() + yd.abs()))).any()):
            raise MatscanError(
                f"--distortion: {self.describe()} folds the image over within the photo (the distortion is not "
                "one-to-one there); check the coefficients' signs, order (k1,k2,p1,p2,k3) and size"
            )
        return x, y

    def describe(self) -> str:
        return ",".join(f"{getattr(self, name):g}" for name in DISTORTION)

    def rays(self, x: Tensor, y: Tensor, size: tuple[int, int]) -> Tensor:
        """Unit rays (3, ...) through pixel positions x (column) and y (row) of the photo:
        each position undistorted (:meth:`undistort`) and seen through the pinhole."""
        f, (cx, cy) = self.focal(size), self.centre(size)
        xu, yu = self.undistort((x - cx) / f, (y - cy) / f)
        d = torch.stack([xu, -yu, -torch.ones_like(xu)])
        return d / d.norm(dim=0, keepdim=True)

    def pixel(self, xu: float, yu: float, size: tuple[int, int]) -> tuple[float, float]:
        """Where the ray (xu, yu, −1) (the ideal pinhole's normalised point, y up) lies in
        the photo: (column, row), distorted."""
        f, (cx, cy) = self.focal(size), self.centre(size)
        xd, yd = self.distort(torch.tensor(xu, dtype=torch.float64), torch.tensor(-yu, dtype=torch.float64))
        return cx + f * float(xd), cy + f * float(yd)


def as_lens(lens: float | Pinhole | None) -> Pinhole | None:
    """A camera given as its angle of view alone (degrees) is a :class:`Pinhole` with the
    principal point at the centre and no distortion."""
    return lens if lens is None or isinstance(lens, Pinhole) else Pinhole(float(lens))


def _pinhole_rays(x: Tensor, y: Tensor, size: tuple[int, int], lens: Pinhole) -> Tensor:
    """Unit rays (3, ...) from the camera through pixel positions x (column) and y (row)."""
    return lens.rays(x, y, size)


def cone_outline(axis: Tensor, half: float, size: tuple[int, int], lens: float | Pinhole) -> tuple[float, float, float]:
    """The outline (centre column, centre row, radius; pixels) that :func:`perspective_sphere`
    reads for a sphere whose tangent cone from the camera has unit ``axis`` and half-angle
    ``half`` (radians): the circle through the silhouette's points nearest and farthest
    from the principal point in the ideal pinhole's image, each put where the lens puts
    it (closed form); :func:`outline_cone` is its inverse."""
    lens = as_lens(lens)
    a = axis.double() / axis.double().norm()
    radial = torch.stack([a[0], a[1]])
    radial = radial / radial.norm() if float(radial.norm()) > 1e-12 else torch.tensor([1.0, 0.0], dtype=torch.float64)
    tilt = math.acos(max(-1.0, min(1.0, -float(a[2]))))
    pts = []
    for t in (tilt - half, tilt + half):  # the cone's edges in the plane of its axis and the optical axis
        r = math.tan(t)
        pts.append(lens.pixel(r * float(radial[0]), r * float(radial[1]), size))
    return (pts[0][0] + pts[1][0]) / 2, (pts[0][1] + pts[1][1]) / 2, math.dist(pts[0], pts[1]) / 2


def outline_cone(
    centre: tuple[float, float], radius: float, size: tuple[int, int], lens: float | Pinhole
) -> tuple[Tensor, float]:
    """The sphere's tangent cone (unit axis (3,), half-angle in radians) whose outline,
    as :func:`cone_outline` gives it, is ``centre`` and ``radius`` (pixels): the rays
    through the circle's points nearest and farthest from the principal point, their
    bisector and half the angle between them. Radial distortion keeps the silhouette's
    two points on that line, so this is exact; tangential distortion moves them off it,
    and the circle is then corrected by what :func:`cone_outline` gives back until the
    two agree (within 1e-9 px)."""
    lens = as_lens(lens)
    target = torch.tensor([*centre, radius], dtype=torch.float64)
    guess = target.clone()
    for _ in range(20):
        c = guess[:2]
        off = c - torch.tensor(lens.centre(size), dtype=torch.float64)
        u = off / off.norm() if float(off.norm()) > 1e-9 else torch.tensor([1.0, 0.0], dtype=torch.float64)
        ends = torch.stack([c - guess[2] * u, c + guess[2] * u])  # (2, 2): x, y
        d1, d2 = _pinhole_rays(ends[:, 0], ends[:, 1], size, lens).T
        axis = (d1 + d2) / (d1 + d2).norm()
        half = math.acos(max(-1.0, min(1.0, float(d1 @ d2)))) / 2
        if not lens.tangential:
            break
        miss = target - torch.tensor(cone_outline(axis, half, size, lens), dtype=torch.float64)
        if float(miss.abs().max()) < 1e-9:
            break
        guess = guess + miss
    return axis, half


def perspective_sphere(
    size: tuple[int, int], centre: tuple[float, float], radius: float, lens: float | Pinhole
) -> tuple[Tensor, Tensor, Tensor]:
    """A sphere seen through a pinhole camera: normals (3, H, W), the unit directions
    toward the camera (3, H, W) and the mask (H, W) of the pixels that see the sphere no
    nearer its rim than ``INNER`` of the orthographic case does (n·v above √(1 − INNER²)).

    The camera (``lens``: a :class:`Pinhole`, or its angle of view across the image's
    width, the principal point then at the centre) looks down −z from the origin with +y
    toward the image's top. The outline (``centre``, ``radius``, pixels) is taken as the circle through the two
    points of the silhouette nearest and farthest from the principal point (a sphere off
    the axis projects to an ellipse stretched along that line): the sphere's axis is the
    bisector of their rays and its angular radius half the angle between them
    (:func:`outline_cone`); the sphere's size is immaterial (radius 1 here)."""
    h, w = size
    lens = as_lens(lens)
    axis, half = outline_cone(centre, radius, size, lens)
    s = axis / math.sin(half)  # the sphere's centre (radius 1) from the camera
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    d = _pinhole_rays(xs, ys, size, lens)  # (3, H, W)
    b = -(d * s.view(3, 1, 1)).sum(0)
    disc = b * b - (float(s @ s) - 1)
    t = -b - disc.clamp_min(0).sqrt()
    normals = t * d - s.view(3, 1, 1)
    views = -d
    mask = (disc > 0) & ((normals * views).sum(0) > math.sqrt(1 - INNER * INNER))
    return normals, views, mask


def highlight_direction(
    image: Tensor,
    centre: tuple[float, float],
    radius: float,
    where: str = "photo",
    lens: float | Pinhole | None = None,
) -> Tensor:
    """The light direction (3,) shown by the highlight on the sphere in a linear image
    (H, W) or (C, H, W) (module doc); with ``lens`` (a :class:`Pinhole`, or its angle of
    view across the width) the photo is that camera's (:func:`perspective_sphere`), else
    orthographic."""
    grey = image.double().mean(0) if image.ndim == 3 else image.double()
    sphere = f"the sphere ({centre[0]:g}, {centre[1]:g}, r {radius:g})"
    check_in_photo(centre, radius, tuple(grey.shape), where, sphere)
    lens = as_lens(lens)
    if lens is None:
        normals, mask = sphere_normals(tuple(grey.shape), centre, radius)
    else:
        normals, views, mask = perspective_sphere(tuple(grey.shape), centre, radius, lens)
    weights = highlight_weights(grey, mask, where, sphere)
    n = (normals * weights).sum(dim=(1, 2))
    n = n / n.norm()
    if lens is None:
        v = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype)
    else:  # the view at the highlight: the weighted mean of the pixels' views there
        v = (views * weights).sum(dim=(1, 2))
        v = v / v.norm()
    light = 2 * (n @ v) * n - v
    return (light / light.norm()).float()


#: How far past the photo's edge a sphere's outline may reach, as a share of its radius
#: (a sphere cut by the frame; its highlights for low lights lie in the part cut off).
OUTSIDE_REACH = 0.25


def check_in_photo(centre: tuple[float, float], radius: float, shape: tuple[int, int], where: str, sphere: str) -> None:
    """Refuse a sphere (centre column and row, radius; pixels) whose centre is outside
    the photo (H, W) or whose outline reaches past its edge by more than
    ``OUTSIDE_REACH`` of the radius: a highlight on a sphere so placed gives a wrong
    direction rather than none (a radius of 1e9 px read every light as overhead)."""
    h, w = shape
    cx, cy = centre
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise MatscanError(f"{where}: {sphere}: its centre lies outside the {w}×{h} photo")
    past = max(radius - cx, cx + radius - w, radius - cy, cy + radius - h)
    if past > OUTSIDE_REACH * radius:
        raise MatscanError(
            f"{where}: {sphere} reaches {past:.0f} px past the {w}×{h} photo's edge, where the highlights of "
            "low lights fall: frame the whole sphere, or check --sphere (centre column, row and radius, pixels)"
        )


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


def _read_linear(path: str | Path, encoding: str) -> Tensor:
    data = read_image(path)
    px = torch.from_numpy(np.ascontiguousarray(data.pixels)).permute(2, 0, 1)[:3]
    return srgb_to_linear(px) if data.kind == "int" and encoding == "srgb" else px.float()


def directions_from_sphere(
    photos: Sequence[str | Path],
    centre: tuple[float, float],
    radius: float,
    encoding: str = "srgb",
    lens: float | Pinhole | None = None,
) -> list[tuple[float, float, float]]:
    """Light directions (matscan's frame) from the sphere's highlight in each photo; with
    ``lens`` (a :class:`Pinhole`, or the camera's angle of view across the photos'
    width) the view is a pinhole camera's, else orthographic."""
    if not (radius > 0 and math.isfinite(radius)):
        raise MatscanError(f"--sphere: radius {radius!r} must be a positive number of pixels")
    lens = as_lens(lens)
    out = []
    for path in photos:
        linear = _read_linear(path, encoding)
        d = highlight_direction(linear, centre, radius, str(path), lens)
        if float(d[2]) <= 0:
            raise input_error(path, "the highlight is at the sphere's outline: the light is at or below the horizon")
        out.append((float(d[0]), float(d[1]), float(d[2])))
    return out


# --- finding the sphere -----------------------------------------------------------------

#: Photos are searched for the sphere at most this many pixels on their longer side (the
#: outline is then fitted on the full-size mean of the photos).
SEARCH_SIDE = 768
#: The smallest sphere looked for, as a share of the photos' shorter side.
MIN_RADIUS_SHARE = 0.03
#: A highlight is the brightest spot on the sphere, at least this many times brighter
#: there than its mean over the photos (it moves with the light), ...
HIGHLIGHT_RATIO = 3.0
#: ... covering at most this share of the sphere (a flat glossy surface's highlight is
#: broad; a mirror-like sphere's is a small spot) ...
HIGHLIGHT_AREA = 0.04
#: ... at most this far from the centre, as a share of the radius: a mirror-like sphere
#: seen from above shows a light above the horizon within sin 45° of its radius (at
#: R·sin(θ/2), θ the light's angle from the view), with some allowance.
HIGHLIGHT_REACH = 0.8
#: A candidate is a chrome sphere when this share of the photos show such a highlight.
HIGHLIGHT_PHOTOS = 0.5
#: The outline is fitted from the steepest step of the mean image along this many rays.
OUTLINE_RAYS = 720


def find_sphere(
    photos: Sequence[str | Path] | Tensor,
    encoding: str = "srgb",
    where: str = "photos",
    lens: float | Pinhole | None = None,
) -> tuple[float, float, float]:
    """The outline (centre column, centre row, radius; pixels) of a mirror-like sphere
    seen in photos of one scene under different lights: file paths, or linear images
    (N, C, H, W). Raises a one-line error when no candidate passes (module doc). With
    ``lens`` (a :class:`Pinhole`, or its angle of view) the outline is fitted as that
    camera sees a sphere (an ellipse, :func:`perspective_sphere`) and given as that
    function reads it."""
    lens = as_lens(lens)
    n = len(photos)
    if n < 3:
        raise MatscanError(f"{where}: finding the sphere needs three photos or more; give --sphere CX,CY,R")
    mean: Tensor | None = None
    small = []
    for i in range(n):
        img = photos[i] if isinstance(photos, Tensor) else _read_linear(photos[i], encoding)
        grey = img.double().mean(0)
        if mean is not None and grey.shape != mean.shape:
            names = ("photo 0", f"photo {i}") if isinstance(photos, Tensor) else (photos[0], photos[i])
            raise MatscanError(
                f"{where}: the photos differ in size ({names[1]}: {grey.shape[1]}×{grey.shape[0]} px, "
                f"{names[0]}: {mean.shape[1]}×{mean.shape[0]})"
            )
        mean = grey / n if mean is None else mean + grey / n
        h, w = grey.shape
        factor = max(1, math.ceil(max(h, w) / SEARCH_SIDE))
        small.append(torch.nn.functional.avg_pool2d(grey[None, None], factor, ceil_mode=True)[0, 0].float())
    assert mean is not None
    stack = torch.stack(small)  # (N, h, w), every photo reduced by ``factor``
    candidates = _circle_candidates(stack.mean(0))
    if not candidates:
        raise MatscanError(f"{where}: no round outline found; give the sphere's place with --sphere CX,CY,R")
    best = None
    for cx, cy, r in candidates:
        share = _highlight_share(stack, (cx, cy), r)
        if share >= HIGHLIGHT_PHOTOS and (best is None or share > best[0]):
            best = (share, cx, cy, r)
    if best is None:
        raise MatscanError(
            f"{where}: no chrome sphere found (no round outline with a small highlight inside it in most "
            "photos); give its place with --sphere CX,CY,R"
        )
    _, cx, cy, r = best
    # from reduced pixels (block means) to the full-size pixel grid: centre x' = (x + 0.5)·f − 0.5
    centre = ((cx + 0.5) * factor - 0.5, (cy + 0.5) * factor - 0.5)
    return _fit_outline(mean, centre, r * factor, where, lens)


def _circle_candidates(mean: Tensor, most: int = 24) -> list[tuple[float, float, float]]:
    """Circles (x, y, r; pixels) in an image: OpenCV's Hough transform in its two forms,
    the one that ranks circles by how round their edges are (which finds a small sphere
    beside a large round motif) first, then the one that ranks them by votes."""
    top = float(torch.quantile(mean.flatten()[:: max(1, mean.numel() // 100_000)].float(), 0.99))
    img = (mean / max(top, 1e-12) * 255).clamp(0, 255).to(torch.uint8).numpy()
    img = cv2.GaussianBlur(img, (5, 5), 1.0)
    side = min(img.shape)
    low, high = max(4, round(MIN_RADIUS_SHARE * side)), side // 2
    found = []
    for method, dp, param1, param2 in ((cv2.HOUGH_GRADIENT_ALT, 1.5, 100, 0.7), (cv2.HOUGH_GRADIENT, 1, 60, 20)):
        circles = cv2.HoughCircles(
            img, method, dp=dp, minDist=max(2.0, low), param1=param1, param2=param2, minRadius=low, maxRadius=high
        )
        if circles is not None:
            found += [(float(x), float(y), float(r)) for x, y, r in circles[0][: most // 2]]
    return found


def _highlight_share(stack: Tensor, centre: tuple[float, float], radius: float) -> float:
    """The share of photos (N, h, w) showing a small highlight inside the circle where a
    mirror-like sphere shows a light above the horizon: the brightest spot inside it
    (grown as :func:`highlight_weights` grows it) is small, within ``HIGHLIGHT_REACH`` of
    the centre, and ``HIGHLIGHT_RATIO`` times that place's mean over the photos (it
    moves with the light)."""
    n, h, w = stack.shape
    ys = torch.arange(h, dtype=torch.float32)[:, None]
    xs = torch.arange(w, dtype=torch.float32)[None, :]
    r2 = ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / radius**2
    disc = r2 < INNER**2
    if int(disc.sum()) < 9:
        return 0.0
    mean = stack.mean(0)
    hits = 0
    for i in range(n):
        inside = torch.where(disc, stack[i], torch.full_like(stack[i], -math.inf))
        row, col = divmod(int(inside.argmax()), w)
        peak, floor = float(inside[row, col]), float(stack[i][disc].median())
        if peak - floor < MIN_CONTRAST * max(peak, 1e-12) or float(r2[row, col]) > HIGHLIGHT_REACH**2:
            continue
        bright = (disc & (stack[i] > floor + HIGHLIGHT_FRACTION * (peak - floor))).numpy().astype(np.uint8)
        _, labels = cv2.connectedComponents(bright, connectivity=8)
        spot = torch.from_numpy(labels == labels[row, col])
        if int(spot.sum()) > HIGHLIGHT_AREA * int(disc.sum()):
            continue
        hits += float(stack[i][spot].mean()) >= HIGHLIGHT_RATIO * float(mean[spot].mean())
    return hits / n


def _fit_outline(
    mean: Tensor, centre: tuple[float, float], radius: float, where: str, lens: Pinhole | None = None
) -> tuple[float, float, float]:
    """The circle through the steepest step of ``mean`` along rays from an approximate
    centre (within ±15% of the radius), fitted by least squares with outlying rays
    dropped; twice, from the first fit's centre. With ``lens``, the sphere's tangent
    cone through those points instead (:func:`_cone_lsq`), given as :func:`cone_outline`."""
    h, w = mean.shape
    img = mean.float()[None, None]
    angles = torch.arange(OUTLINE_RAYS, dtype=torch.float64) * (2 * math.pi / OUTLINE_RAYS)
    cx, cy, r = centre[0], centre[1], radius
    for _ in range(3):
        steps = torch.linspace(0.85, 1.15, 121, dtype=torch.float64) * r
        x = cx + steps[None, :] * angles.cos()[:, None]  # (rays, steps)
        y = cy + steps[None, :] * angles.sin()[:, None]
        grid = torch.stack([(x + 0.5) / w * 2 - 1, (y + 0.5) / h * 2 - 1], dim=-1).float()[None]
        prof = torch.nn.functional.grid_sample(img, grid, align_corners=False, padding_mode="border")[0, 0].double()
        ok = ((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)).all(1)
        d = prof[:, 2:] - prof[:, :-2]  # central differences at steps 1 .. len − 2
        sign = 1.0 if float(d[ok].sum(1).median()) >= 0 else -1.0
        d = d * sign
        j = d.argmax(1)
        jj = j.clamp(1, d.shape[1] - 2)
        a, b, c = d.gather(1, (jj - 1)[:, None]), d.gather(1, jj[:, None]), d.gather(1, (jj + 1)[:, None])
        denom = (a - 2 * b + c).squeeze(1)
        offset = torch.where(denom < 0, 0.5 * (a - c).squeeze(1) / denom, torch.zeros_like(denom)).clamp(-1, 1)
        pos = jj.double() + 1 + offset  # index into ``steps``
        rad = steps[0] + pos * (steps[1] - steps[0])
        px, py = cx + rad * angles.cos(), cy + rad * angles.sin()
        keep = ok & (j > 0) & (j < d.shape[1] - 1) & (b.squeeze(1) > 0)
        for _ in range(3):
            if int(keep.sum()) < OUTLINE_RAYS // 4:
                raise MatscanError(f"{where}: the sphere's outline is too faint to fit; give --sphere CX,CY,R")
            if lens is None:
                cx, cy, r = _circle_lsq(px[keep], py[keep])
                resid = ((px - cx) ** 2 + (py - cy) ** 2).sqrt() - r
            else:
                cx, cy, r, resid = _cone_lsq(px, py, keep, (h, w), lens)
            spread = float(resid[keep].abs().median()) * 1.4826 + 0.05
            keep = keep & (resid.abs() < 3 * spread)
    if not (0 <= cx < w and 0 <= cy < h):
        raise MatscanError(f"{where}: the sphere's fitted centre lies outside the photos; give --sphere CX,CY,R")
    return float(cx), float(cy), float(r)


def _circle_lsq(x: Tensor, y: Tensor) -> tuple[float, float, float]:
    """The circle through points in the algebraic least-squares sense (Kåsa): x² + y² =
    2ax + 2by + c, radius √(c + a² + b²)."""
    design = torch.stack([2 * x, 2 * y, torch.ones_like(x)], dim=1)
    a, b, c = torch.linalg.lstsq(design, x * x + y * y).solution.tolist()
    return a, b, math.sqrt(max(c + a * a + b * b, 0.0))


def _cone_lsq(
    x: Tensor, y: Tensor, keep: Tensor, size: tuple[int, int], lens: Pinhole
) -> tuple[float, float, float, Tensor]:
    """The cone of rays tangent to a sphere, through outline points seen by a pinhole
    camera: every ray d on it makes the same angle α with the axis a, d · a/cos α = 1,
    linear in q = a / cos α (least squares over the ``keep`` points). Returns the
    :func:`cone_outline` circle and each point's residual, in pixels (its angle from the
    cone times the focal length)."""
    d = _pinhole_rays(x, y, size, lens).T  # (N, 3)
    q = torch.linalg.lstsq(d[keep], torch.ones(int(keep.sum()), 1, dtype=d.dtype)).solution[:, 0]
    axis, half = q / q.norm(), math.acos(min(1.0, 1 / float(q.norm())))
    resid = ((d @ axis).clamp(-1, 1).acos() - half) * lens.focal(size)
    return (*cone_outline(axis, half, size, lens), resid)


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


def shell_point(origin: Tensor, direction: Tensor, centre: Sequence[float], radius: float) -> Tensor | None:
    """Where a ray from inside a sphere (``centre``, ``radius``; mm) leaves it, None where
    the ray starts outside it."""
    oc = origin - torch.tensor(centre, dtype=torch.float64)
    b = float(direction @ oc)
    c = float(oc @ oc) - radius * radius
    if c >= 0:
        return None
    return origin + (-b + math.sqrt(b * b - c)) * direction


def light_position_from_spheres(
    image: Tensor,
    field_mm,
    camera_mm,
    spheres: Sequence[tuple[Sequence[float], float]],
    where: str = "photo",
    dome: tuple[Sequence[float], float] | None = None,
) -> tuple[tuple[float, float, float], float]:
    """A near light's position (mm) from its highlights on mirror-like spheres whose
    centres (mm) and radii (mm) are known, and the spread of the evidence (mm). Without
    ``dome``: two spheres or more, the point nearest to the rays the highlights send back
    (:func:`highlight_ray`) and the rays' mean distance from it. With ``dome`` (the
    centre and radius, mm, of the shell the lights are mounted on): one sphere or more,
    the mean of the points where the rays meet the shell and their mean distance from it
    (0 with one sphere)."""
    if not spheres or (dome is None and len(spheres) < 2):
        raise MatscanError(
            "--sphere: a light's position needs two spheres or more (one gives only its direction), "
            "or one with --dome-radius (the lights on a shell of known radius)"
        )
    rays = [highlight_ray(image, field_mm, camera_mm, c, r, where) for c, r in spheres]
    if dome is None:
        x, spread = nearest_point(rays)
    else:
        points = []
        for (o, d), (c, _) in zip(rays, spheres, strict=True):
            hit = shell_point(o, d, *dome)
            if hit is None:
                raise MatscanError(
                    f"--dome-radius: the sphere at {list(c)} mm lies outside the dome of radius {dome[1]:g} mm "
                    f"about {list(dome[0])} mm"
                )
            points.append(hit)
        x = torch.stack(points).mean(0)
        spread = sum(float((p - x).norm()) for p in points) / len(points)
    return (float(x[0]), float(x[1]), float(x[2])), spread


def rig_from_spheres(
    capture, spheres: Sequence[tuple[Sequence[float], float]], dome: tuple[Sequence[float], float] | None = None
):
    """The capture's rig with each photographed light moved to where its highlights on the
    spheres place it (:func:`light_position_from_spheres`, with the lights on the shell
    ``dome`` when given); lights not photographed keep their place. Returns the rig and
    each moved light's spread (mm)."""
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
            capture.linear([i])[0],
            capture.field_mm,
            rig.camera.position_mm,
            spheres,
            str(capture.folder / capture.files[i]) if capture.folder is not None else capture.files[i],
            dome,
        )
        lights[k] = dataclasses.replace(lights[k], position_mm=pos)
        spreads[k] = spread
    return dataclasses.replace(rig, lights=tuple(lights)), spreads
