"""The solver: maps fitted to the photos by inverse rendering.

Two solvers share the start (the networks' maps, or :func:`flat_start`):
:func:`solve_maps`, the default, a batched second-order fit with closed-form albedos
(:mod:`matscan.reconstruct.lm`, which also gives the confidence maps); and
:func:`refine_maps`, first-order (Adam) descent on a log-space L1, which also fits
an emissive map. The rest of this docstring describes the latter.

Per-pixel maps, initialised from the networks (or from :func:`flat_start`), are
fitted to the photos through the differentiable renderer (L1 in log space,
saturated pixels masked), with a prior term holding each map near its start
where the photos say little, and a light smoothness term. A capture whose light
intensity is not calibrated (the ``flash`` rig) gets one intensity scale fitted
with the maps. Work is done in pixel tiles, so memory stays bounded at any size.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from matscan.capture import Capture
from matscan.mapset import MapSet
from matscan.reconstruct.lm import SolverConfig, reweight_passes, solve, solve_rows
from matscan.render import flat_albedo, flat_irradiance, render, render_maps, surface_points
from matscan.rig import LightSet

LOG_EPS = 0.01


def flat_start(capture: Capture) -> MapSet:
    """Maps to start refinement from without networks: albedo from photo ÷ flat
    irradiance (:func:`matscan.render.flat_albedo`), flat normal, roughness 0.5,
    specular 0.04."""
    h, w = capture.size
    points = surface_points(capture.field_mm, (h, w))
    rho = torch.empty(3, h, w)
    for r0, r1 in capture.strips():
        rho[:, r0:r1] = flat_albedo(capture.linear(rows=(r0, r1)), flat_irradiance(capture.lights, points[r0:r1]))
    normal = torch.zeros(3, h, w)
    normal[2] = 1
    return MapSet(rho, torch.full((3, h, w), 0.04), torch.full((1, h, w), 0.5), normal)


def _to_params(maps: MapSet) -> dict[str, Tensor]:
    n = maps.normal
    nz = n[2:3].clamp_min(0.05)
    return {
        "diffuse": maps.diffuse.clone(),
        "specular": maps.specular.clone(),
        "roughness": maps.roughness.clone(),
        "slope": torch.cat([n[0:1] / nz, n[1:2] / nz]),  # n ∝ (sx, sy, 1)
    }


def _to_maps(p: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    d = p["diffuse"].clamp(0, 1)
    s = p["specular"].clamp(0, 1)
    r = p["roughness"].clamp(0.02, 1)
    sl = p["slope"]
    n = torch.cat([sl, torch.ones_like(sl[:1])], dim=-3)
    n = n / n.norm(dim=-3, keepdim=True)
    return d, s, r, n


def refine_maps(
    start: MapSet,
    capture: Capture,
    steps: int = 150,
    lr: float = 0.02,
    prior_weight: float = 0.05,
    smooth_weight: float = 0.01,
    tile: int = 128,
    fit_intensity: bool | None = None,
    lights_used: list[int] | None = None,
    emissive: bool = False,
    progress: bool = False,
) -> tuple[MapSet, float, list[float]]:
    """Fit per-pixel maps to the photos by inverse rendering (module doc, step 3).

    ``lights_used``: which photos (positions in the capture) to fit; all by default.
    ``emissive``: also fit a per-pixel emission added to every photo (non-negative).
    Returns (maps, intensity scale, mean data loss per step over the first tile).
    """
    h, w = capture.size
    used = list(range(len(capture.files))) if lights_used is None else list(lights_used)
    lights = capture.lights.select(used)
    if fit_intensity is None:
        fit_intensity = capture.rig.per_image_geometry
    points_all = surface_points(capture.field_mm, (h, w))
    scale = torch.zeros(())  # log intensity scale
    if fit_intensity:  # one global scale, from the starting maps
        scale = _fit_scale(*_pooled(capture, used, points_all), lights)
    out = {
        name: t.clone() for name, t in start.present().items() if name in ("diffuse", "specular", "roughness", "normal")
    }
    if emissive:
        out["emissive"] = torch.zeros(3, h, w)
    history: list[float] = []
    tiles = [(r, c) for r in range(0, h, tile) for c in range(0, w, tile)]
    for t_index, (r0, c0) in enumerate(tqdm(tiles, desc="refine", unit="tile", disable=not progress, leave=False)):
        th, tw = min(tile, h - r0), min(tile, w - c0)
        crop = start.crop(r0, c0, th, tw)
        params = _to_params(crop)
        if emissive:
            params["emissive"] = torch.zeros(3, th, tw)
        params = {k: v.requires_grad_() for k, v in params.items()}
        init = {k: v.detach().clone() for k, v in params.items()}
        opt = torch.optim.Adam(params.values(), lr=lr)
        region = {"rows": (r0, r0 + th), "cols": (c0, c0 + tw)}
        target = torch.log(LOG_EPS + capture.linear(used, **region))
        mask = (~capture.saturation(used, **region)).float()
        pts = points_all[r0 : r0 + th, c0 : c0 + tw]
        k = float(scale.exp())
        for _ in range(steps):
            d, s, r, n = _to_maps(params)
            img = render(d, s, r, n, lights, pts) * k
            if emissive:
                img = img + params["emissive"].clamp_min(0)
            data = ((torch.log(LOG_EPS + img) - target).abs() * mask).sum() / mask.sum().clamp_min(1) / 3
            prior = sum(((params[key] - init[key]) ** 2).mean() for key in params)
            smooth = sum(
                (params[key][..., 1:, :] - params[key][..., :-1, :]).abs().mean()
                + (params[key][..., :, 1:] - params[key][..., :, :-1]).abs().mean()
                for key in ("diffuse", "roughness", "specular")
            )
            loss = data + prior_weight * prior + smooth_weight * smooth
            opt.zero_grad()
            loss.backward()
            opt.step()
            if t_index == 0:
                history.append(float(data.detach()))
        d, s, r, n = (t.detach() for t in _to_maps(params))
        for name, t in (("diffuse", d), ("specular", s), ("roughness", r), ("normal", n)):
            out[name][..., r0 : r0 + th, c0 : c0 + tw] = t
        if emissive:
            out["emissive"][..., r0 : r0 + th, c0 : c0 + tw] = params["emissive"].detach().clamp_min(0)
    extra = {k: v for k, v in start.present().items() if k not in out}
    return MapSet(**out, **extra), float(scale.exp()), history


#: The longer side, in pixels, of the image the intensity scale is fitted on.
SCALE_SIZE = 48


def _pooled(capture: Capture, used: list[int], points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Photos ``used`` box-filtered to about :data:`SCALE_SIZE` on the longer side (read a
    band of rows at a time), their valid masks (1 where no pixel in the box is saturated)
    and the surface points (H, W, 3) filtered alike."""
    h, w = capture.size
    factor = max(1, max(h, w) // SCALE_SIZE)
    if factor == 1:
        return capture.linear(used), (~capture.saturation(used)).float(), points
    band = max(factor, capture.strips(len(used))[0][1] // factor * factor)
    photos, valid = [], []
    for r0 in range(0, h // factor * factor, band):
        rows = (r0, min(h // factor * factor, r0 + band))
        photos.append(F.avg_pool2d(capture.linear(used, rows), factor))
        valid.append((F.avg_pool2d((~capture.saturation(used, rows)).float(), factor) > 0.999).float())
    points = F.avg_pool2d(points.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)
    return torch.cat(photos, dim=-2), torch.cat(valid, dim=-2), points


def _fit_scale(photos: Tensor, valid: Tensor, points: Tensor, lights: LightSet, steps: int = 150) -> Tensor:
    """Log intensity scale k of an uncalibrated capture, from small photos (:func:`_pooled`).

    Diffuse light only fixes k·ρ; the highlights fix k, because dielectric F0 is
    known (0.04): on a downsampled image, fit one k and one roughness, with flat
    normals, F0 = 0.04 and the albedo that best explains each pixel given k (the
    median over photos of photo ÷ (k · irradiance) minus the specular part), by
    minimising the log-space L1 over unsaturated pixels (robust to the few metal
    pixels that break the F0 assumption). Dielectric F0 spans about 0.03–0.05, so
    the scale is known to about ±25% — when the highlights are not saturated (they
    are masked, and with them goes what fixes the scale). A calibrated capture
    needs none of this.
    """
    hh, ww = photos.shape[-2:]
    normal = torch.zeros(3, hh, ww)
    normal[2] = 1
    f0 = torch.full((3, hh, ww), 0.04)
    irr = flat_irradiance(lights, points)
    log_k = torch.zeros((), requires_grad=True)
    rough = torch.zeros((), requires_grad=True)  # logit of roughness
    opt = torch.optim.Adam([log_k, rough], lr=0.05)
    target = torch.log(LOG_EPS + photos)
    for _ in range(steps):
        k = log_k.exp()
        r = torch.sigmoid(rough).expand(1, hh, ww)
        spec = render(torch.zeros(3, hh, ww), f0, r, normal, lights, points)
        rho = ((photos / k - spec) / irr.clamp_min(1e-3)).median(dim=0).values.clamp(0, 1).detach()
        img = k * render(rho, f0, r, normal, lights, points)
        loss = ((torch.log(LOG_EPS + img) - target).abs() * valid).sum() / valid.sum().clamp_min(1)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return log_k.detach()


#: Albedo values pinned at 1 (of the diffuse and specular maps fitted on the small image)
#: above which an intensity scale is taken to be too small.
PINNED = 0.002
#: How much the scale grows each time it is found too small.
SCALE_STEP = 1.5


def _scale_floor(
    photos: Tensor,
    valid: Tensor,
    points: Tensor,
    lights: LightSet,
    scale: float,
    start: MapSet,
    cfg: SolverConfig,
    strength: float,
    tries: int = 8,
) -> float:
    """The intensity scale raised until the maps fitted to the small photos (:func:`_pooled`)
    stay inside [0, 1].

    Re-rendering is the same for any scale k as long as the albedos can take the photos ÷ k:
    k·(ρ/k) = ρ. So the photos say nothing of k above that bound, but a k below it shows as
    albedos pinned at their upper bound 1, which cannot explain the photos. _fit_scale's
    estimate assumes dielectric highlights (F0 0.04); on a metallic print, whose bright
    highlights are mostly saturated, it came out 5 times too small (0.21 against 1), and
    every held-out photo was then predicted badly. Raising k until nothing is pinned fixes that
    without changing the estimate where the assumption holds.
    """
    hh, ww = photos.shape[-2:]
    pooled = {
        name: F.adaptive_avg_pool2d(getattr(start, name)[None], (hh, ww))[0]
        for name in ("diffuse", "specular", "roughness", "normal")
    }
    normal = pooled["normal"] / pooled["normal"].norm(dim=0, keepdim=True).clamp_min(1e-8)
    small_cfg = SolverConfig(
        iterations=0,
        fine_iterations=cfg.fine_iterations + 4,
        coarse=0,
        tau=cfg.tau,
        tile_pixels=hh * ww,
        # dropped, as when this was chosen: a clipped peak the pooled model cannot reach
        # would pin ρ or F0 at 1, and the search would raise the scale to unpin them
        censored=False,
        more_iterations=0,  # the fixed steps it was chosen with
    )
    for _ in range(tries):
        out, _ = solve(
            photos / scale,
            valid,
            lights,
            points,
            pooled["diffuse"],
            pooled["specular"],
            pooled["roughness"],
            normal,
            small_cfg,
            strength,
        )
        pinned = max(float((out["diffuse"] >= 0.999).float().mean()), float((out["specular"] >= 0.999).float().mean()))
        if pinned <= PINNED:
            break
        scale *= SCALE_STEP
    return scale


def rerender_error(maps: MapSet, capture: Capture, positions: list[int], scale: float = 1.0) -> float:
    """RMSE between photos (at these capture positions) and renderings of ``maps``
    (:func:`~matscan.render.render_maps`: emission and alpha too, as the fit and the
    record's other numbers render them), over unsaturated pixels (a band of rows at a
    time)."""
    lights = capture.lights.select(positions)
    total, count = 0.0, 0
    for rows in capture.strips(len(positions)):
        with torch.no_grad():
            # eager: compiling the fused kernel costs more (3.3 s at 512² × 24) than it saves once
            img = render_maps(maps, lights, capture.field_mm, scale, rows=rows, compile=False)
        img = img.clamp_(0, 1).sub_(capture.linear(positions, rows))
        valid = ~capture.saturation(positions, rows).expand_as(img)
        diff = img[valid]
        total += float(diff.square().sum())
        count += diff.numel()
    return (total / count) ** 0.5 if count else float("nan")


def clips_are_bounds(capture: Capture) -> bool:
    """Whether a saturated value, as read, is a lower bound on the light that reached it
    (what the solver's censored values assume): the photos' gains, exposure ratio and flat
    fields are positive, but a colour matrix with a negative entry mixes a clipped
    channel's missing light into the others with a minus sign, so they may read too
    high. Such captures have their saturated values dropped, as before."""
    matrix = capture.correction.matrix if capture.correction is not None else None
    return matrix is None or bool((matrix >= 0).all())


def solve_maps(
    start: MapSet,
    capture: Capture,
    cfg: SolverConfig | None = None,
    strength: float = 1.0,
    lights_used: list[int] | None = None,
    progress: bool = False,
) -> tuple[MapSet, dict[str, Tensor], float]:
    """Fit maps to the photos with the second-order solver (:mod:`matscan.reconstruct.lm`),
    starting from and held near ``start``.

    ``strength`` scales the prior (1 for the networks' maps, small for a flat start);
    a capture with per-image geometry (``flash``) gets one intensity scale first
    (:func:`_fit_scale`). Returns (maps, confidence per map (1, H, W), intensity scale).
    """
    cfg = cfg or SolverConfig()
    if cfg.censored and not clips_are_bounds(capture):
        cfg = replace(cfg, censored=False)
    h, w = capture.size
    used = list(range(len(capture.files))) if lights_used is None else list(lights_used)
    lights = capture.lights.select(used)
    points = surface_points(capture.field_mm, (h, w))
    scale = 1.0
    if capture.rig.per_image_geometry:
        small, valid_small, points_small = _pooled(capture, used, points)
        scale = float(_fit_scale(small, valid_small, points_small, lights).exp())
        scale = _scale_floor(small, valid_small, points_small, lights, scale, start, cfg, strength)

    def read(r0: int, r1: int) -> tuple[Tensor, Tensor]:
        photos = capture.linear(used, (r0, r1))
        return photos / scale if scale != 1.0 else photos, (~capture.saturation(used, (r0, r1))).float()

    rows = max(1, cfg.tile_pixels // w)
    tiles = math.ceil(h / rows)
    sweeps = 1 + reweight_passes(cfg, len(used))  # at most: the noise decides (lm's module doc)
    with tqdm(total=tiles * sweeps, desc="solve", unit="tile", disable=not progress or tiles == 1, leave=False) as bar:
        out, conf = solve_rows(
            read,
            len(used),
            lights,
            points,
            start.diffuse,
            start.specular,
            start.roughness,
            start.normal,
            cfg,
            strength,
            progress=lambda done: bar.update(done - bar.n),
        )
    extra = {k: v for k, v in start.present().items() if k not in out}
    return MapSet(**out, **extra), conf, scale
