"""Training losses (the paper's Eqs. 6–11, as the issue and design state them).

For each map network, with the other three maps taken from the ground truth:

    L_x = λ_m · L1(x̂, x) + λ_r · Σ_k L1(log(ε + R_k(x̂, rest)), log(ε + R_k(x, rest)))   (+ terms below)
    L_d += 1 − SSIM(d̂, d)                    (diffuse)
    L_n += 1 − mean(n̂ · n)                   (normals: the cosine loss)

with λ_m = 1, λ_r = 1/24, R_k the rendering (design.md image formation) under
novel light k (random position over the sample), and ε = 0.01: renderings are
compared in log space so highlights do not drown the rest (as in Deschaintre et
al. 2018). The paper sums 24 renderings; ``render_lights`` sets how many.

The paper's form trains each network against renderings whose other maps are
*true*, so no network learns what the others' errors do to the relighting (a
roughness read against true normals relights worse with predicted ones). Training
with ``render_with="joint"`` replaces the per-network rendering terms with one,

    L_joint = λ_r · Σ_k L1(log(ε + R_k(x̂₁, …, x̂ₘ, rest)), log(ε + R_k(truth)))

with every trained map predicted together (the maps not trained from the truth),
added once to the sum of the networks' other terms.

SSIM: Wang et al. 2004, 11 × 11 Gaussian window (σ = 1.5), C1 = 0.01², C2 = 0.03²,
on values in [0, 1], averaged over channels and pixels ('valid' window positions).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from matscan.render import render
from matscan.rig import LightSet

LAMBDA_MAP = 1.0
LAMBDA_RENDER = 1.0 / 24
LOG_EPS = 0.01


def l1(pred: Tensor, target: Tensor) -> Tensor:
    """Mean absolute error."""
    return (pred - target).abs().mean()


def _gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32) -> Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(x: Tensor, y: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean structural similarity of (B, C, H, W) images in [0, 1] (Wang et al. 2004)."""
    c = x.shape[1]
    g = _gaussian_window(window, sigma, x.dtype).to(x.device)
    kernel = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(t, kernel, groups=c)

    c1, c2 = 0.01**2, 0.03**2
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def cosine_loss(pred: Tensor, target: Tensor) -> Tensor:
    """1 − mean cosine between (B, 3, H, W) unit normals."""
    return 1 - (pred * target).sum(dim=1).mean()


def novel_lights(
    batch: int, count: int, reference_distance_mm: float, camera_mm, g: torch.Generator, camera_w: float = 1.0
) -> LightSet:
    """``count`` random isotropic point lights per batch element over the sample:
    directions uniform over the hemisphere above 10° elevation, distance R to 2R.
    ``camera_mm`` and ``camera_w`` as for :class:`LightSet` (w 0: orthographic)."""
    u = torch.rand(batch, count, generator=g)
    phi = 2 * math.pi * torch.rand(batch, count, generator=g)
    z = math.sin(math.radians(10)) + (1 - math.sin(math.radians(10))) * u  # uniform in solid angle
    r = torch.sqrt(1 - z * z)
    dist = reference_distance_mm * (1 + torch.rand(batch, count, generator=g))
    pos = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1) * dist[..., None]
    cam = torch.as_tensor(camera_mm, dtype=torch.float32).expand(batch, count, 3)
    return LightSet.points(pos, cam, reference_distance_mm, camera_w=camera_w)


def rendering_loss(
    pred: dict[str, Tensor],
    truth: dict[str, Tensor],
    name: str | tuple[str, ...],
    lights: LightSet,
    points: Tensor,
    target: Tensor | None = None,
) -> Tensor:
    """Σ_k L1 in log space between renderings with the predicted ``name`` map (or
    maps, for the joint loss; the rest from ``truth``) and the ground truth, under
    ``lights``. ``target``: the ground truth's rendering under them (:func:`truth_rendering`),
    where several terms of a step share it."""
    maps = dict(truth)
    for n in (name,) if isinstance(name, str) else name:
        maps[n] = pred[n]
    # one chunk: with gradients kept, chunks save no memory, and each costs a kernel launch per operation
    whole = maps["diffuse"].shape[0] * lights.position.shape[-2] * maps["diffuse"].shape[-2] * maps["diffuse"].shape[-1]
    a = render(maps["diffuse"], maps["specular"], maps["roughness"], maps["normal"], lights, points, chunk=whole)
    b = truth_rendering(truth, lights, points) if target is None else target
    diff = (torch.log(LOG_EPS + a.clamp_min(0)) - torch.log(LOG_EPS + b)).abs()
    return diff.mean(dim=(0, 2, 3, 4)).sum()  # mean per rendering, summed over the K renderings


def truth_rendering(truth: dict[str, Tensor], lights: LightSet, points: Tensor) -> Tensor:
    """The ground-truth maps rendered under the loss's novel lights (no gradient): the
    target of every rendering term of a step."""
    with torch.no_grad():
        return render(truth["diffuse"], truth["specular"], truth["roughness"], truth["normal"], lights, points)


def map_loss(
    name: str,
    pred: dict[str, Tensor],
    truth: dict[str, Tensor],
    lights: LightSet | None,
    points: Tensor | None,
    lambda_map: float = LAMBDA_MAP,
    lambda_render: float = LAMBDA_RENDER,
    target: Tensor | None = None,
) -> tuple[Tensor, dict[str, float]]:
    """The loss of one map network, and its terms (for logging); ``target`` as for
    :func:`rendering_loss`."""
    terms = {"l1": l1(pred[name], truth[name])}
    total = lambda_map * terms["l1"]
    if lights is not None and lambda_render > 0:
        terms["render"] = rendering_loss(pred, truth, name, lights, points, target)
        total = total + lambda_render * terms["render"]
    if name == "diffuse":
        terms["ssim"] = 1 - ssim(pred[name].clamp(0, 1), truth[name])
        total = total + terms["ssim"]
    elif name == "normal":
        terms["cosine"] = cosine_loss(pred[name], truth[name])
        total = total + terms["cosine"]
    return total, {k: float(v.detach()) for k, v in terms.items()}
