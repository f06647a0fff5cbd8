"""Capture → maps: network inference at any size, then refinement by inverse rendering.

1. **Check** the capture: saturated fraction per photo, lights missing from the
   rig's full set; each becomes a warning that says what to do.
2. **Networks** (:func:`predict_maps`): the photos go into their rig-light slots
   with presence planes (any subset of lights); images larger than ``tile`` are
   processed in overlapping tiles blended with linear ramps, and the global-skip
   averages are computed over the whole image first (summed over tiles), so
   memory is bounded by the tile size.
3. **Refinement** (:func:`refine_maps`): per-pixel maps, initialised from the
   networks, are fitted to the photos through the differentiable renderer (L1 in
   log space, saturated pixels masked), with a prior term holding each map near
   the networks' where the photos say little, and a light smoothness term. A
   capture whose light intensity is not calibrated (the ``flash`` rig) gets one
   intensity scale fitted with the maps. Work is done in pixel tiles, so memory
   stays bounded at any size.

``reconstruct`` writes the maps (design.md conventions) and ``matscan.json``
(rig, inputs, model, conventions, timings, mm per pixel, version).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from matscan import __version__
from matscan.atomic import atomic_folder
from matscan.capture import Capture, load_capture
from matscan.errors import MatscanError
from matscan.mapset import CONVENTIONS, MapSet, normalize_normals, write_maps
from matscan.nets import MapNets, network_input
from matscan.render import flat_albedo, flat_irradiance, render, surface_points
from matscan.rig import LightSet

LOG_EPS = 0.01


@dataclass(frozen=True)
class ReconstructConfig:
    """How a capture is reconstructed."""

    model: str = "default"
    refine: str = "auto"  # "auto": on from REFINE_AUTO_PHOTOS photos, or without networks; "on"; "off"
    refine_steps: int = 150
    refine_lr: float = 0.02
    prior_weight: float = 0.05
    smooth_weight: float = 0.01
    tile: int = 512
    overlap: int = 64
    refine_tile: int = 128
    saturation_warn: float = 0.05
    emissive: bool = False  # also fit an emissive map (light the sample gives off under any LED)
    validate: int = 0  # leave this many photos out, reconstruct, and report their re-rendering error
    exr: bool = False  # also write every map as float EXR under exr/
    directx_normals: bool = False  # also write normal_directx.png


#: ``--refine auto`` refines captures with at least this many photos. Measured in
#: docs/results.md (11 materials, Table 4 subsets): from 10 photos up refinement lowers
#: every error of the networks' maps but specular's (a tie) and halves the re-rendering
#: error under novel lights; with 1–3 it raises nearly all of them, and with 6 it trades
#: 1.7° → 5.1° normal error for better diffuse and roughness.
REFINE_AUTO_PHOTOS = 10


@dataclass
class Result:
    maps: MapSet
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    intensity_scale: float = 1.0
    refine_history: list[float] = field(default_factory=list)


def check_capture(capture: Capture, cfg: ReconstructConfig) -> list[str]:
    """Warnings about a capture, each saying what to do."""
    warnings = []
    for file, sat in zip(capture.files, capture.saturated, strict=True):
        frac = float(sat.float().mean())
        if frac > cfg.saturation_warn:
            warnings.append(
                f"{file}: {frac:.1%} of pixels saturated; lower the exposure (they are left out of the fit)"
            )
    if not capture.rig.per_image_geometry:
        missing = sorted(set(range(len(capture.rig.lights))) - {k for k in capture.light_indices if k is not None})
        if missing:
            warnings.append(
                f"lights {', '.join(map(str, missing))} of rig {capture.rig.name} are missing; "
                "reconstructing from the other photos"
            )
    return warnings


# --- networks ----------------------------------------------------------------------------


def _slots(capture: Capture, n_lights: int, r0: int, c0: int, th: int, tw: int) -> tuple[Tensor, Tensor]:
    """A tile of the photos in their rig-light slots (1, L, 3, th, tw), and the presence (1, L)."""
    photos = torch.zeros(1, n_lights, 3, th, tw)
    present = torch.zeros(1, n_lights)
    for img, k in zip(capture.images, capture.light_indices, strict=True):
        photos[0, k] = img[:, r0 : r0 + th, c0 : c0 + tw]
        present[0, k] = 1
    return photos, present


def _ramp(n: int, overlap: int, first: bool, last: bool) -> Tensor:
    w = torch.ones(n)
    if overlap > 0:
        r = (torch.arange(overlap, dtype=torch.float32) + 0.5) / overlap
        if not first:
            w[:overlap] = r
        if not last:
            w[-overlap:] = r.flip(0)
    return w


def _starts(size: int, tile: int, overlap: int) -> list[int]:
    if size <= tile:
        return [0]
    step = tile - overlap
    starts = list(range(0, size - tile, step)) + [size - tile]
    return sorted(set(starts))


@torch.no_grad()
def predict_maps(nets: MapNets, capture: Capture, tile: int = 512, overlap: int = 64, progress: bool = False) -> MapSet:
    """The networks' maps for a capture of any size (see module doc, step 2)."""
    if capture.rig.per_image_geometry:
        raise MatscanError(
            f"rig {capture.rig.name!r}: the networks are trained for fixed-light rigs; "
            "use --refine on with --model none"
        )
    if nets.n_lights != len(capture.rig.lights):
        raise MatscanError(
            f"model: trained for {nets.n_lights} lights, but rig {capture.rig.name!r} has {len(capture.rig.lights)}"
        )
    nets.eval()
    h, w = capture.size
    m = nets.multiple
    tile = max(m, tile // m * m)
    overlap = min(overlap, tile // 2)
    full = torch.tensor([[h, w]])

    def encoded(r0: int, c0: int, th: int, tw: int) -> Tensor:
        photos, present = _slots(capture, nets.n_lights, r0, c0, th, tw)
        return network_input(
            photos,
            present,
            torch.tensor([[r0, c0]]),
            full,
            capture.rig,
            capture.field_mm,
        )

    rows, cols = _starts(h, tile, overlap), _starts(w, tile, overlap)
    pooled = None
    if len(rows) * len(cols) > 1:  # global averages over the whole image, from non-overlapping tiles
        totals: dict[str, list[Tensor]] = {}
        for r0 in range(0, h, tile):
            for c0 in range(0, w, tile):
                th, tw = min(tile, h - r0), min(tile, w - c0)
                for name, sums in nets.encoder_sums(encoded(r0, c0, th, tw)).items():
                    acc = totals.setdefault(name, [torch.zeros_like(s) for s in sums])
                    for a, s in zip(acc, sums, strict=True):
                        a += s
        pooled = {}
        for name, sums in totals.items():
            levels = []
            for i, s in enumerate(sums):
                count = math.ceil(h / 2**i) * math.ceil(w / 2**i)
                levels.append(s / count)
            pooled[name] = levels

    out = {
        name: torch.zeros(1, c, h, w)
        for name, c in (("diffuse", 3), ("specular", 3), ("roughness", 1), ("normal", 3))
        if name in nets.maps
    }
    weight = torch.zeros(1, 1, h, w)
    tiles = [(r, c) for r in rows for c in cols]
    for r0, c0 in tqdm(tiles, desc="networks", unit="tile", disable=not progress or len(tiles) == 1, leave=False):
        th, tw = min(tile, h - r0), min(tile, w - c0)
        pred = nets(encoded(r0, c0, th, tw), pooled)
        wr = _ramp(th, overlap, r0 == 0, r0 + th >= h)
        wc = _ramp(tw, overlap, c0 == 0, c0 + tw >= w)
        wt = (wr[:, None] * wc[None, :])[None, None]
        for name, t in pred.items():
            out[name][..., r0 : r0 + th, c0 : c0 + tw] += t * wt
        weight[..., r0 : r0 + th, c0 : c0 + tw] += wt
    maps = {name: (t / weight)[0] for name, t in out.items()}
    maps["normal"] = normalize_normals(maps["normal"])
    maps["diffuse"] = maps["diffuse"].clamp(0, 1)
    maps["specular"] = maps["specular"].clamp(0, 1)
    maps["roughness"] = maps["roughness"].clamp(0, 1)
    return MapSet(**maps)


def flat_start(capture: Capture) -> MapSet:
    """Maps to start refinement from without networks: albedo from photo ÷ flat
    irradiance (:func:`matscan.render.flat_albedo`), flat normal, roughness 0.5,
    specular 0.04."""
    h, w = capture.size
    e = flat_irradiance(capture.lights, surface_points(capture.field_mm, (h, w)))
    rho = flat_albedo(capture.images, e)
    normal = torch.zeros(3, h, w)
    normal[2] = 1
    return MapSet(rho, torch.full((3, h, w), 0.04), torch.full((1, h, w), 0.5), normal)


# --- refinement -----------------------------------------------------------------------------


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
    photos = capture.images[used]
    valid = (~capture.saturated[used]).float()
    if fit_intensity is None:
        fit_intensity = capture.rig.per_image_geometry
    points_all = surface_points(capture.field_mm, (h, w))
    scale = torch.zeros(())  # log intensity scale
    if fit_intensity:  # one global scale, from the starting maps
        scale = _fit_scale(start, photos, valid, lights, points_all)
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
        target = torch.log(LOG_EPS + photos[..., r0 : r0 + th, c0 : c0 + tw])
        mask = valid[..., r0 : r0 + th, c0 : c0 + tw]
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


def _fit_scale(
    start: MapSet, photos: Tensor, valid: Tensor, lights: LightSet, points: Tensor, steps: int = 150, size: int = 48
) -> Tensor:
    """Log intensity scale k of an uncalibrated capture.

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
    h, w = photos.shape[-2:]
    factor = max(1, max(h, w) // size)
    if factor > 1:
        photos = F.avg_pool2d(photos, factor)
        valid = (F.avg_pool2d(valid, factor) > 0.999).float()
        points = F.avg_pool2d(points.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)
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


def rerender_error(maps: MapSet, capture: Capture, positions: list[int], scale: float = 1.0) -> float:
    """RMSE between photos (at these capture positions) and renderings of ``maps``,
    over unsaturated pixels."""
    lights = capture.lights.select(positions)
    pts = surface_points(capture.field_mm, capture.size)
    with torch.no_grad():
        img = render(maps.diffuse, maps.specular, maps.roughness, maps.normal, lights, pts) * scale
    valid = ~capture.saturated[positions].expand_as(img)
    diff = (img.clamp(0, 1) - capture.images[positions])[valid]
    return float(diff.square().mean().sqrt())


# --- special materials (paper §4.5) ------------------------------------------------------------


def alpha_from_backlight(backlight: dict[str, Tensor]) -> Tensor:
    """Alpha by triangulation matting (Smith & Blinn 1996; the paper's Eq. 12).

    With the sample over the green and the blue stage, C_k = F + (1 − α) B_k, and the
    empty stage photographed as B_k: C_g − C_b = (1 − α)(B_g − B_b), solved for
    (1 − α) in least squares over RGB. Returns (1, H, W) in [0, 1].
    """
    missing = [k for k in ("green", "blue", "green_empty", "blue_empty") if k not in backlight]
    if missing:
        raise MatscanError(f"backlight: alpha needs the {', '.join(missing)} photo(s)")
    dc = backlight["green"] - backlight["blue"]
    db = backlight["green_empty"] - backlight["blue_empty"]
    transparency = (dc * db).sum(0, keepdim=True) / (db * db).sum(0, keepdim=True).clamp_min(1e-6)
    return (1 - transparency).clamp(0, 1)


def height_from_normals(normal: Tensor, mm_per_px: tuple[float, float]) -> Tensor:
    """Height (1, H, W) in mm, zero mean, integrated from unit normals (3, H, W).

    Frankot & Chellappa 1988: the least-squares surface whose gradient best matches
    (∂h/∂x, ∂h/∂y) = (−n_x/n_z, −n_y/n_z), found in the Fourier domain (periodic
    boundary). x grows with columns, y with −rows (design.md).
    """
    nz = normal[2].clamp_min(0.05)
    p = -normal[0] / nz  # ∂h/∂x, per mm
    q = -normal[1] / nz  # ∂h/∂y
    h, w = p.shape
    dx, dy = mm_per_px
    # in pixel steps along columns (j) and rows (i): ∂h/∂j = p·dx, ∂h/∂i = −q·dy
    gj, gi = p * dx, -q * dy
    wj = 2 * math.pi * torch.fft.fftfreq(w, dtype=torch.float64)[None, :]
    wi = 2 * math.pi * torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    gj_f = torch.fft.fft2(gj.double())
    gi_f = torch.fft.fft2(gi.double())
    denom = wj**2 + wi**2
    denom[0, 0] = 1
    hf = (-1j * wj * gj_f - 1j * wi * gi_f) / denom
    hf[0, 0] = 0
    return torch.fft.ifft2(hf).real.float()[None]


# --- the whole job -----------------------------------------------------------------------------


def reconstruct_capture(
    capture: Capture, cfg: ReconstructConfig = ReconstructConfig(), nets: MapNets | None = None, progress: bool = False
) -> Result:
    """Maps from a loaded capture (no files written)."""
    timings: dict[str, float] = {}
    warnings = check_capture(capture, cfg)
    t0 = time.perf_counter()
    if nets is not None and not capture.rig.per_image_geometry:
        start = predict_maps(nets, capture, cfg.tile, cfg.overlap, progress)
    else:
        if nets is not None:
            warnings.append(
                f"rig {capture.rig.name}: the networks do not apply to per-image geometry; "
                "starting refinement from flat maps"
            )
        start = flat_start(capture)
    timings["networks_s"] = time.perf_counter() - t0
    used_nets = nets is not None and not capture.rig.per_image_geometry
    refine = cfg.refine == "on" or (
        cfg.refine == "auto" and (not used_nets or len(capture.files) >= REFINE_AUTO_PHOTOS)
    )
    if cfg.refine not in ("auto", "on", "off"):
        raise MatscanError(f"--refine: {cfg.refine!r} is not one of auto, on, off")
    result = Result(start, warnings, timings)
    if refine:
        t0 = time.perf_counter()
        maps, scale, hist = refine_maps(
            start,
            capture,
            cfg.refine_steps,
            cfg.refine_lr,
            cfg.prior_weight,
            cfg.smooth_weight,
            cfg.refine_tile,
            emissive=cfg.emissive,
            progress=progress,
        )
        timings["refine_s"] = time.perf_counter() - t0
        result.maps, result.intensity_scale, result.refine_history = maps, scale, hist
    elif cfg.emissive:
        warnings.append("--emissive needs refinement; no emissive map was fitted")
    result.maps = with_special_maps(result.maps, capture, warnings)
    return result


def with_special_maps(maps: MapSet, capture: Capture, warnings: list[str]) -> MapSet:
    """Add alpha (from backlight photos, when the capture has them), height (from the
    normals) and the metal/rough workflow (basecolor, metallic)."""
    from matscan.brdf import specular_to_metallic

    extra = {}
    if capture.backlight:
        try:
            extra["alpha"] = alpha_from_backlight(capture.backlight)
        except MatscanError as exc:
            warnings.append(f"{exc}; no alpha map")
    extra["height"] = height_from_normals(maps.normal, capture.mm_per_pixel)
    extra["basecolor"], extra["metallic"] = specular_to_metallic(maps.diffuse, maps.specular)
    present = maps.present()
    present.update(extra)
    return MapSet(**present)


def subset_capture(capture: Capture, positions: list[int]) -> Capture:
    """The same capture with only some of its photos (positions in its image list)."""
    from dataclasses import replace

    return replace(
        capture,
        images=capture.images[positions],
        saturated=capture.saturated[positions],
        light_indices=tuple(capture.light_indices[i] for i in positions),
        lights=capture.lights.select(positions),
        files=tuple(capture.files[i] for i in positions),
    )


def leave_out_validation(capture: Capture, count: int, cfg: ReconstructConfig, nets: MapNets | None) -> dict:
    """Self-validation without ground truth: reconstruct without ``count`` photos
    (spread evenly over the capture) and measure the re-rendering RMSE on them."""
    n = len(capture.files)
    if not 1 <= count <= n - 1:
        raise MatscanError(f"--validate: {count} must be between 1 and {n - 1} (the capture has {n} photos)")
    left = sorted({round((i + 0.5) * n / count - 0.5) for i in range(count)})
    kept = [i for i in range(n) if i not in left]
    res = reconstruct_capture(subset_capture(capture, kept), cfg, nets)
    return {
        "left_out": [capture.files[i] for i in left],
        "rmse_left_out": rerender_error(res.maps, capture, left, res.intensity_scale),
        "rmse_fitted": rerender_error(res.maps, capture, kept, res.intensity_scale),
    }


def reconstruct(
    capture_path: str | Path,
    out: str | Path,
    cfg: ReconstructConfig = ReconstructConfig(),
    overwrite: bool = False,
    progress: bool = False,
) -> dict[str, Any]:
    """``matscan reconstruct``: read a capture, write maps and ``matscan.json``; return the record."""
    t_all = time.perf_counter()
    from matscan.calibrate import apply_calibration

    capture = apply_calibration(load_capture(capture_path))
    nets, model_name, networks = None, "none", {}
    if cfg.model != "none":
        from matscan.train import training_record
        from matscan.weights import load_model, model_path

        nets, model_meta = load_model(cfg.model)
        model_name, networks = str(model_path(cfg.model)), training_record(model_meta)
    validation = leave_out_validation(capture, cfg.validate, cfg, nets) if cfg.validate else None
    res = reconstruct_capture(capture, cfg, nets, progress)
    positions = list(range(len(capture.files)))
    error = rerender_error(res.maps, capture, positions, res.intensity_scale)
    h, w = capture.size
    record = {
        "format": "matscan-reconstruction/1",
        "matscan_version": __version__,
        "capture": str(Path(capture_path)),
        "rig": capture.rig.name,
        "inputs": [{"file": f, "light": k} for f, k in zip(capture.files, capture.light_indices, strict=True)],
        "size_px": [w, h],
        "field_mm": list(capture.field_mm),
        "mm_per_pixel": list(capture.mm_per_pixel),
        "model": {"name": cfg.model, "file": model_name, "networks": networks},
        "config": asdict(cfg),
        "refined": bool(res.refine_history),
        "intensity_scale": res.intensity_scale,
        "rerender_rmse": error,
        "warnings": res.warnings,
        "conventions": CONVENTIONS,
        "timings_s": {k: round(v, 3) for k, v in res.timings.items()},
    }
    if validation is not None:
        record["validation"] = validation
    with atomic_folder(out, overwrite=overwrite) as tmp:
        write_maps(tmp, res.maps)
        from matscan.export import export_all

        record["exports"] = export_all(tmp, res.maps, capture.field_mm, cfg.exr, cfg.directx_normals)
        from matscan.report.html import write_report

        write_report(tmp / "report.html", capture, res.maps, record, res.intensity_scale)
        record["timings_s"]["total_s"] = round(time.perf_counter() - t_all, 3)
        (tmp / "matscan.json").write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return record
