"""Differentiable rendering of material maps under point lights.

Image formation (shared/design.md), for a surface point p, light k at q_k with
intensity I_k, LED axis a_k and exponent m_k, camera centre c and the rig's
reference distance R:

    l = normalize(q_k − p),  v = normalize(c − p),  d = |q_k − p|
    pixel = π · I_k · (R/d)² · max(a_k·(−l), 0)^m_k · f_r(v, l) · max(n·l, 0)

with f_r the paper's Eq. 1 (:mod:`matscan.brdf`). The renderer evaluates it as
π·E·(ρ/π·(n·l) + D·G·F/(4 n·v)) where n·l > 0 and n·v > 0, which is the same
expression with the (n·l) factor cancelled, and stable at grazing angles.

Shapes: maps are (B, C, H, W) or (C, H, W); surface points (B, H, W, 3) or
(H, W, 3) in mm; a :class:`~matscan.rig.LightSet` holds L lights, or (B, L) for
different lights per batch element. The result is (B, L, 3, H, W), or (L, 3, H, W)
when nothing was batched: linear radiance, float32 or float64 as the inputs.

Without gradients the work is done in chunks of pixels written into one output
tensor, so memory is the output plus a bounded working set (3072² and beyond).
With gradients, chunks are concatenated and autograd keeps what it needs.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from matscan.brdf import fresnel_schlick, ggx_alpha, ggx_distribution, smith_g
from matscan.errors import MatscanError
from matscan.rig import LightSet, Rig

if TYPE_CHECKING:
    from matscan.mapset import MapSet

#: Light-pixels evaluated at once when chunking (bounds the working set to ~100 MB).
DEFAULT_CHUNK = 1 << 19


def surface_points(
    field_mm: Sequence[float],
    size: tuple[int, int],
    offset: tuple[int, int] = (0, 0),
    full_size: tuple[int, int] | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """World positions (mm) of pixel centres on the sample plane z = 0.

    A map of ``full_size`` = (H, W) pixels covers ``field_mm`` = (width, height);
    pixel (i, j) has its centre at x = (j + 0.5)/W·width − width/2,
    y = height/2 − (i + 0.5)/H·height (design.md, "Frames and units").
    ``size`` and ``offset`` select a crop of that grid (rows, cols), so a crop is
    rendered at its true place in the field. Returns (h, w, 3).
    """
    h, w = size
    full_h, full_w = full_size if full_size is not None else size
    width, height = float(field_mm[0]), float(field_mm[1])
    rows = torch.arange(offset[0], offset[0] + h, dtype=torch.float64)
    cols = torch.arange(offset[1], offset[1] + w, dtype=torch.float64)
    x = (cols + 0.5) / full_w * width - width / 2
    y = height / 2 - (rows + 0.5) / full_h * height
    pts = torch.stack([x.expand(h, w), y[:, None].expand(h, w), torch.zeros(h, w, dtype=torch.float64)], dim=-1)
    return pts.to(dtype)


def _batched(t: Tensor, ndim: int) -> Tensor:
    return t if t.ndim == ndim else t.unsqueeze(0)


def _check(name: str, t: Tensor, channels: int) -> None:
    if t.ndim not in (3, 4) or t.shape[-3] != channels:
        raise MatscanError(f"render: {name} must be ({channels}, H, W) or (B, {channels}, H, W), got {tuple(t.shape)}")


def render(
    diffuse: Tensor,
    specular: Tensor,
    roughness: Tensor,
    normal: Tensor,
    lights: LightSet,
    points: Tensor,
    chunk: int = DEFAULT_CHUNK,
    compile: bool | None = None,
) -> Tensor:
    """Render maps under lights (design.md, "Image formation").

    Args:
        diffuse: ρ, (B, 3, H, W) linear [0, 1].
        specular: F0, (B, 3, H, W) linear [0, 1].
        roughness: r, (B, 1, H, W) [0, 1].
        normal: unit normals, (B, 3, H, W), tangent frame = world frame for a flat sample.
        lights: L lights (or B×L), positions in mm in the sample frame.
        points: surface points (B, H, W, 3) or (H, W, 3), mm (:func:`surface_points`).
        chunk: light-pixels per chunk when no gradient is needed.
        compile: use the torch.compile'd kernel (no-gradient path only); by default
            for jobs of at least ``COMPILE_MIN`` light-pixels. Falls back to eager.

    Returns:
        (B, L, 3, H, W) linear radiance; (L, 3, H, W) if no input was batched.
    """
    for name, t, c in (
        ("diffuse", diffuse, 3),
        ("specular", specular, 3),
        ("roughness", roughness, 1),
        ("normal", normal, 3),
    ):
        _check(name, t, c)
    unbatched = diffuse.ndim == 3 and points.ndim == 3 and lights.position.ndim == 2
    rho, f0, r, n = (_batched(t, 4) for t in (diffuse, specular, roughness, normal))
    hw = rho.shape[-2:]
    for name, t in (("specular", f0), ("roughness", r), ("normal", n)):
        if t.shape[-2:] != hw:
            raise MatscanError(f"render: {name} is {tuple(t.shape[-2:])} pixels but diffuse is {tuple(hw)}")
    if points.shape[-3:-1] != hw or points.shape[-1] != 3:
        raise MatscanError(f"render: points must be (H, W, 3) = {(*hw, 3)}, got {tuple(points.shape)}")
    pts = _batched(points, 4)
    batch = max(rho.shape[0], f0.shape[0], r.shape[0], n.shape[0], pts.shape[0])
    if lights.position.ndim == 3:
        batch = max(batch, lights.position.shape[0])
    dtype = rho.dtype
    height, width = hw
    npix = height * width

    # Flattened, component-wise layout: pixel quantities (B, C, P), per-light ones (B, L, k).
    rho_f, f0_f, r_f, n_f = (t.reshape(t.shape[0], t.shape[1], npix) for t in (rho, f0, r, n))
    pts_f = pts.to(dtype).reshape(pts.shape[0], npix, 3).transpose(1, 2)

    def per_light(t: Tensor) -> Tensor:
        t = t.to(dtype)
        return t if t.ndim == 3 else t.unsqueeze(0)

    # homogeneous points (x, y, z, w): w = 0 for directional lights and orthographic cameras
    q = per_light(torch.cat([lights.position, lights.w.unsqueeze(-1)], -1))
    intensity = per_light(lights.intensity)
    axis = per_light(lights.axis)
    exponent = per_light(lights.exponent.unsqueeze(-1))[..., 0]
    cam = per_light(torch.cat([lights.camera, lights.camera_w.unsqueeze(-1)], -1))
    if bool((cam == cam[:, :1]).all()):
        cam = cam[:, :1]  # one camera for every image: view directions are per pixel only
    scale = float(lights.reference_distance_mm) ** 2
    n_lights = q.shape[1]
    light_args = (q, intensity, axis, exponent, cam)

    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (rho, f0, r, n, pts, lights.position, lights.intensity)
    )
    step = max(1, chunk // max(1, batch * n_lights))
    starts = range(0, npix, step)
    if needs_grad:
        parts = [
            _shade(
                rho_f[..., s : s + step],
                f0_f[..., s : s + step],
                r_f[..., s : s + step],
                n_f[..., s : s + step],
                pts_f[..., s : s + step],
                *light_args,
                scale,
            )
            for s in starts
        ]
        out = torch.cat(parts, dim=-1).expand(batch, n_lights, 3, npix)
    else:
        use_compiled = compile if compile is not None else batch * n_lights * npix >= COMPILE_MIN
        shade = _compiled_shade() if use_compiled else None
        out = torch.empty(batch, n_lights, 3, npix, dtype=dtype, device=rho.device)
        for s in starts:
            e = min(s + step, npix)
            pix = [t[..., s:e] for t in (rho_f, f0_f, r_f, n_f, pts_f)]
            if shade is not None:  # one shape and layout for every chunk: pad the last one
                pix = [_standard(torch.nn.functional.pad(t, (0, step - (e - s)), value=1.0)) for t in pix]
            out[..., s:e] = _run(shade, *pix, *light_args, scale)[..., : e - s]
    out = out.reshape(batch, n_lights, 3, height, width)
    return out[0] if unbatched else out


def led_lobe(cosine: Tensor, exponent: Tensor) -> Tensor:
    """An LED's lobe, max(a·(−l), 0)^m (design.md), from the cosine a·(−l) between its
    axis and the direction to the point: 0 behind the LED (for m above 0; an isotropic
    emitter, m = 0, lights every way, as 0^0 = 1). The base is kept above 1e-30 where it
    is used, so the power's gradient stays finite (a clamp alone left (1e-30)^m behind the
    LED: 0.5 of the light at m = 0.01)."""
    lit = cosine.clamp_min(1e-30) ** exponent
    behind = (exponent == 0).to(lit.dtype)
    return torch.where(cosine > 0, lit, behind)


def _shade(
    rho: Tensor,
    f0: Tensor,
    r: Tensor,
    n: Tensor,
    p: Tensor,
    q: Tensor,
    intensity: Tensor,
    axis: Tensor,
    exponent: Tensor,
    cam: Tensor,
    scale: float,
) -> Tensor:
    """Radiance of P pixels under L lights, component by component.

    Pixel inputs are (B, C, P), light inputs (B, L, k); returns (B, L, 3, P). ``q`` and
    ``cam`` are homogeneous points (B, L, 4): the vector toward them is xyz − w·p.
    Written with scalar planes (x, y, z separately) so that every operation is
    elementwise over (B, L, P), which is what lets torch.compile fuse it into one
    vectorised loop.
    """
    px, py, pz = (p[:, i].unsqueeze(1) for i in range(3))  # (B, 1, P)
    nx, ny, nz = (n[:, i].unsqueeze(1) for i in range(3))

    def comp(t: Tensor, i: int) -> Tensor:  # (B, L, 3) -> (B, L, 1)
        return t[..., i : i + 1]

    qw, cw = comp(q, 3), comp(cam, 3)
    lx, ly, lz = comp(q, 0) - qw * px, comp(q, 1) - qw * py, comp(q, 2) - qw * pz  # (B, L, P)
    d2 = lx * lx + ly * ly + lz * lz
    inv = torch.rsqrt(d2)
    lx, ly, lz = lx * inv, ly * inv, lz * inv
    vx, vy, vz = comp(cam, 0) - cw * px, comp(cam, 1) - cw * py, comp(cam, 2) - cw * pz
    inv = torch.rsqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx * inv, vy * inv, vz * inv
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    inv_h = torch.rsqrt((hx * hx + hy * hy + hz * hz).clamp_min(1e-20))
    n_l = nx * lx + ny * ly + nz * lz
    n_v = nx * vx + ny * vy + nz * vz
    n_h = ((nx * hx + ny * hy + nz * hz) * inv_h).clamp_min(0)
    v_h = ((vx * hx + vy * hy + vz * hz) * inv_h).clamp(0, 1)
    lobe = led_lobe(-(comp(axis, 0) * lx + comp(axis, 1) * ly + comp(axis, 2) * lz), exponent.unsqueeze(-1))
    irradiance = (scale / d2) * lobe  # π·I·(R/d)²·lobe / π, without I
    alpha = ggx_alpha(r[:, 0].unsqueeze(1))
    n_l_c = n_l.clamp_min(1e-7)
    n_v_c = n_v.clamp_min(1e-7)
    # D·G·F/(4 n·l n·v) · n·l · π, with F applied per channel below
    spec = ggx_distribution(n_h, alpha) * smith_g(n_l_c, n_v_c, alpha) * (math.pi / 4) / n_v_c
    spec = torch.where((n_l > 0) & (n_v > 0), spec, torch.zeros((), dtype=spec.dtype))
    n_l_pos = n_l.clamp_min(0)
    channels = [
        comp(intensity, c)
        * irradiance
        * (rho[:, c].unsqueeze(1) * n_l_pos + spec * fresnel_schlick(f0[:, c].unsqueeze(1), v_h))
        for c in range(3)
    ]
    return torch.stack(channels, dim=2)


#: Light-pixels from which rendering without gradients uses the compiled kernel by default.
COMPILE_MIN = 1 << 22
_COMPILED: list = []


def _compiled_shade():
    """torch.compile of :func:`_shade` (fused, vectorised C++), or None where it cannot be built."""
    if not _COMPILED:
        try:
            _COMPILED.append(torch.compile(_shade))
        except Exception:  # no compiler back-end on this platform
            _COMPILED.append(None)
    return _COMPILED[0]


def _standard(t: Tensor) -> Tensor:
    """A copy with standard contiguous strides (also on size-1 dimensions, which
    torch.compile's guards compare)."""
    return torch.empty(t.shape, dtype=t.dtype, device=t.device).copy_(t)


def _run(shade, *args):
    if shade is not None:
        try:
            return shade(*args)
        except Exception as exc:  # a failed compilation falls back to eager, once, with a warning
            warnings.warn(f"render: compiled kernel unavailable ({type(exc).__name__}); using eager mode", stacklevel=3)
            _COMPILED[0] = None
    return _shade(*args)


def render_maps(
    maps: MapSet,
    lights: LightSet,
    field_mm: Sequence[float],
    scale: float = 1.0,
    rows: tuple[int, int] | None = None,
    compile: bool | None = None,
    points: Tensor | None = None,
    emission: float = 1.0,
) -> Tensor:
    """A map set as the camera sees it under each light: (L, 3, H, W) linear radiance.

    The four reflectance maps are rendered (:func:`render`, design.md "Image
    formation") over the field they cover, then

        image = (scale · rendering + emission · emissive) · alpha

    the emissive map (light the sample gives off, linear RGB) added and alpha
    (coverage; 0 shows a black stage) multiplied, each where the map set has it.
    The CLI's ``render``, the report, the solvers' error and the training data all
    render through this function.

    Args:
        maps: (C, H, W) maps (:class:`~matscan.mapset.MapSet`), covering the whole field.
        lights: L lights, positions in mm in the sample frame (design.md, "Frames and units").
        field_mm: (width, height) in mm the maps cover.
        scale: factor on the reflected light (a fitted intensity scale), not on emission.
        rows: (start, stop) renders only those rows, at their place in the field.
        compile: as for :func:`render`.
        points: (H, W, 3) surface points of the maps' pixels, mm, where they are a crop
            of the field rather than all of it (:func:`surface_points` with an offset);
            ``field_mm`` and ``rows`` are then not used.
        emission: factor on the emissive map (a camera's exposure scales it with the rest).

    Returns:
        (L, 3, H, W) linear radiance in the maps' dtype (``rows``: (L, 3, stop − start, W)).
        Not clamped: highlights may exceed 1.
    """
    height, width = maps.size
    start, stop = rows if rows is not None and points is None else (0, height)
    if not 0 <= start < stop <= height:
        raise MatscanError(f"render_maps: rows {(start, stop)} are not a band of the {height} rows of the maps")
    band = slice(start, stop)
    if points is None:
        points = surface_points(field_mm, (stop - start, width), (start, 0), (height, width), maps.diffuse.dtype)
    img = render(
        maps.diffuse[:, band],
        maps.specular[:, band],
        maps.roughness[:, band],
        maps.normal[:, band],
        lights,
        points,
        compile=compile,
    )
    if scale != 1.0:
        img = img * scale
    if maps.emissive is not None:
        img = img + (maps.emissive[:, band] * emission if emission != 1.0 else maps.emissive[:, band])
    if maps.alpha is not None:
        img = img * maps.alpha[:, band]
    return img


def light_vectors(lights: LightSet, points: Tensor) -> tuple[Tensor, Tensor]:
    """Unit directions (L, H, W, 3) toward each light from points (H, W, 3), and the
    squared distances (L, H, W) (design.md: a directional light's vector is its direction
    at the reference distance, whatever the point)."""
    lv = lights.position[:, None, None, :] - lights.w[:, None, None, None] * points[None]  # (L, H, W, 3)
    d2 = (lv * lv).sum(-1)
    return lv / d2.sqrt()[..., None], d2


def flat_irradiance(lights: LightSet, points: Tensor) -> Tensor:
    """I_k (R/d)² max(a_k·(−l), 0)^m_k max(n·l, 0) at points (H, W, 3) of a flat surface
    (n = +z): (L, 3, H, W). A Lambertian pixel of albedo ρ images to ρ times this."""
    l_dir, d2 = light_vectors(lights, points)
    lobe = (-(l_dir * lights.axis[:, None, None, :]).sum(-1)).clamp_min(0) ** lights.exponent[:, None, None]
    e = (lights.reference_distance_mm**2 / d2) * lobe * l_dir[..., 2].clamp_min(0)
    return lights.intensity[:, :, None, None] * e[:, None]


def flat_albedo(photos: Tensor, irradiance: Tensor) -> Tensor:
    """Albedo (3, H, W) in [0, 1] of a flat Lambertian reading of photos (L, 3, H, W)
    whose flat-surface irradiance is given (:func:`flat_irradiance`): per pixel and
    channel, the lower-third order statistic (sorted index ⌊(L − 1)/3⌋) of photo ÷
    irradiance. Highlights only add light, so a low order statistic drops them; the
    lowest would keep shadows and noise. Measured on the fixed validation set (dome24,
    32 materials), albedo RMSE by light count 1/2/3/6/10/16/24: 0.148, 0.096, 0.089,
    0.065, 0.054, 0.053, 0.052; the median gave 0.148, 0.096, 0.202, 0.055, 0.060, 0.055,
    0.052 (with 3 lights two of them sit near the camera and both highlight).
    """
    ratio = photos / irradiance.clamp_min(1e-3)
    k = (ratio.shape[0] - 1) // 3
    return ratio.sort(dim=0).values[k].clamp(0, 1)


def render_rig(
    diffuse: Tensor,
    specular: Tensor,
    roughness: Tensor,
    normal: Tensor,
    rig: Rig,
    indices: Sequence[int] | None = None,
    field_mm: Sequence[float] | None = None,
) -> Tensor:
    """Render full maps (covering the whole field) under some of a rig's lights."""
    hw = diffuse.shape[-2:]
    points = surface_points(field_mm or rig.field_mm, (hw[0], hw[1]), dtype=diffuse.dtype)
    return render(diffuse, specular, roughness, normal, rig.light_set(indices, diffuse.dtype), points)
