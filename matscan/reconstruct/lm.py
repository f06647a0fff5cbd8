"""A batched second-order per-pixel solver: every pixel's maps fitted at once.

For one pixel under light k, the image formation model (design.md, Eq. 1) is, per
colour channel c,

    m_kc = ρ_c · A_kc + F0_c · S1_kc + S0_kc
    A_kc  = I_kc E_k (n·l)⁺                       (diffuse)
    S1_kc = I_kc E_k π D G /(4 n·v) · (1 − w_k)   (Schlick: F = F0 (1 − w) + w,
    S0_kc = I_kc E_k π D G /(4 n·v) · w_k          w = (1 − v·h)⁵)

with E_k = (R/d)² · lobe. Given roughness r and normal n the model is *linear* in
(ρ_c, F0_c), so those are solved in closed form (a 2 × 2 ridge regression per pixel
and channel) and only θ = (r, s_x, s_y) — the normal as slopes, n ∝ (s_x, s_y, 1) —
is nonlinear: variable projection (Golub & Pereyra 1973). θ is found by
Levenberg–Marquardt (Marquardt 1963) on all pixels at once, with the Jacobian by
forward differences of the projected residual, 3 × 3 systems solved in closed form,
and the damping adapted per pixel. A coarse level (the photos box-filtered) finds
the basin, after a grid search over roughness; the full level polishes.

Residuals are relative, √W (m − y) with W = valid / (y + τ)², so dark and bright
pixels count alike (as the log-space loss of the first-order refinement does). Weights
taken from the photos favour the values the noise pushed low (and those the camera
clipped at 0): with noisy photos the fit follows them down (a glossy sample at the
exposure that keeps its highlights unsaturated, its diffuse regions a few code values
above black, came out with half its albedo; runs/lm-noise/README.md). So where a capture
has ``reweight_from`` photos or more and the first sweep's residuals (noise, and misfit:
lights placed or scaled wrong) show the photos noisier than τ assumes (``noise_floor`` ×
σ̂ > τ, σ̂ the robust deviation of the darker half of the values' residuals, measured
over the whole image), ``reweight`` more sweeps at full resolution take the weights from
the fitted model m instead, W = valid / (m + τ')², τ' = ``noise_floor`` × σ̂: a dark
value counts as the noise allows rather than as a relative error of 1/τ. Elsewhere the
first sweep's maps stand: with photos no noisier than τ assumes, the model's weights
only move the misfit about (better on some materials, worse on others: the engine
study), and with fewer photos the fit follows each value's noise, so its model weighs as
the photos do.

A saturated value (``valid`` 0: the camera stored its top code) is not unknown: the
surface sent at least that much light. With ``censored`` (the default) each stays in the
fit as a one-sided observation, its residual √W · min(m − y, 0) with W = 1 / (y + τ)²: a
model below the clip is pulled up to it, one above it costs nothing (the hinge of
censored regression, as Tobin 1958 treats limited values). ρ and F0 are then solved in
closed form with the censored values that the last solve's model puts below their clip
counted as ordinary ones, solved again until that set stops changing (an active set,
at most :data:`CENSORED_SOLVES` solves more); on the
coarse level a pooled value with any saturated value in its box is censored at the pooled
value, also a lower bound. Dropped instead, as before, a highlight's peak could sit
anywhere below the clip, and metals whose peaks clip came out with F0 too low and
roughness too high (runs/lm-censored/README.md).

The full level takes ``fine_iterations`` steps, then, from ``more_from`` photos, up to
``more_iterations`` more on the pixels still converging (those whose last accepted step
lowered their cost by more than :data:`CONVERGED` and whose damping has not reached
:data:`STUCK`), solved as a smaller problem. From flat maps two steps left pixels far
from their minimum (a black leather on a 49-light dome relit at 30.2 dB where converged
it relights at 44.4); from the networks' maps, and with fewer photos, the fixed steps'
hold on the start relit better, so ``reconstruct`` gives the networks' start none
(runs/lm-converge/README.md).

The prior: ridge terms hold ρ and F0 near their start (the networks' maps) and
quadratic terms hold r and the slopes near theirs, with fixed strengths. Where the
photos constrain a value (a highlight constrains F0 and r), the data's curvature is
large and the prior barely matters; where they do not (no highlight ever), the
prior decides. The ratio data curvature / (data curvature + prior) per parameter is
the **confidence** of each map: 1 where the photos determined the value, 0 where
the start filled it in.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from matscan.brdf import ggx_alpha, ggx_distribution, smith_g
from matscan.errors import MatscanError
from matscan.render import led_lobe
from matscan.rig import LightSet

#: From this many photos a capture's weights may be taken from the fitted model
#: (``SolverConfig.reweight_from``): chosen on a selection set (runs/lm-noise/README.md).
REWEIGHT_FROM = 6


@dataclass(frozen=True)
class SolverConfig:
    """Settings of the second-order solver (:func:`solve`).

    Prior strengths are in units of one relative-error observation: 1 means the
    start counts as much as one photo that pins the value to it.
    """

    iterations: int = 12  # Levenberg–Marquardt steps on the coarse level
    fine_iterations: int = 2  # and on the full-resolution level (at least 1)
    more_iterations: int = 8  # then at most this many on the pixels still converging (module doc)
    more_from: int = REWEIGHT_FROM  # from this many photos on (reconstruct gives the networks' start none)
    coarse: int = 96  # longer side of the coarse level in pixels (0: no coarse level)
    tau: float = 0.02  # relative residuals are (m − y)/(y + τ)
    prior_diffuse: float = 0.1
    prior_specular: float = 0.2
    prior_roughness: float = 0.5  # per unit of roughness²
    prior_normal: float = 0.5  # per unit of slope²
    tile_pixels: int = 1 << 16  # pixels solved at once (bounds memory)
    reweight: int = 2  # passes with the weights from the fitted model (module doc)
    reweight_from: int = REWEIGHT_FROM  # photos a capture needs for them
    noise_floor: float = 3.0  # τ' = noise_floor × the residuals' deviation, where it exceeds τ (else no sweeps)
    censored: bool = True  # saturated values count as "at least the clip" (module doc), not dropped

    def __post_init__(self) -> None:
        integers = (
            ("iterations", 0),
            ("fine_iterations", 1),
            ("more_iterations", 0),
            ("coarse", 0),
            ("tile_pixels", 1),
            ("reweight", 0),
        )
        for name, low in (*integers, ("reweight_from", 1), ("more_from", 1)):
            value = getattr(self, name)  # fine_iterations ≥ 1: the confidence needs one Jacobian
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise MatscanError(f"solver.{name}: {value!r} must be an integer of at least {low}")
        for name in ("tau", "prior_diffuse", "prior_specular", "prior_roughness", "prior_normal", "noise_floor"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise MatscanError(f"solver.{name}: {value!r} must be a finite number of at least 0")
        if self.tau <= 0:
            raise MatscanError("solver.tau: must be above 0")


@dataclass
class Geometry:
    """What the lights and camera give every pixel of a set of P pixels, K lights."""

    l: Tensor  # (K, 3, P) unit, toward the light
    v: Tensor  # (1, 3, P) or (K, 3, P) unit, toward the camera
    e: Tensor  # (K, C, P) I_k (R/d)² lobe: irradiance on a surface facing the light, per channel
    h: Tensor  # (K, 3, P) unit half vectors: none of these depend on the maps
    w: Tensor  # (K, P) Schlick's weight (1 − v·h)⁵


def geometry(lights: LightSet, points: Tensor) -> Geometry:
    """:class:`Geometry` of ``points`` (P, 3) in mm."""
    p = points.T  # (3, P)
    lv = lights.position[:, :, None] - lights.w[:, None, None] * p[None]  # (K, 3, P); w = 0: directional
    d2 = (lv * lv).sum(1)
    l = lv * torch.rsqrt(d2)[:, None]
    lobe = led_lobe(-(lights.axis[:, :, None] * l).sum(1), lights.exponent[:, None])
    e = lights.intensity[:, :, None] * ((lights.reference_distance_mm**2 / d2) * lobe)[:, None]
    cams, cw = lights.camera, lights.camera_w
    if bool((cams == cams[:1]).all()) and bool((cw == cw[:1]).all()):
        cv = (cams[0][:, None] - cw[0] * p)[None]
    else:
        cv = cams[:, :, None] - cw[:, None, None] * p[None]
    v = cv * torch.rsqrt((cv * cv).sum(1, keepdim=True))
    h = l + v
    h = h * torch.rsqrt((h * h).sum(1, keepdim=True).clamp_min(1e-20))
    w = (1 - (v * h).sum(1).clamp(0, 1)) ** 5
    return Geometry(l, v, e, h, w)


def normal_of(theta: Tensor) -> Tensor:
    """Unit normals (3, P) from θ = (r, s_x, s_y) (3, P)."""
    n = torch.stack([theta[1], theta[2], torch.ones_like(theta[1])])
    return n * torch.rsqrt((n * n).sum(0, keepdim=True))


def bases(theta: Tensor, geo: Geometry) -> tuple[Tensor, Tensor, Tensor]:
    """(A, S1, S0), each (K, C, P): the model is ρ·A + F0·S1 + S0 (module doc)."""
    n = normal_of(theta)[None]
    n_l = (n * geo.l).sum(1)  # (K, P)
    n_v = (n * geo.v).sum(1).expand_as(n_l)
    n_h = (n * geo.h).sum(1).clamp_min(0)
    alpha = ggx_alpha(theta[0].clamp(0.02, 1))[None]
    n_l_c, n_v_c = n_l.clamp_min(1e-7), n_v.clamp_min(1e-7)
    spec = ggx_distribution(n_h, alpha) * smith_g(n_l_c, n_v_c, alpha) * (math.pi / 4) / n_v_c
    spec = torch.where((n_l > 0) & (n_v > 0), spec, torch.zeros((), dtype=spec.dtype))
    w = geo.w
    a = geo.e * n_l.clamp_min(0)[:, None]
    s = geo.e * spec[:, None]
    return a, s * (1 - w)[:, None], s * w[:, None]


@dataclass
class Problem:
    """One set of pixels to solve: photos, weights, geometry and the prior."""

    y: Tensor  # (K, 3, P) photos, linear (divided by any intensity scale)
    wt: Tensor  # (K, 3, P) W = valid / (y + τ)²
    geo: Geometry
    rho0: Tensor  # (3, P) prior means
    f00: Tensor  # (3, P)
    theta0: Tensor  # (3, P)
    lam_d: Tensor  # (3, P) ridge strengths
    lam_s: Tensor  # (3, P)
    lam_t: Tensor  # (3, 1) strengths on θ
    sw: Tensor | None = None  # √W, computed once
    # the censored values' weights (1 − valid) / (y + τ)² (K, 3, P), or None; kept as a list
    # of the values that have one (few: a highlight's peaks), by their place in (K, 3, P)
    cw: Tensor | None = None
    cflat: Tensor | None = None  # (N,) places in (K, 3, P) flattened
    cout: Tensor | None = None  # (N,) their places in (3, P) flattened: channel and pixel
    cwe: Tensor | None = None  # (N,) their weights
    cye: Tensor | None = None  # (N,) their values

    def __post_init__(self) -> None:
        if self.sw is None:
            self.sw = self.wt.sqrt()
        if self.cw is not None:
            flat = self.cw.reshape(-1)
            self.cflat = flat.nonzero()[:, 0]
            self.cout = self.cflat % (self.cw.shape[1] * self.cw.shape[2])
            self.cwe, self.cye = flat[self.cflat], self.y.reshape(-1)[self.cflat]
            self.cw = None  # the list is kept instead
        if self.cflat is not None and len(self.cflat) == 0:
            self.cflat = self.cout = self.cwe = self.cye = None


def _sums(y: Tensor, wt: Tensor, a: Tensor, s1: Tensor, s0: Tensor) -> Tensor:
    """Σ_k W·(A², S1², A·S1, A·(y − S0), S1·(y − S0)): (5, 3, P)."""
    t = y - s0
    wa, ws = wt * a, wt * s1
    return torch.stack([(wa * a).sum(0), (ws * s1).sum(0), (wa * s1).sum(0), (wa * t).sum(0), (ws * t).sum(0)])


def _ridge(p: Problem, sums: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """ρ, F0 of :func:`linear_solve` from the data's :func:`_sums` and the prior."""
    haa, hss, has, ga, gs = sums.unbind(0)
    h11, h22 = haa + p.lam_d, hss + p.lam_s
    g1, g2 = ga + p.lam_d * p.rho0, gs + p.lam_s * p.f00
    det = (h11 * h22 - has * has).clamp_min(1e-12)
    rho = ((h22 * g1 - has * g2) / det).clamp(0, 1)
    f0 = ((g2 - has * rho) / h22.clamp_min(1e-12)).clamp(0, 1)  # F0 given the clamped ρ
    rho = ((g1 - has * f0) / h11.clamp_min(1e-12)).clamp(0, 1)  # and ρ given that F0
    return rho, f0, haa, hss


#: At most this many closed-form solves more per evaluation with censored values: each
#: counts those the last solve's model puts below their clip (an active set), until the
#: set stops changing (measured on half of rti-icon's photos: 3 or 4 solves in 143 of
#: 147 evaluations, and 1 reached this cap).
CENSORED_SOLVES = 12


def linear_solve(p: Problem, a: Tensor, s1: Tensor, s0: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """ρ, F0 (3, P) minimising Σ W (ρA + F0 S1 + S0 − y)² + λ_d(ρ − ρ0)² + λ_s(F0 − F0₀)²,
    within [0, 1]; and the data curvatures (Σ W A², Σ W S1²) (3, P). Censored values
    count as ordinary ones where the model falls below them (module doc)."""
    sums = _sums(p.y, p.wt, a, s1, s0)
    out = _ridge(p, sums)
    if p.cflat is None:
        return out
    # the censored values' bases and their products, as _sums forms them, once
    ae, s1e, s0e = (t.reshape(-1)[p.cflat] for t in (a, s1, s0))
    te = p.cye - s0e
    terms = torch.stack([ae * ae, s1e * s1e, ae * s1e, ae * te, s1e * te]) * p.cwe
    active = None
    for _ in range(CENSORED_SOLVES):
        now = out[0].reshape(-1)[p.cout] * ae + out[1].reshape(-1)[p.cout] * s1e + s0e < p.cye
        if active is not None and bool((now == active).all()):
            break  # the model agrees with the set it was solved with: the minimum
        active = now
        extra = torch.zeros(5, sums[0].numel(), dtype=sums.dtype)
        extra.index_add_(1, p.cout, terms * active)
        out = _ridge(p, sums + extra.reshape(sums.shape))
    return out


def residuals(p: Problem, theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The stacked residual vector (CK + 2C + 3, P) at θ with ρ, F0 projected out, and ρ, F0."""
    a, s1, s0 = bases(theta, p.geo)
    rho, f0, _, _ = linear_solve(p, a, s1, s0)
    m = rho[None] * a + f0[None] * s1 + s0
    k, c = m.shape[:2]
    data = p.sw * (m - p.y)
    if p.cflat is not None:  # W is 0 on a censored value: its one row is the hinge
        me = m.reshape(-1)[p.cflat]
        data = data.reshape(-1).index_add(0, p.cflat, p.cwe.sqrt() * (me - p.cye).clamp_max(0))
    data = data.reshape(k * c, -1)
    prior = torch.cat(
        [
            p.lam_d.sqrt() * (rho - p.rho0),
            p.lam_s.sqrt() * (f0 - p.f00),
            p.lam_t.sqrt() * (theta - p.theta0),
        ]
    )
    return torch.cat([data, prior]), rho, f0


def _solve3(m: Tensor, b: Tensor) -> Tensor:
    """Solve 3 × 3 systems m (3, 3, P) x = b (3, P) by Cramer's rule (symmetric positive definite)."""
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    det = torch.where(det.abs() < 1e-20, torch.full_like(det, 1e-20), det)
    c10 = m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]
    c11 = m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]
    c12 = m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]
    c20 = m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
    c21 = m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
    c22 = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    x0 = (c00 * b[0] + c10 * b[1] + c20 * b[2]) / det
    x1 = (c01 * b[0] + c11 * b[1] + c21 * b[2]) / det
    x2 = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det
    return torch.stack([x0, x1, x2])


#: roughness from √(1e-3) (below it GGX α is clamped, so the data cannot move it), slopes about ±72°
THETA_LOW = torch.tensor([0.032, -3.0, -3.0])[:, None]
THETA_HIGH = torch.tensor([1.0, 3.0, 3.0])[:, None]
_STEPS = (1e-3, 1e-3, 1e-3)  # forward-difference steps for r, s_x, s_y


def _subset(p: Problem, idx: Tensor) -> Problem:
    """The :class:`Problem` of the pixels ``idx`` (P',) of ``p``, censored values included."""
    g = p.geo
    geo = Geometry(l=g.l[..., idx], v=g.v[..., idx], e=g.e[..., idx], h=g.h[..., idx], w=g.w[..., idx])
    sub = Problem(
        y=p.y[..., idx],
        wt=p.wt[..., idx],
        geo=geo,
        rho0=p.rho0[:, idx],
        f00=p.f00[:, idx],
        theta0=p.theta0[:, idx],
        lam_d=p.lam_d[:, idx],
        lam_s=p.lam_s[:, idx],
        lam_t=p.lam_t,
        sw=p.sw[..., idx],
    )
    if p.cflat is not None:
        total, n = p.y.shape[-1], len(idx)
        place = torch.full((total,), -1, dtype=torch.long)
        place[idx] = torch.arange(n)
        pixel, row = p.cflat % total, p.cflat // total  # row: photo × channel
        keep = place[pixel] >= 0
        if bool(keep.any()):
            sub.cflat = row[keep] * n + place[pixel[keep]]
            sub.cout = (row[keep] % p.y.shape[1]) * n + place[pixel[keep]]
            sub.cwe, sub.cye = p.cwe[keep], p.cye[keep]
    return sub


def _lm_step(
    p: Problem, theta: Tensor, res: Tensor, cost: Tensor, mu: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """One damped Gauss–Newton step per pixel (:func:`levenberg_marquardt`): θ, residuals,
    cost and damping after it, and the data part of JᵀJ's diagonal at the θ it started from."""
    k3 = p.y.shape[0] * p.y.shape[1]  # the data rows
    cols = []
    for j, h in enumerate(_STEPS):
        # a backward difference where a forward one would pass the upper bound (at r = 1
        # a forward step is clamped away and the column would be zero)
        step = torch.where(theta[j] + h > THETA_HIGH[j, 0], -h, h)
        tp = theta.clone()
        tp[j] = tp[j] + step
        rj, _, _ = residuals(p, tp)
        cols.append((rj - res) / step)
    # JᵀJ and Jᵀr from the columns (R, P): products summed over residuals (einsum
    # would batch over pixels, which is many times slower here)
    jtj = torch.empty(3, 3, *theta.shape[1:], dtype=theta.dtype)
    for i in range(3):
        for j in range(i, 3):
            jtj[i, j] = jtj[j, i] = (cols[i] * cols[j]).sum(0)
    jtr = torch.stack([(c * res).sum(0) for c in cols])
    jtj_data = torch.stack([c[:k3].square().sum(0) for c in cols])
    damped = jtj.clone()
    for i in range(3):
        damped[i, i] = jtj[i, i] * (1 + mu) + 1e-9
    step = _solve3(damped, -jtr)
    trial = torch.max(torch.min(theta + step, THETA_HIGH.to(theta)), THETA_LOW.to(theta))
    res_t, _, _ = residuals(p, trial)
    cost_t = (res_t * res_t).sum(0)
    better = cost_t < cost
    theta = torch.where(better[None], trial, theta)
    res = torch.where(better[None], res_t, res)
    cost = torch.where(better, cost_t, cost)
    mu = torch.where(better, mu * 0.3, mu * 10).clamp(1e-6, 1e6)
    return theta, res, cost, mu, jtj_data


#: A pixel is still converging while its last accepted step lowered its cost by more than
#: this share and its damping is below :data:`STUCK` (``SolverConfig.more_iterations``).
CONVERGED = 1e-3
#: Damping at which a pixel's steps are taken as going nowhere (six rejected in a row
#: from the start's 1e-2, in float32). A pixel none of whose steps was accepted counts as
#: still converging until then.
STUCK = 1e3


def levenberg_marquardt(p: Problem, theta: Tensor, iterations: int, more: int = 0) -> tuple[Tensor, Tensor]:
    """Refine θ (3, P) for ``iterations`` steps, then up to ``more`` steps on the pixels
    still converging (:data:`CONVERGED`); returns θ and the data part of JᵀJ's diagonal
    (3, P) at each pixel's last step (the curvature the confidence uses)."""
    mu = torch.full_like(theta[0], 1e-2)
    res, _, _ = residuals(p, theta)
    cost = (res * res).sum(0)
    jtj_data = torch.zeros_like(theta)
    gain = torch.full_like(cost, math.inf)  # the share of cost each pixel's last accepted step removed
    for _ in range(iterations):
        before = cost
        theta, res, cost, mu, jtj_data = _lm_step(p, theta, res, cost, mu)
        gain = torch.where(cost < before, (before - cost) / before.clamp_min(1e-30), gain)
    if more == 0 or iterations == 0:
        return theta, jtj_data
    idx = ((gain > CONVERGED) & (mu < STUCK)).nonzero()[:, 0]
    sub = None
    for _ in range(more):
        if len(idx) == 0:
            break
        if sub is None:  # the pixels still converging, as one problem
            sub, at = _subset(p, idx), idx
            st, sr, sc, smu, sj, sg = theta[:, at], res[:, at], cost[at], mu[at], jtj_data[:, at], gain[at]
            keep = torch.ones(len(at), dtype=torch.bool)
        before = sc
        st2, sr2, sc2, smu2, sj2 = _lm_step(sub, st, sr, sc, smu)
        # pixels that have converged keep what they had; the others take the step
        st, sr, sj = (torch.where(keep[None], new, old) for new, old in ((st2, st), (sr2, sr), (sj2, sj)))
        sc, smu = torch.where(keep, sc2, sc), torch.where(keep, smu2, smu)
        sg = torch.where(keep & (sc < before), (before - sc) / before.clamp_min(1e-30), sg)
        keep = keep & (sg > CONVERGED) & (smu < STUCK)
        if int(keep.sum()) * 2 < len(at):  # half have converged: a smaller problem
            theta[:, at], jtj_data[:, at] = st, sj
            res[:, at], cost[at], mu[at], gain[at] = sr, sc, smu, sg
            idx, sub = at[keep], None
    if sub is not None:
        theta[:, at], jtj_data[:, at] = st, sj
    return theta, jtj_data


ROUGHNESS_GRID = (0.08, 0.15, 0.25, 0.35, 0.5, 0.7, 0.9)


def grid_start(p: Problem, theta: Tensor) -> Tensor:
    """θ with each pixel's roughness replaced by the best of a grid (and its start)."""
    best = theta.clone()
    res, _, _ = residuals(p, theta)
    cost = (res * res).sum(0)
    for r in ROUGHNESS_GRID:
        t = theta.clone()
        t[0] = r
        res, _, _ = residuals(p, t)
        c = (res * res).sum(0)
        better = c < cost
        best[0] = torch.where(better, r, best[0])
        cost = torch.where(better, c, cost)
    return best


# --- the driver: coarse level, then full resolution in tiles ---------------------------------


def _theta_of(roughness: Tensor, normal: Tensor) -> Tensor:
    """θ (3, H, W) from roughness (1, H, W) and unit normals (3, H, W)."""
    nz = normal[2:3].clamp_min(0.2)
    return torch.cat([roughness.clamp(0.02, 1), normal[0:1] / nz, normal[1:2] / nz]).clamp(
        THETA_LOW.view(3, 1, 1), THETA_HIGH.view(3, 1, 1)
    )


def _pool(t: Tensor, f: int) -> Tensor:
    return F.avg_pool2d(t.unsqueeze(0) if t.ndim == 3 else t, f, ceil_mode=True).squeeze(0) if f > 1 else t


def _problem(
    y: Tensor,
    valid: Tensor,
    geo: Geometry,
    rho0: Tensor,
    f00: Tensor,
    theta0: Tensor,
    cfg: SolverConfig,
    strength: float,
) -> Problem:
    """A :class:`Problem` over pixels: y (K, 3, P), valid (K, 1, P), priors (·, P).

    θ is fitted to all three channels, not their mean: the darkest channel shows the
    highlight's shape best (measured: roughness RMSE 0.035 → 0.018 on a brick map set).
    Linear photos may hold small negative values (noise around black); they are read as 0,
    or a value near −τ would weigh like a million photos."""
    y = y.clamp_min(0)
    wt = valid.expand_as(y) / (y + cfg.tau) ** 2
    cw = None
    if cfg.censored and bool((valid < 1).any()):
        cw = (1 - valid).expand_as(y) / (y + cfg.tau) ** 2
    lam_t = torch.tensor([cfg.prior_roughness, cfg.prior_normal, cfg.prior_normal])[:, None] * strength
    return Problem(
        y=y,
        wt=wt,
        geo=geo,
        rho0=rho0,
        f00=f00,
        theta0=theta0,
        lam_d=cfg.prior_diffuse * strength / (rho0 + 0.05) ** 2,
        # a relative tolerance above an absolute one of 0.1: around a dielectric start (0.04) a
        # metal's few highlights must still win (with 0.02 there the prior outweighed them)
        lam_s=cfg.prior_specular * strength / (f00 + 0.1) ** 2,
        lam_t=lam_t,
        cw=cw,
    )


def reweight_passes(cfg: SolverConfig, photos: int) -> int:
    """The passes with the weights from the fitted model for a capture of ``photos``
    photos: ``cfg.reweight`` from ``cfg.reweight_from`` photos on, else none."""
    return cfg.reweight if photos >= cfg.reweight_from else 0


#: Values (pixel × photo × channel) kept to measure the noise between sweeps.
NOISE_SAMPLE = 1 << 22


def noise_tau(model: Tensor, residual: Tensor, cfg: SolverConfig) -> float:
    """τ' = max(τ, ``noise_floor`` × 1.4826 × the median |residual| of the values whose
    model is at most the median model value), from the valid values' model and
    |photo − model| (module doc)."""
    if cfg.noise_floor <= 0 or model.numel() == 0:
        return cfg.tau
    dark = model <= model.median()
    return max(cfg.tau, cfg.noise_floor * 1.4826 * float(residual[dark].median()))


def _model_of(rho: Tensor, f0: Tensor, theta: Tensor, geo: Geometry) -> Tensor:
    """The model ρ·A + F0·S1 + S0 (K, 3, P), at least 0."""
    a, s1, s0 = bases(theta, geo)
    return (rho[None] * a + f0[None] * s1 + s0).clamp_min(0)


#: Reads rows r0:r1 of the photos: (linear photos (K, 3, r, W) divided by any intensity
#: scale, valid (K, 1, r, W) float, 0 where saturated).
PhotoRows = Callable[[int, int], tuple[Tensor, Tensor]]

#: Pixel-photos read at once while pooling the coarse level (4 Mi: 48 MiB of float32 photos).
POOL_VALUES = 1 << 22


def solve(
    photos: Tensor,
    valid: Tensor,
    lights: LightSet,
    points: Tensor,
    diffuse: Tensor,
    specular: Tensor,
    roughness: Tensor,
    normal: Tensor,
    cfg: SolverConfig = SolverConfig(),
    strength: float = 1.0,
    progress=None,
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """Fit maps to photos (module doc), starting from (and held near) the given maps.

    Args:
        photos: (K, 3, H, W) linear, already divided by any intensity scale.
        valid: (K, 1, H, W) float, 0 where a pixel is saturated.
        lights: the K photos' lights; points: (H, W, 3) surface points in mm.
        diffuse, specular, roughness, normal: the start and prior, (3|1, H, W).
        strength: multiplies every prior (small for a start that knows nothing).
        progress: a callable taking the number of pixel tiles done, or None.

    Returns:
        (maps, confidence): diffuse, specular, roughness, normal (3|1, H, W); and
        per map a (1, H, W) confidence in [0, 1] (module doc).
    """
    return solve_rows(
        lambda r0, r1: (photos[..., r0:r1, :], valid[..., r0:r1, :]),
        len(photos),
        lights,
        points,
        diffuse,
        specular,
        roughness,
        normal,
        cfg,
        strength,
        progress,
    )


def solve_rows(
    read: PhotoRows,
    k: int,
    lights: LightSet,
    points: Tensor,
    diffuse: Tensor,
    specular: Tensor,
    roughness: Tensor,
    normal: Tensor,
    cfg: SolverConfig = SolverConfig(),
    strength: float = 1.0,
    progress=None,
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """:func:`solve` with the K photos read a band of rows at a time by ``read``
    (:data:`PhotoRows`), so they need never be in memory as floats all at once."""
    h, w = diffuse.shape[-2:]
    correction = None  # the coarse level's change to θ, at full resolution
    f = max(1, math.ceil(max(h, w) / cfg.coarse)) if cfg.coarse else 1
    if f > 1 and cfg.iterations > 0:
        # pooled a band at a time; bands start at multiples of f, so each window lies in one
        band = max(f, POOL_VALUES // max(1, w * k) // f * f)
        yc, vc, tc0 = [], [], []
        for r0 in range(0, h, band):
            r1 = min(h, r0 + band)
            y, v = read(r0, r1)
            yc.append(_pool(y, f))
            vc.append((_pool(v, f) > 0.999).float())
            tc0.append(_pool(_theta_of(roughness[:, r0:r1], normal[:, r0:r1]), f))
        yc, vc, tc0 = torch.cat(yc, dim=-2), torch.cat(vc, dim=-2), torch.cat(tc0, dim=-2)
        pc = _pool(points.permute(2, 0, 1), f).permute(1, 2, 0)
        hc, wc = yc.shape[-2:]
        flat = lambda t: t.reshape(t.shape[0], hc * wc)  # noqa: E731
        prob = _problem(
            yc.reshape(k, 3, -1),
            vc.reshape(k, 1, -1),
            geometry(lights, pc.reshape(-1, 3)),
            flat(_pool(diffuse, f)),
            flat(_pool(specular, f)),
            flat(tc0),
            cfg,
            strength,
        )
        theta = grid_start(prob, flat(tc0))
        theta, _ = levenberg_marquardt(prob, theta, cfg.iterations)
        delta = (theta - flat(tc0)).reshape(3, hc, wc)
        correction = F.interpolate(delta[None], scale_factor=f, mode="bilinear", align_corners=False)[0, :, :h, :w]
    coarse_done = f > 1 and cfg.iterations > 0

    out = {
        "diffuse": torch.empty(3, h, w),
        "specular": torch.empty(3, h, w),
        "theta": torch.empty(3, h, w),
    }
    conf = {name: torch.empty(1, h, w) for name in ("diffuse", "specular", "roughness", "normal")}
    rows = max(1, cfg.tile_pixels // w)
    passes = reweight_passes(cfg, k)
    more = cfg.more_iterations if k >= cfg.more_from else 0
    tiles = math.ceil(h / rows)
    # every stride-th pixel's values (by its place in the image, so the same whatever the
    # tiles) measure the noise between sweeps: NOISE_SAMPLE values or so
    stride = max(1, h * w * k * 3 // NOISE_SAMPLE)
    tau = cfg.tau
    for sweep in range(passes + 1):
        last = sweep == passes
        samples: list[tuple[Tensor, Tensor]] = []
        for done, r0 in enumerate(range(0, h, rows)):
            r1 = min(h, r0 + rows)
            px = lambda t, r0=r0, r1=r1: t[..., r0:r1, :].reshape(*t.shape[:-2], -1)  # noqa: E731
            y, v = read(r0, r1)
            args = (
                y.reshape(k, 3, -1),
                v.reshape(k, 1, -1),
                geometry(lights, points[r0:r1].reshape(-1, 3)),
                px(diffuse),
                px(specular),
            )
            # θ's start per band (a full-size copy would be 12 bytes a pixel more)
            theta_start = _theta_of(roughness[:, r0:r1], normal[:, r0:r1]).reshape(3, -1)
            prob = _problem(*args, theta_start, cfg, strength)
            if sweep == 0:
                theta = theta_start
                if correction is not None:
                    theta = (theta_start + px(correction)).clamp(THETA_LOW, THETA_HIGH)
                if not coarse_done:  # small images: no coarse level
                    theta = grid_start(prob, theta)
            else:  # the weights from the model the last sweep fitted (module doc)
                theta = px(out["theta"])
                m = _model_of(px(out["diffuse"]), px(out["specular"]), theta, prob.geo)
                prob = replace(prob, wt=args[1].expand_as(m) / (m + tau) ** 2, sw=None)
            theta, jtj = levenberg_marquardt(prob, theta, cfg.fine_iterations, more)
            a, s1, s0 = bases(theta, prob.geo)
            rho, f0, haa, hss = linear_solve(prob, a, s1, s0)
            shape = (r1 - r0, w)
            out["diffuse"][:, r0:r1] = rho.reshape(3, *shape)
            out["specular"][:, r0:r1] = f0.reshape(3, *shape)
            out["theta"][:, r0:r1] = theta.reshape(3, *shape)
            conf["diffuse"][0, r0:r1] = (haa / (haa + prob.lam_d).clamp_min(1e-12)).mean(0).reshape(shape)
            conf["specular"][0, r0:r1] = (hss / (hss + prob.lam_s).clamp_min(1e-12)).mean(0).reshape(shape)
            lam = prob.lam_t
            c = [jtj[i] / (jtj[i] + lam[i]).clamp_min(1e-12) for i in range(3)]
            conf["roughness"][0, r0:r1] = c[0].reshape(shape)
            conf["normal"][0, r0:r1] = ((c[1] + c[2]) / 2).reshape(shape)
            if not last:  # the picked pixels' model and residuals, for the noise's measure
                pick = (torch.arange(r0 * w, r1 * w) % stride == 0).nonzero()[:, 0]
                m = (rho[None, :, pick] * a[..., pick] + f0[None, :, pick] * s1[..., pick] + s0[..., pick]).clamp_min(0)
                kept = (args[1][..., pick] > 0).expand_as(m)
                samples.append((m[kept], (prob.y[..., pick] - m)[kept].abs()))
            if progress is not None:
                progress(sweep * tiles + done + 1)
        if not last:
            tau = noise_tau(torch.cat([m for m, _ in samples]), torch.cat([r for _, r in samples]), cfg)
            if tau <= cfg.tau:  # the photos are no noisier than τ assumes: the first sweep's maps stand
                if progress is not None:
                    progress((passes + 1) * tiles)
                break
    theta = out.pop("theta")
    out["roughness"] = theta[0:1].clamp(0.02, 1)
    out["normal"] = normal_of(theta.reshape(3, -1)).reshape(3, h, w)
    return out, conf
