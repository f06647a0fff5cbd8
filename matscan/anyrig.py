"""One network for any rig: photos pooled with their light geometry.

The dome24 networks (:mod:`matscan.nets`) read fixed light slots. This network reads
each photo on its own, with what the rig says about it at every pixel, and pools over
the photos (as Deschaintre et al. 2019 pool their inputs), so it takes any number, any
order and any geometry of lights: domes of 8 to 100 lights, directional or near, and
flashes.

Per photo and pixel (10 channels, :func:`photo_input`): the photo divided by the
irradiance a flat surface gets there from its light, log-encoded (3); the unit direction
toward the light (3) and toward the camera (3); and the log of the light's falloff
(R/d)² (1). A shared encoder turns each photo into features at three scales; max and
mean over the photos at each scale (:func:`pool`) feed a U-Net decoder that gives the
four maps. Training draws a rig at random for every sample (:func:`random_lights`) and
renders procedural materials through it with the project's renderer and camera model.

With ``AnyRigConfig(ps_skip=True)`` (the default; ``train-anyrig --no-ps-skip`` for the
first version without it) the decoder also gets
what the photos say about each pixel directly: a per-pixel Lambertian photometric-stereo
solve (:func:`ps_estimate`: ridge-regularised, reweighted against highlights and shadows,
streamed over photos), and predicts the normals and albedo as corrections to it, the
paper's global skip with a physical estimate in place of the input photo.

``matscan train-anyrig --out RUN`` trains it (resumable; CUDA when there is one);
weights are safetensors. With ``TrainAnyRig.ema`` the checkpoint also keeps an
exponential moving average of the weights (``ema.`` + each name), which :func:`load`
uses: a few hundred steps move the raw weights' scores on unseen rigs by up to 44%, and
the average scored better than the raw weights, in the mean over each dome's light
counts, at every checkpoint measured (runs/anyrig-ema-cpu/README.md). This is a first,
small version: docs/rti.md says what it scores.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from matscan.errors import MatscanError, input_error
from matscan.mapset import MapSet
from matscan.nets import IRRADIANCE_FLOOR, LOG_SCALE, OUT_CHANNELS
from matscan.render import flat_irradiance
from matscan.rig import LightSet

IN_CHANNELS = 10
MULTIPLE = 4  # image sizes are padded to a multiple of this
PS_CHANNELS = 7  # the photometric-stereo skip's channels (:func:`ps_estimate`)
PS_RIDGE = 0.01  # pull of the per-pixel solve toward a flat normal, in photos' worth
PS_SHADOW = 0.01  # a value this dark counts half (attached and cast shadows)
PS_RESIDUAL = 0.1  # residuals this far (× albedo) from the last round's fit count half
PS_ROUNDS = 3  # one least-squares solve, then two reweighted by its residuals
PS_MAX_SLOPE = 3.0  # the skip's normals are kept within atan 3 = 72° of the vertical


def photo_input(photo: Tensor, lights: LightSet, points: Tensor) -> Tensor:
    """The 10 input channels (10, H, W) of one photo (3, H, W, linear) under one light
    (``lights`` of length 1) at surface points (H, W, 3) in mm."""
    irr = flat_irradiance(lights, points)[0]
    ratio = photo / irr.clamp_min(IRRADIANCE_FLOOR)
    log = torch.log1p(ratio.clamp_min(0) * LOG_SCALE) / math.log1p(LOG_SCALE)
    p = points.permute(2, 0, 1)  # (3, H, W)
    q, w = lights.position[0].view(3, 1, 1), lights.w[0]
    lv = q - w * p
    d2 = (lv * lv).sum(0, keepdim=True)
    l = lv * torch.rsqrt(d2)
    c, cw = lights.camera[0].view(3, 1, 1), lights.camera_w[0]
    vv = c - cw * p
    v = vv * torch.rsqrt((vv * vv).sum(0, keepdim=True))
    falloff = torch.log(lights.reference_distance_mm**2 / d2) / 4  # 0 at distance R; about ±0.5 over a dome
    return torch.cat([log, l, v, falloff]).to(photo.dtype)


def ps_terms(x: Tensor, b: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One photo's part of the per-pixel photometric-stereo solve, from its inputs
    (B, ≥6, H, W) (:func:`photo_input`'s first 6 channels): for a Lambertian pixel of
    albedo ρ and normal n, y = ratio · l_z = ρ (n · l), linear in b = ρ n. Dark values
    (shadows) count little; given the previous round's solve ``b`` (B, H, W, 3, 3), so
    do values far from its prediction (highlights, cast shadows): a Cauchy weight of
    the residual on a scale of ``PS_RESIDUAL`` of the pixel's albedo. Returns the weighted
    normal matrix w l lᵀ (B, H, W, 3, 3), right-hand sides w l yᵀ (B, H, W, 3, 3: one
    column per colour channel), the weight w (B, 1, H, W) and w · ratio (B, 3, H, W);
    sums over photos of these are all :func:`ps_solve` needs."""
    ratio = torch.expm1(x[:, :3].float().clamp_min(0) * math.log1p(LOG_SCALE)) / LOG_SCALE
    l = x[:, 3:6].float()
    y = ratio * l[:, 2:3]
    grey = y.mean(1, keepdim=True).clamp_min(0)
    w = grey / (grey + PS_SHADOW)
    lp = l.permute(0, 2, 3, 1)  # (B, H, W, 3)
    if b is not None:
        bg = b.mean(-1)  # (B, H, W, 3)
        residual = grey[:, 0] - (lp * bg).sum(-1)
        scale = PS_RESIDUAL * bg.norm(dim=-1) + PS_SHADOW
        w = w / (1 + (residual / scale).square())[:, None]
    wl = w.permute(0, 2, 3, 1) * lp
    a = wl[..., :, None] * lp[..., None, :]
    rhs = wl[..., :, None] * y.permute(0, 2, 3, 1)[..., None, :]
    return a, rhs, w, w * ratio


def ps_solve(a: Tensor, rhs: Tensor, w: Tensor, wratio: Tensor) -> Tensor:
    """b = ρ n per pixel and colour channel (B, H, W, 3, 3) from summed :func:`ps_terms`: a
    ridge solve pulled toward a flat pixel of the photos' mean ratio (``PS_RIDGE``)."""
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    flat = (wratio / w.clamp_min(1e-6)).permute(0, 2, 3, 1)  # (B, H, W, 3)
    prior = torch.zeros_like(rhs)
    prior[..., 2, :] = flat
    return torch.linalg.solve(a + PS_RIDGE * eye, rhs + PS_RIDGE * prior)


def ps_estimate(photos: Callable[[], Iterable[tuple[Tensor, Tensor | None]]]) -> tuple[Tensor, Tensor, Tensor]:
    """The photometric-stereo estimate: ``PS_ROUNDS`` rounds of :func:`ps_solve`, each
    reweighting by the last (iteratively reweighted least squares). ``photos()`` yields
    (inputs (B, ≥6, H, W), presence (B,) or None) once per photo, afresh each round.

    Returns the normal's slopes (B, 2, H, W: n_x/n_z, n_y/n_z, within ``PS_MAX_SLOPE``; the
    grey channel's direction), the albedo (B, 3, H, W: each channel's b · n, in [0, 2]) and
    the ``PS_CHANNELS`` network inputs: slopes / PS_MAX_SLOPE, log-encoded albedo, the
    solve's conditioning (smallest eigenvalue of the normal matrix, log-encoded) and the
    photos' weight (log-encoded)."""
    b = None
    for _ in range(PS_ROUNDS):
        sums: list[Tensor] | None = None
        for x, present in photos():
            terms = ps_terms(x, b)
            if present is not None:
                keep = [present.view(-1, *[1] * (t.dim() - 1)) > 0 for t in terms]
                terms = tuple(torch.where(k, t, torch.zeros_like(t)) for k, t in zip(keep, terms, strict=True))
            sums = list(terms) if sums is None else [s + t for s, t in zip(sums, terms, strict=True)]
        if sums is None:
            raise MatscanError("anyrig: no photos")
        b = ps_solve(*sums)
    a, _, w, _ = sums
    grey = b.mean(-1)
    n = grey / grey.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    albedo = (b * n[..., None]).sum(-2).clamp(0, 2).permute(0, 3, 1, 2)
    slope = (n[..., :2] / n[..., 2:].clamp_min(1 / PS_MAX_SLOPE)).clamp(-PS_MAX_SLOPE, PS_MAX_SLOPE)
    slope = slope.permute(0, 3, 1, 2)
    low = torch.linalg.eigvalsh(a)[..., 0].clamp_min(0)[:, None]  # (B, 1, H, W)
    code = torch.cat(
        [
            slope / PS_MAX_SLOPE,
            torch.log1p(albedo * LOG_SCALE) / math.log1p(LOG_SCALE),
            torch.log1p(10 * low) / math.log1p(10),
            torch.log1p(w) / math.log1p(12),
        ],
        1,
    )
    return slope, albedo, code


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, 1), nn.LeakyReLU(0.2), nn.Conv2d(cout, cout, 3, 1, 1), nn.LeakyReLU(0.2)
    )


def pool(features: Tensor, present: Tensor) -> Tensor:
    """Max and mean over the photo dimension of (B, K, C, H, W) features, absent photos
    (``present`` (B, K) = 0) left out: (B, 2C, H, W)."""
    mask = present.view(*present.shape, 1, 1, 1).to(features.dtype)
    top = torch.where(mask > 0, features, torch.full_like(features, -1e4)).amax(dim=1)
    mean = (features * mask).sum(1) / mask.sum(1).clamp_min(1)
    return torch.cat([top, mean], 1)


@dataclass(frozen=True)
class AnyRigConfig:
    width: int = 32  # channels at full resolution; ×2 and ×4 below
    # a per-pixel photometric-stereo estimate (:func:`ps_estimate`) goes to the decoder's
    # last stage, and the normals and albedo are predicted as corrections to it (off:
    # the first version's network, runs/anyrig-cpu)
    ps_skip: bool = True


class AnyRigNet(nn.Module):
    """Shared per-photo encoder, pooling over photos, U-Net decoder (module doc)."""

    def __init__(self, cfg: AnyRigConfig = AnyRigConfig()) -> None:
        super().__init__()
        w = cfg.width
        self.cfg = cfg
        self.enc1 = _block(IN_CHANNELS, w)
        self.enc2 = _block(w, 2 * w, 2)
        self.enc3 = _block(2 * w, 4 * w, 2)
        self.mid = _block(8 * w, 4 * w)
        self.up2 = nn.ConvTranspose2d(4 * w, 2 * w, 2, 2)
        self.dec2 = _block(2 * w + 4 * w, 2 * w)
        self.up1 = nn.ConvTranspose2d(2 * w, w, 2, 2)
        self.dec1 = _block(w + 2 * w + (PS_CHANNELS if cfg.ps_skip else 0), w)
        self.head = nn.Conv2d(w, sum(OUT_CHANNELS.values()), 1)
        if cfg.ps_skip:  # start from the photometric-stereo estimate itself
            with torch.no_grad():
                self.head.weight.mul_(0.1)
                self.head.bias.zero_()

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        f1 = self.enc1(x)
        f2 = self.enc2(f1)
        return f1, f2, self.enc3(f2)

    def decode(self, p1: Tensor, p2: Tensor, p3: Tensor, ps: tuple[Tensor, ...] | None = None) -> dict[str, Tensor]:
        y = self.mid(p3)
        y = self.dec2(torch.cat([self.up2(y), p2], 1))
        y = self.dec1(torch.cat([self.up1(y), p1, *([ps[2]] if ps is not None else [])], 1))
        out = self.head(y)
        d, s, r, n = torch.split(out, [3, 3, 1, 3], 1)
        if ps is None:
            normal = torch.cat([torch.tanh(n[:, :2]) * 2, F.softplus(n[:, 2:]) + 0.2], 1)
            diffuse = torch.sigmoid(d)
        else:
            slope, albedo, _ = ps
            normal = torch.cat([slope + 2 * torch.tanh(n[:, :2]), torch.ones_like(n[:, 2:])], 1)
            diffuse = torch.sigmoid(torch.logit(albedo.clamp(0.02, 0.98)) + d)
        return {
            "diffuse": diffuse,
            "specular": torch.sigmoid(s - 2),
            "roughness": torch.sigmoid(r),
            "normal": normal / normal.norm(dim=1, keepdim=True),
        }

    def forward(self, x: Tensor, present: Tensor) -> dict[str, Tensor]:
        """Maps (B, C, H, W) from inputs (B, K, 10, H, W) and presence (B, K)."""
        b, k, c, h, w = x.shape
        if h % MULTIPLE or w % MULTIPLE:
            raise MatscanError(f"anyrig: the size {h}×{w} is not a multiple of {MULTIPLE}")
        flat = x.reshape(b * k, c, h, w)
        feats = self.encode(flat)
        pooled = [pool(f.reshape(b, k, *f.shape[1:]), present) for f in feats]
        ps = None
        if self.cfg.ps_skip:
            ps = ps_estimate(lambda: ((x[:, i], present[:, i]) for i in range(k)))
        return self.decode(*pooled, ps=ps)

    @torch.no_grad()
    def predict(self, inputs) -> dict[str, Tensor]:
        """Maps (C, H, W) from an iterable of (10, H, W) inputs, one photo at a time: the
        pooling runs as it goes, so the features' memory does not grow with the number of
        photos (the photometric-stereo skip keeps 6 channels a photo for its reweighted
        rounds: 72 photos of a 512² tile, 450 MB)."""
        tops: list[Tensor | None] = [None, None, None]
        sums: list[Tensor | None] = [None, None, None]
        kept: list[Tensor] = []  # what the photometric-stereo skip needs: 6 channels a photo
        count = 0
        for x in inputs:
            feats = self.encode(x[None])
            for i, f in enumerate(feats):
                tops[i] = f if tops[i] is None else torch.maximum(tops[i], f)
                sums[i] = f if sums[i] is None else sums[i] + f
            if self.cfg.ps_skip:
                kept.append(x[None, :6].clone())
            count += 1
        if count == 0:
            raise MatscanError("anyrig: no photos")
        pooled = [torch.cat([t, s / count], 1) for t, s in zip(tops, sums, strict=True)]
        ps = ps_estimate(lambda: ((t, None) for t in kept)) if self.cfg.ps_skip else None
        return {k: v[0] for k, v in self.decode(*pooled, ps=ps).items()}


# --- training data: a random rig for every sample ---------------------------------------


def random_lights(g: torch.Generator, count: int, reference_mm: float = 225.0) -> tuple[LightSet, float]:
    """``count`` lights of a rig drawn at random, and the camera's height (mm): a dome
    (directional lights, or near ones at 150–600 mm) at 10°–80° elevation with a camera
    above (perspective or, with directional lights, orthographic), or a phone flash
    moved over the sample (light beside the camera, 150–400 mm up)."""

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=g))

    kind = u(0, 1)
    height = u(200, 600)
    if kind < 0.2:  # flash: light and camera together, moved from photo to photo
        pos = []
        cams = []
        for _ in range(count):
            h = u(150, 400)
            x, y = u(-60, 60), u(-60, 60)
            pos.append((x + u(-15, 15), y + u(-15, 15), h))
            cams.append((x, y, h))
        lights = LightSet.points(torch.tensor(pos), torch.tensor(cams), reference_mm)
        return lights, height
    elevation = torch.deg2rad(10 + 70 * torch.rand(count, generator=g))
    azimuth = 2 * math.pi * torch.rand(count, generator=g)
    d = torch.stack(
        [torch.cos(elevation) * torch.cos(azimuth), torch.cos(elevation) * torch.sin(azimuth), torch.sin(elevation)], 1
    )
    directional = kind < 0.6
    orthographic = directional and u(0, 1) < 0.5
    cam = (0.0, 0.0, reference_mm) if orthographic else (0.0, 0.0, height)
    if directional:
        pos, w = d * reference_mm, torch.zeros(count)
    else:
        pos, w = d * torch.empty(count, 1).uniform_(150, 600, generator=g), torch.ones(count)
    lights = LightSet(
        position=pos,
        intensity=torch.ones(count, 3) * (1 + 0.1 * torch.randn(count, 1, generator=g)),
        axis=-d,
        exponent=torch.zeros(count),
        camera=torch.tensor(cam).expand(count, 3).clone(),
        reference_distance_mm=reference_mm,
        w=w,
        camera_w=torch.full((count,), 0.0 if orthographic else 1.0),
    )
    return lights, height


def miscalibrated(lights: LightSet, g: torch.Generator, degrees: float, intensity: float) -> LightSet:
    """The lights as they really were where the rig file says ``lights``: each one's place
    (its direction, or its position about the sample's centre) turned by an angle drawn
    from |N(0, ``degrees``)| about a random axis, and its intensity scaled by
    1 + N(0, ``intensity``) (at least 0.2): what a handheld light, directions read off a
    sphere, or LEDs of unequal brightness do to a capture."""
    n = len(lights)
    pos = lights.position.double()
    d = pos / pos.norm(dim=-1, keepdim=True)
    a = torch.randn(n, 3, generator=g, dtype=torch.float64)
    a = a - (a * d).sum(-1, keepdim=True) * d
    a = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t = torch.deg2rad(torch.randn(n, 1, generator=g, dtype=torch.float64).abs() * degrees)
    turned = d * t.cos() + a * t.sin()
    turned[:, 2] = turned[:, 2].clamp_min(0.02)  # never below the horizon
    turned = turned / turned.norm(dim=-1, keepdim=True)
    scale = (1 + intensity * torch.randn(n, 1, generator=g)).clamp_min(0.2)
    return replace(
        lights,
        position=(turned * pos.norm(dim=-1, keepdim=True)).to(lights.position.dtype),
        axis=-turned.to(lights.axis.dtype),
        intensity=lights.intensity * scale,
    )


def sample(
    g: torch.Generator,
    size: int,
    photos: int,
    prior: str = "v2",
    library: Sequence[MapSet] = (),
    library_prob: float = 0.5,
    library_metal_prob: float = 0.0,
    miscalibration: tuple[float, float] = (0.0, 0.0),
    tilt: tuple[float, float] = (0.0, 0.0),
) -> dict[str, Tensor]:
    """One training sample: a material (a crop of a 120 mm field) photographed under
    ``photos`` random lights of a random rig, through the camera model. The material is
    procedural (``prior``) or, with probability ``library_prob`` when ``library`` is given,
    a random crop of one of its map sets, metallized (:func:`matscan.data.metallize`)
    with probability ``library_metal_prob``. With ``miscalibration`` (degrees, intensity)
    the photos are taken under :func:`miscalibrated` lights while the network is told the
    drawn ones. With ``tilt`` (degrees, share) that share of samples lies tilted: every
    normal turned by an angle drawn uniformly up to ``degrees`` about a horizontal axis of
    random direction (:func:`tilted`). Without a library, miscalibration or tilt the draws
    are those of every earlier run."""
    from matscan.capture.virtual import CameraModel, apply_camera
    from matscan.data import metallize, random_crop
    from matscan.materials.procedural import random_material
    from matscan.render import render_maps, surface_points

    if library and float(torch.rand((), generator=g)) < library_prob:
        maps = random_crop(library[int(torch.randint(len(library), (), generator=g))], g, size)
        if library_metal_prob > 0 and float(torch.rand((), generator=g)) < library_metal_prob:
            maps = metallize(maps, g)
    else:
        seed = int(torch.randint(0, 2**31 - 1, (), generator=g))
        _, maps = random_material(size, seed, prior=prior)
    if tilt[0] > 0 and tilt[1] > 0 and float(torch.rand((), generator=g)) < tilt[1]:
        angle = tilt[0] * float(torch.rand((), generator=g))
        azimuth = 360.0 * float(torch.rand((), generator=g))
        maps = replace(maps, normal=tilted(maps.normal, angle, azimuth))
    full = 4 * size
    off = (
        int(torch.randint(0, full - size + 1, (), generator=g)),
        int(torch.randint(0, full - size + 1, (), generator=g)),
    )
    points = surface_points((120.0, 120.0), (size, size), off, (full, full))
    lights, _ = random_lights(g, photos)
    true = miscalibrated(lights, g, *miscalibration) if any(miscalibration) else lights
    with torch.no_grad():
        radiance = render_maps(maps, true, (120.0, 120.0), points=points)
    exposure = 1 / max(float(radiance.quantile(0.99)), 0.05) * float(0.3 + 0.6 * torch.rand((), generator=g))
    srgb = bool(torch.rand((), generator=g) < 0.7)
    camera = CameraModel(read_noise=0.002, encoding="srgb" if srgb else "linear", bits=8 if srgb else 16)
    shots = apply_camera(radiance * exposure, camera, g) / exposure
    x = torch.stack([photo_input(shots[k], lights.select([k]), points) for k in range(photos)])
    return {"x": x, "points": points, **{k: getattr(maps, k) for k in OUT_CHANNELS}}


def tilted(normal: Tensor, degrees: float, azimuth_degrees: float) -> Tensor:
    """Normals (3, H, W) of a sample tilted by ``degrees`` toward the azimuth
    ``azimuth_degrees`` (from +x toward +y): each turned about the horizontal axis
    perpendicular to that azimuth (Rodrigues' formula), so a flat normal (0, 0, 1) becomes
    (sin t cos φ, sin t sin φ, cos t)."""
    t, phi = math.radians(degrees), math.radians(azimuth_degrees)
    k = torch.tensor([-math.sin(phi), math.cos(phi), 0.0], dtype=normal.dtype, device=normal.device).view(3, 1, 1)
    cross = torch.linalg.cross(k.expand_as(normal), normal, dim=0)
    dot = (k * normal).sum(0, keepdim=True)
    return normal * math.cos(t) + cross * math.sin(t) + k * dot * (1 - math.cos(t))


def loss(
    pred: dict[str, Tensor], batch: dict[str, Tensor], render_weight: float = 0.0, lights: LightSet | None = None
) -> Tensor:
    """L1 of diffuse, specular and roughness plus 1 − cos of the normals; with
    ``render_weight`` also that times the log-space L1 of the predicted maps rendered
    under the novel ``lights`` (batched, one set per sample) against the true maps
    rendered there (:func:`matscan.losses.rendering_loss`, summed over the lights), at
    the batch's surface points: a map the photos leave open is then judged by how it
    relights, not by its distance from the truth alone."""
    terms = [(pred[k] - batch[k]).abs().mean() for k in ("diffuse", "specular", "roughness")]
    terms.append(1 - (pred["normal"] * batch["normal"]).sum(1).mean())
    if render_weight > 0:
        from matscan.losses import rendering_loss

        if lights is None:
            raise ValueError("a rendering term needs its lights")
        truth = {k: batch[k] for k in OUT_CHANNELS}
        terms.append(render_weight * rendering_loss(pred, truth, tuple(OUT_CHANNELS), lights, batch["points"]))
    return sum(terms)


def render_lights(g: torch.Generator, batch: int, count: int) -> LightSet:
    """The rendering term's novel lights: ``count`` isotropic point lights per sample over
    the hemisphere above 10°, 225–450 mm away, seen by a camera 225 mm above the centre
    (:func:`matscan.losses.novel_lights`)."""
    from matscan.losses import novel_lights

    return novel_lights(batch, count, 225.0, (0.0, 0.0, 225.0), g)


# --- training ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainAnyRig:
    size: int = 64
    batch: int = 4
    min_photos: int = 1
    max_photos: int = 12
    lr: float = 3e-4
    seed: int = 0
    prior: str = "v2"
    device: str = "auto"
    library: tuple[str, ...] = ()  # map set folders mixed with the procedural prior (tools/photo_library.py)
    library_prob: float = 0.5  # the share of samples drawn from them, when there are any
    library_metal_prob: float = 0.0  # the share of those given metal patches (matscan.data.metallize)
    # the weights' exponential moving average kept beside them, decay per step (0: none);
    # it starts from the checkpoint's weights where the checkpoint has no average yet
    ema: float = 0.0
    # photos taken under lights other than the ones the network is told (miscalibrated):
    # each light's place off by |N(0, degrees)|, its intensity by N(0, intensity)
    miscal_degrees: float = 0.0
    miscal_intensity: float = 0.0
    # ... only in samples of at least this many photos: one photo cannot show that its light
    # is not the one named, so miscalibrating it teaches nothing the network could use
    miscal_min_photos: int = 1
    # the rendering term's weight (0: none; the paper's λ_r is 1/24) and its novel lights per sample
    render_weight: float = 0.0
    render_lights: int = 8
    # a share of samples lying tilted, every normal turned by up to this angle (0: none)
    tilt_degrees: float = 0.0
    tilt_prob: float = 0.5


CHECKPOINT = "checkpoint.safetensors"
WEIGHTS = "weights.safetensors"  # the run's network to ship: :func:`export` of the checkpoint
EMA_PREFIX = "ema."


def _split_ema(state: dict[str, Tensor]) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """A checkpoint's tensors as (weights, their moving average; empty when it has none)."""
    ema = {k[len(EMA_PREFIX) :]: v for k, v in state.items() if k.startswith(EMA_PREFIX)}
    return {k: v for k, v in state.items() if not k.startswith(EMA_PREFIX)}, ema


def read_library(paths: Iterable[str | Path]) -> list[MapSet]:
    """The map sets of a training config's ``library``, read once (a folder that is not a
    map set is a one-line MatscanError naming it)."""
    from matscan.materials.library import read_any

    return [read_any(p) for p in paths]


def _batch(g: torch.Generator, cfg: TrainAnyRig, library: Sequence[MapSet] = ()) -> dict[str, Tensor]:
    k = int(torch.randint(cfg.min_photos, cfg.max_photos + 1, (), generator=g))
    miscal = (cfg.miscal_degrees, cfg.miscal_intensity) if k >= cfg.miscal_min_photos else (0.0, 0.0)
    items = [
        sample(
            g,
            cfg.size,
            k,
            cfg.prior,
            library,
            cfg.library_prob,
            cfg.library_metal_prob,
            miscal,
            (cfg.tilt_degrees, cfg.tilt_prob),
        )
        for _ in range(cfg.batch)
    ]
    return {key: torch.stack([it[key] for it in items]) for key in items[0]}


def train(
    out: str | Path,
    cfg: TrainAnyRig = TrainAnyRig(),
    minutes: float = 10.0,
    max_steps: int | None = None,
    progress: bool = False,
    net_cfg: AnyRigConfig | None = None,
) -> dict:
    """Train (or resume, from ``out/checkpoint.safetensors``) for ``minutes``; writes the
    checkpoint (weights, their moving average when ``cfg.ema``, and step; Adam restarts on
    resume), ``log.csv`` and, at the end, ``weights.safetensors`` (:func:`export`: the
    network to ship). A new run's network is ``net_cfg`` (default
    :class:`AnyRigConfig`); a resumed run keeps the checkpoint's, and a ``net_cfg`` that
    differs from it is an error, as is resuming a run that keeps an average without one."""
    from safetensors.torch import save_file
    from tqdm import tqdm

    from matscan.atomic import atomic_file, write_text
    from matscan.materials.procedural import check_prior

    check_prior(cfg.prior)
    if cfg.size < 8 or cfg.size % 4 or cfg.batch < 1:
        raise MatscanError(
            f"--size, --batch: {cfg.size!r}, {cfg.batch!r} must be a crop of 8 pixels or more, a multiple of 4, "
            "and at least one sample a step"
        )
    if not 0 <= cfg.ema < 1:
        raise MatscanError(f"--ema: {cfg.ema!r} must be a decay per step in [0, 1)")
    if not 0 <= cfg.miscal_degrees <= 45 or not 0 <= cfg.miscal_intensity <= 1:
        raise MatscanError(
            f"--miscalibration: {cfg.miscal_degrees!r}, {cfg.miscal_intensity!r} must be degrees in [0, 45] "
            "and a relative intensity in [0, 1]"
        )
    if not (0 <= cfg.tilt_degrees <= 60 and 0 <= cfg.tilt_prob <= 1):
        raise MatscanError(
            f"--tilt: {cfg.tilt_degrees!r}, {cfg.tilt_prob!r} must be degrees in [0, 60] and a share in [0, 1]"
        )
    if cfg.miscal_min_photos < 1:
        raise MatscanError(f"--miscal-from: {cfg.miscal_min_photos!r} must be a number of photos, at least 1")
    if not (0 <= cfg.render_weight < 100 and 1 <= cfg.render_lights <= 64):
        raise MatscanError(
            f"--render-weight, --render-lights: {cfg.render_weight!r}, {cfg.render_lights!r} must be a weight in "
            "[0, 100) and 1 to 64 lights"
        )
    from matscan.outputs import check_run_folder
    from matscan.train import resolve_device

    out = Path(out)
    check_run_folder(out, cfg.library, (CHECKPOINT, "log.csv", WEIGHTS))
    if (out / "config.json").is_file():  # rewritten at each start: it must be a run's of this kind
        from matscan.jsonfile import read_json

        kept = read_json(out / "config.json")
        if not (isinstance(kept, dict) and {"train", "net"} <= set(kept)):
            raise input_error(out / "config.json", "is not a train-anyrig run's config; choose another --out")
    device = resolve_device(cfg.device)
    library = read_library(cfg.library)
    step = 0
    ckpt = out / CHECKPOINT
    state = None
    averaged: dict[str, Tensor] = {}
    if ckpt.exists():
        state, averaged = _split_ema(_read_checkpoint(ckpt))
        step = int(state.pop("step").item())
        if averaged and not cfg.ema:
            raise MatscanError(f"{ckpt}: the run keeps its weights' moving average; resume it with --ema DECAY")
        found = config_of(state)
        if net_cfg is not None and net_cfg != found:
            raise MatscanError(f"{ckpt}: the run's network is {found}, not {net_cfg}; use a new run folder")
        net_cfg = found
    net = AnyRigNet(net_cfg or AnyRigConfig()).to(device)
    if state is not None:
        try:
            net.load_state_dict(state)
        except RuntimeError:
            raise input_error(ckpt, "is not an any-rig network's checkpoint (its tensors do not fit)") from None
    ema = None
    if cfg.ema > 0:
        ema = {k: v.detach().clone() for k, v in net.state_dict().items()}
        if averaged:  # the checkpoint's own average carries on
            ema = {k: averaged[k].to(device) if k in averaged else v for k, v in ema.items()}

    def checkpoint() -> None:
        tensors = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
        if ema is not None:
            tensors.update({EMA_PREFIX + k: v.cpu().contiguous() for k, v in ema.items()})
        with atomic_file(ckpt) as tmp:  # a run killed while writing keeps its last checkpoint
            save_file({**tensors, "step": torch.tensor(step)}, tmp)

    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "config.json", json.dumps({"train": asdict(cfg), "net": asdict(net.cfg)}, indent=1))
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    deadline = time.monotonic() + 60 * minutes
    new_log = not (out / "log.csv").exists()
    with open(out / "log.csv", "a", newline="") as f, tqdm(desc="anyrig", unit="step", disable=not progress) as bar:
        writer = csv.writer(f)
        if new_log:
            writer.writerow(["step", "loss", "photos", "seconds"])
        while time.monotonic() < deadline and (max_steps is None or step < max_steps):
            t0 = time.perf_counter()
            batch = {k: v.to(device) for k, v in _batch(g, cfg, library).items()}
            present = torch.ones(batch["x"].shape[:2], device=device)
            novel = None
            if cfg.render_weight > 0:  # its own generator: the samples are those of a run without it
                lg = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step + 7)
                novel = render_lights(lg, batch["x"].shape[0], cfg.render_lights).to(device)
            value = loss(net(batch["x"], present), batch, cfg.render_weight, novel)
            opt.zero_grad()
            value.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            if ema is not None:
                with torch.no_grad():
                    for k, v in net.state_dict().items():
                        ema[k].lerp_(v, 1 - cfg.ema)
            step += 1
            writer.writerow(
                [step, f"{float(value.detach()):.5f}", batch["x"].shape[1], f"{time.perf_counter() - t0:.3f}"]
            )
            bar.update(1)
            if step % 50 == 0:
                f.flush()
                checkpoint()
    checkpoint()
    export(ckpt, out / WEIGHTS)
    return {"steps": step, "checkpoint": str(ckpt), "weights": str(out / WEIGHTS)}


def _read_checkpoint(path: Path) -> dict[str, Tensor]:
    """A train-anyrig checkpoint's tensors; a file that is not one is a one-line error."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        state = load_file(path)
    except (SafetensorError, OSError, ValueError) as exc:
        raise input_error(path, f"is not a readable safetensors file ({str(exc).splitlines()[0][:120]})") from None
    if "step" not in state or state["step"].numel() != 1:
        raise input_error(path, "is not a train-anyrig checkpoint (no step); give the run a new folder")
    return state


def config_of(state: dict[str, Tensor]) -> AnyRigConfig:
    """The :class:`AnyRigConfig` a state dict was made with, from its tensors' shapes."""
    enc = state.get("enc1.0.weight")
    dec = state.get("dec1.0.weight")
    if enc is None or dec is None:
        return AnyRigConfig()  # load_state_dict names what is missing
    width = int(enc.shape[0])
    return AnyRigConfig(width=width, ps_skip=int(dec.shape[1]) == 3 * width + PS_CHANNELS)


def load(path: str | Path, averaged: bool = True) -> AnyRigNet:
    """An AnyRigNet from a checkpoint or weights file, with the weights' moving average
    where the checkpoint has one (``averaged=False``: its raw weights); a file that is not
    one is a one-line error naming it."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        state = load_file(path)
    except (SafetensorError, OSError, ValueError) as exc:
        raise input_error(path, f"is not a readable safetensors file ({str(exc).splitlines()[0][:120]})") from None
    state.pop("step", None)
    raw, average = _split_ema(state)
    state = (average if averaged else None) or raw
    net = AnyRigNet(config_of(state))
    try:
        net.load_state_dict(state)
    except RuntimeError:
        expected = set(net.state_dict())
        missing, extra = sorted(expected - set(state)), sorted(set(state) - expected)
        what = f"lacks {missing[0]}" if missing else f"has {extra[0]}" if extra else "has tensors of other shapes"
        raise input_error(path, f"is not an any-rig network's weights (it {what})") from None
    return net.eval()


def export(checkpoint: str | Path, out: str | Path, dtype: torch.dtype = torch.float16) -> Path:
    """A checkpoint's network as a weights file to ship: the moving average where the
    run keeps one (what :func:`load` uses), else the raw weights, stored as ``dtype``
    (float16 quarters the checkpoint; they load into a float32 network), without the
    raw weights or the step; the step and the source go in the file's metadata.
    Written atomically; the checkpoint is checked by loading it first."""
    from safetensors.torch import load_file, save_file

    from matscan.atomic import atomic_file

    net = load(checkpoint)  # a file that is not a network is a one-line error here
    step = load_file(str(checkpoint)).get("step")
    tensors = {k: v.detach().to(dtype).contiguous() for k, v in net.state_dict().items()}
    meta = {"format": "matscan-anyrig/1", "source": Path(checkpoint).name}
    if step is not None:
        meta["step"] = str(int(step.item()))
    with atomic_file(out) as tmp:
        save_file(tensors, tmp, metadata=meta)
    return Path(out)


def predict_capture(
    net: AnyRigNet, capture, tile: int = 512, overlap: int = 64, progress: bool = False
) -> dict[str, Tensor]:
    """The network's maps for a loaded capture of any rig. Images larger than ``tile``
    go in overlapping tiles blended with linear ramps (the network sees about 40 px
    around a pixel and pools nothing over the image, so a tile's maps are the whole
    image's there), which bounds memory by the tile; each tile is padded to a multiple
    of 4 and cropped back."""
    from tqdm import tqdm

    from matscan.reconstruct.networks import _ramp, _starts
    from matscan.render import surface_points

    h, w = capture.size
    tile = max(MULTIPLE, tile // MULTIPLE * MULTIPLE)
    overlap = min(overlap, tile // 2)
    out = {name: torch.zeros(c, h, w) for name, c in OUT_CHANNELS.items()}
    weight = torch.zeros(1, h, w)
    tiles = [(r, c) for r in _starts(h, tile, overlap) for c in _starts(w, tile, overlap)]
    quiet = not progress or len(tiles) == 1
    for r0, c0 in tqdm(tiles, desc="any-rig network", unit="tile", disable=quiet, leave=False):
        th, tw = min(tile, h - r0), min(tile, w - c0)
        points = surface_points(capture.field_mm, (th, tw), (r0, c0), (h, w))
        ph, pw = (-th) % MULTIPLE, (-tw) % MULTIPLE

        def inputs(r0=r0, c0=c0, th=th, tw=tw, points=points, ph=ph, pw=pw):
            for i in range(len(capture.files)):
                photo = capture.linear([i], rows=(r0, r0 + th), cols=(c0, c0 + tw))[0]
                x = photo_input(photo, capture.lights.select([i]), points)
                yield F.pad(x[None], (0, pw, 0, ph), mode="replicate")[0]

        maps = net.predict(inputs())
        wr, wc = _ramp(th, overlap, r0 == 0, r0 + th >= h), _ramp(tw, overlap, c0 == 0, c0 + tw >= w)
        wt = (wr[:, None] * wc[None])[None]
        for name, t in maps.items():
            out[name][:, r0 : r0 + th, c0 : c0 + tw] += t[:, :th, :tw] * wt
        weight[:, r0 : r0 + th, c0 : c0 + tw] += wt
    maps = {name: t.div_(weight) for name, t in out.items()}
    maps["normal"] = maps["normal"] / maps["normal"].norm(dim=0, keepdim=True).clamp_min(1e-8)
    return maps
