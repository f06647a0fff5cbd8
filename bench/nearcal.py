"""Near-light positions from the photos alone: the joint fit ``--self-calibrate-positions``
uses (``--joint``), the bound on any estimator (``--bound``), and earlier estimators that
failed, kept for the record (docs/rti.md).

A simulated dome24 whose LEDs are ±5 mm off their rig-file positions (uniform per axis,
each LED's axis still aimed at the centre) and ±20% in brightness photographs a material
(8-bit sRGB, read noise 0.002). Then:

1. the intensities are self-calibrated as ``--self-calibrate`` does, and the maps fitted
   with the rig file's positions;
2. the positions are estimated by variable projection: under a Lambertian model each
   pixel's b = ρ·n is the 3 × 3 least-squares solution given the lights, so the misfit
   of the photos (grey, over the (pixel, photo) pairs that are unsaturated, lit and
   mostly diffuse by the fit of step 1) is a function of the 72 light coordinates and
   24 gains alone, minimised by L-BFGS;
3. the intensities are self-calibrated again with the new positions and the maps fitted.

Printed per material: the positions' mean and largest error (mm), and the novel-light
PSNR (dB, sRGB) of fits with the true dome ("ideal"), the rig file ("nominal"), the
self-calibrated intensities ("gains") and the estimated positions too ("+positions").
``--matte`` zeroes the materials' specular maps first: there the positions of three of
the four come back within 2 mm (the leather's relief leaves too few usable pixels); with
the materials' own specular they do not (docs/rti-record.md gives the numbers).

``--prior=K`` adds K × Σ (offset / 5 mm)² to the (scaled) misfit, a pull toward the rig
file's places; ``--only=NAME[,NAME...]`` runs the materials whose names start so.

``--full`` replaces step 2's Lambertian model by the ``lm`` solver's own per-pixel model
(diffuse, F0, roughness and normal; ρ and F0 projected out in closed form, every hold
10⁻⁴ of the solver's): the misfit at given positions is that of the per-pixel fit there,
and L-BFGS moves the 72 coordinates by its gradient at the fitted maps (the maps refitted,
warm, by 8 Levenberg–Marquardt steps at every evaluation), 6 rounds of 20 evaluations.
It uses every pixel and photo, so no fit made with the wrong lights chooses them.

``--joint`` replaces steps 2 and 3 by ``matscan.reconstruct.lightpos.estimate_positions``
(what ``reconstruct --self-calibrate-positions`` runs): positions, gains and every pixel's
maps fitted together by Gauss–Newton with the pixels eliminated, then the maps fitted
with its positions and gains (their gradient across the dome and overall factor removed).
``--pairs=K`` removes the fit's bias measured with K antithetic pairs of replicas
(``lightpos.BIAS_PAIRS``, 0 by default), ``--steps=N`` sets the Gauss–Newton steps
(``ITERATIONS``, 10, and ``SHARED_ITERATIONS``, 20; the replicas need the fit settled:
``--own-f0 --steps=30 --pairs=1``) and
``--side=N`` fits on N pixels along the longer side (``POSITION_SIDE``).
``--pairs-radial`` (with ``--pairs=1``) removes only the bias's common radial part, the
dome's scale (``lightpos.BIAS_RADIAL``); ``--pair-seed=K`` draws the pairs' noise from
another seed (``lightpos.PAIR_SEED``); ``--replica-searched`` fits each replica from
a second, searched start too (``lightpos.REPLICA_SEARCHED``); ``--pairs-iterated`` measures
the pair's bias again at each replica's end and removes twice the first less the second
(``lightpos.BIAS_ITERATED``); ``--replica-fence=K`` renders the replicas with the
roughness beyond K interquartile ranges outside its quartiles set to the median
(``lightpos.REPLICA_FENCE``). ``--parts`` prints under each material what
each part of the fitted lights' error costs: the maps fitted at the true places moved by
that part alone (radial, along each light's direction from the sample's centre;
tangential; the mean shift; the mean radial shift, signed, + where the fitted dome is
too large; vertical), with the fitted gains, and
at the true places. ``--bound`` prints beside the bound the standard deviation it gives
the lights' mean radial shift and the rig file's own mean radial error.
``--second-order`` removes instead the bias its second-order formula gives
(``lightpos.SECOND_ORDER``; with ``--own-f0 --steps=30``). The joint fit shares one F0
among the dielectric pixels (``lightpos.SHARED_F0``, the default since its rule held under
the level convention, 20 steps); ``--own-f0`` fits each pixel's own instead, in 10 steps,
as every run before that did (``--shared-f0`` named the shared one then, with
``--steps=20``; both still read so, and reproduce those runs).
``--gradient=A`` multiplies the LEDs' brightness by exp(A · x), x the x component of each
LED's direction from the centre (A = 0.1: about ±9% from one side of the dome to the
other), a gradient the self-calibration takes as none (a tilted sample looks alike);
``--drawn-gradient`` keeps the gradient each draw of ±20% LEDs has (median 0.057),
which the bench's draws otherwise remove. ``--level`` and ``--no-level`` set the
self-calibration's convention (``selfcal.LEVEL``): the sample level and the gradient in
the gains (the default since it passed its rule, docs/rti-record.md), or no gradient (the
convention every table before that rule was made under).
``--record`` prints under each fitted material the joint fit's record (``matscan.json``'s
``positions``): the pixels used, the misfit at its start and end, and the shared F0; then
the angle of the one turn of the whole dome about the sample's centre that brings the
fitted positions nearest the true ones (a tilt of the sample looks the same), and their
error without it.
``--split`` prints under each fitted material the gains' RMS error and the PSNR of maps
fitted with the fitted positions and the true gains, and with the true positions and the
fitted gains (which of the two the relighting follows), and the mean slope of the fitted
maps' normals (how far the fit tilted the sample as a whole).
Where the intensities could not be read (too little diffuse reflection: the record's
``updated`` is false), reconstruct keeps the rig file's places, and so does the bench
(marked *; reconstruct now fits the gains there with the lights held: ``--held-gains``).

``--at-bound=R`` asks what an estimator at that bound would relight at: R times, the
lights' positions and log gains are drawn from the bound's joint distribution (the photos
and the rig file's ±5 mm; each channel's overall gain held) and the maps fitted there as
the final reconstruction fits them; it prints the ideal dome's novel-light PSNR, the
draws' mean and worst, how many came within 0.5 dB of the ideal, their mean position
error and the bound's RMS.
``--held-gains`` (with ``--joint``) adds under each material whose intensities are unread
a line "held gains": the gains the joint fit finds with every light held at the rig file's
place (``lightpos.estimate_held_gains``, what ``reconstruct --self-calibrate-positions``
now does there), and the relighting with them there; the line marked * above it keeps the
rig file's intensities, as reconstruct did before.
``--profile`` (with ``--joint``, under each material whose intensities are unread) asks
whether placing those lights fails by its start or by what it fits: it runs the joint fit
(as ``estimate_positions`` runs it) from the rig file's places with the held gains, and
from the true places with the true gains and with the held gains, and prints each end's
position error, its relighting (the maps fitted there with the fit's gains; the places
after any level turns, the error and misfit before them) and its profile misfit: the
misfit per value left when the gains and every pixel's maps are fitted again (30 steps
from the first fit's start maps) with the lights held there, on the pixels and under the
noise model of the fit from the true places and gains, so that all are in one unit; then
the same misfit at the true places and at the rig file's. An end whose profile misfit is
above another's stopped in a worse valley or short (a start's failing); the truth's above
an end's means the misfit itself prefers that end, as far as the refit finds (the
estimator's bias); the differences, times the values counted, are in units of the
noise's variance (Δχ²). The refit starts from one set of maps and may stop above what a
fit's own path found at its end: a line "from ..." before the profiles gives each fit's
ends' own misfits (``--record``'s ``misfit_per_value``, in the units of that fit's noise
model, which its starts share; the first fit's is the profiles').
``--bound`` prints instead the Cramér–Rao bound of the positions given the true maps and
the camera's noise: the RMS error (mm) of any unbiased estimator that fits positions,
gains and maps from these photos, alone and with the rig file's ±5 mm as a prior.

``--calibrated-on=NAME[,NAME...]`` (with ``--joint``; each NAME the start of a name in the
bench's lists, :func:`listed`: paper, brick, leather, plastic, woven_plain, ...)
calibrates each material's dome on NAME's photos under the same LEDs instead (their own
camera noise; ``--self-calibrate-positions`` as it ships), and fits the material's photos
with the lights and gains found there, as ``reconstruct --calibration`` fits a later
capture with an earlier one's ``self_calibration.json``; with several NAMEs, with their
calibrations merged as ``calibrate --merge`` merges them (those whose intensities could
not be read left out, and any it finds astray). It prints the calibration's position
error, the ideal dome's novel-light PSNR and the calibration's, and the difference
(docs/rti.md, "A dome calibrated once"). ``--then-fit`` self-calibrates each material from
there too (``reconstruct --calibration FILE --self-calibrate-positions``: the joint fit
starts at the calibration's places and scales, or holds them where the material's
intensities cannot be read) and prints that fit's position error, PSNR and shortfall after
("(held)": the places held and the intensities fitted with them; "(kept)": the
calibration's intensities and places kept as they are; "refused": the intensities'
estimate was refused as no better); ``--calibrated-spread=S`` fits them from there with a
prior of S mm per axis about the calibration's places, and fits them even where the
intensities were right already (``lightpos.CALIBRATED_SPREAD_MM``; without it the places
are held there); ``--calibrated-common`` fits them from there too where the intensities
were right already, the lights moved only together (one shift and the dome's scale:
``lightpos.CALIBRATED_COMMON`` "confirmed"; ``=always``: every material so).
``--merge-weighted`` merges the calibrations' places weighted
(``calibrate.MERGE_WEIGHTED``). ``--calibrations-only`` prints instead each calibration's
position error and mean radial shift (in brackets; + too far out) and the merge's, and
fits nothing. ``--calibration-cache=DIR`` keeps each calibration in DIR (by NAME, side,
seed and the material's index, which is what the dome's draw depends on: the four,
``--held-out`` and ``--others`` share domes by index) and reads it there in later runs,
nothing else changed; the cache is the user's to clear when the code changes.

``--oracle-pair`` prints instead the antithetic pair's bias (as ``--pairs=1 --pairs-radial``
measures it at the fit's end) measured at the truth: the replicas rendered from the true
maps (their dielectric pixels' F0 the shared F0's scan, as the fit shares it; their own
roughness, not the scan's), the true
places and the true gains (128², where the joint fit uses every pixel), each fitted as the
photos are: the shift of the lights' mean radial place (mm, + outward) and the mean of
each light's shift, beside which the pair at the fit's end (the record's ``radial_mm``) can be read.
``--hybrid-pair=maps`` (with ``--joint --pairs=1 --pairs-radial``) measures the pair at the
fit's end with the fit's maps replaced by the true ones, ``--hybrid-pair=lights`` with its
lights' places replaced by the true ones (``--hybrid-pair=maps:roughness``, ``:normal``,
``:diffuse`` or ``:f0``: that part of the maps alone), and prints that pair's mean radial
shift; ``--hybrid-pair=stats`` prints instead the quantiles of the fit's roughness and the
true one at the fit's pixels, and removes nothing.

``--from-truth`` starts the joint fit (``fit_positions``, its bias left in, 30 steps; with
``--own-f0`` as every run of it before the shared F0 became the default) at
the true lights, gains and maps and prints how far it drifts (mm; and the lights' mean
radial shift, signed) and where it leaves the
shared F0 (its value, the scan's and its standard error ``se``): with the camera's
noise, or with ``--from-truth=S`` on float photos with Gaussian noise S alone,
``--from-truth=shot`` with the camera's shot and read noise in 16-bit linear files, and
``--from-truth=steps`` with the camera's 8-bit steps and no noise. ``--reduced`` fits
it on as many pixels as the joint fit uses (every ⌈side / ``POSITION_SIDE``⌉-th: at 256²,
every second, from the first, where the joint fit takes each block's centre; the photos
rendered at that side), not every pixel. Diagnostics of what carries
the bias: ``--no-reseed`` searches no pixel's roughness again (``_RESEED_GRID``),
``--pin-roughness`` also holds each pixel's roughness at its start (the truth), and
``--f0-grid=V[,V...]`` sets the shared F0's scan (``_F0_GRID``; one value with
``--hold-f0`` holds it there). ``--true-start`` (with ``--joint``) starts the
joint fit from the true maps instead of the ``lm`` solver's at the rig file's places: what
the start's maps cost; ``--start-prior=K`` fits the start's maps with the ``lm`` solver's
priors times K (``lightpos.START_PRIOR``, 1 by default), ``--start-roughness-prior=K``
with its roughness prior alone times K (``START_ROUGHNESS_PRIOR``), the maps after it
as before. ``--weak-start=K`` adds a third start, the solver's maps with its priors times
K, whose end is kept where it fits the photos better (``lightpos.WEAK_START``; ``--record``
prints each start's misfit at its end, ``ends``), ``--weak-margin=M`` keeps it only where
its misfit is lower by more than the share M (``lightpos.WEAK_MARGIN``); where its end was
kept, a last line "without weak" gives the same photos' fit without it (the default), so
that the two pair. ``--ends`` prints each start's end (its misfit, its lights' error
before the turns and its distance from the rig file's places, its shared F0 and share, its
median roughness). ``--weak-own`` fits the third start with its own pixels sharing an F0
and its own scan (``lightpos.WEAK_SAME`` False; by default those of the first start, so
that the three ends fit the same unknowns). ``--ends-by=nearest`` keeps the end whose lights
lie nearest the rig file's places (``lightpos.ENDS_BY``); where it kept another than the
defaults would, a last line "as default" gives the same photos' fit with the defaults.

``--variants`` (with ``--own-f0 --steps=30 --pairs=1``) scores the joint fit four ways: its end
with the bias left in, the pair's correction on positions and gains (``BIAS_PAIRS``), on
the positions alone and on the gains alone.

``--versus-choose`` compares, per material, ``reconstruct --self-calibrate-positions``
under ``--led-gradient auto`` as it was before ``selfcal.CHOOSE`` (the level convention,
with its fallback) and ``choose`` (both conventions, the better re-rendering kept,
without the tie-breaker, as on draws 3 and 4): the convention each kept, and where the
two kept different intensities the final novel-light PSNR of each beside the ideal
dome's (where they kept the same, the reconstruction is the same and is not run), and
the re-rendering RMSE of each convention's estimate, which ``choose`` compared.

``--versus-tie=G`` compares in the same way ``auto`` without a tie-breaker and with
``selfcal.TIE_GRADIENT`` G: where the two re-renderings tie within ``CHOOSE_MARGIN``, the
estimate without a gradient kept if the level gains' gradient is at least G.

``--slopes`` estimates the intensities under each convention alone and prints their
re-rendering RMSEs, the ratio ``choose`` compares (none / level), and the length of the
gradient across the dome (``selfcal.gradient``) of the level estimate's gains beside the
true gains': whether a tilt read as a gradient stands out from the LEDs' own, to break
the ties ``CHOOSE_MARGIN`` leaves to the level convention.

``--level-start`` starts the joint fit from the ``lm`` solver's maps laid level (their
median slope removed; ``lightpos.LEVEL_START``): under the level convention the fit
holds the slopes' sum where its start put it, and the solver's maps, fitted at the rig
file's places, come out tilted. ``--grey-f0`` makes the shared F0 one number for the
three channels (``lightpos.GREY_F0``); ``--hold-f0`` holds it at its scan's value through
the steps (``lightpos.HOLD_F0``; ``--record`` prints both, ``scanned`` and ``value``).
``--place-prior=S`` gives the joint fit the rig file's places as a Gaussian prior of S mm
a axis (``lightpos.PLACE_SPREAD_MM``; the dome's ±5 mm uniform is 2.9 mm).
``--polish=K`` gives each pixel's best roughness in another valley K Levenberg–Marquardt
steps whenever the roughness is searched again, kept where it fits better
(``lightpos.POLISH``), ``--polish-margin=M`` only where better by more than M
(``lightpos.POLISH_MARGIN``).
``--validate-choice`` prints under each fitted material the re-rendering error of 6 photos
left out (``reconstruct --validate 6``) with the fitted lights and with the rig file's
places and the intensities alone: whether the photos could tell which relights better (on
the paper at 256² they could not, docs/rti-record.md). The fitted near lights are turned about
the sample's centre until the solver's maps at them lie level, at most K times
(``lightpos.LEVEL_TURNS``, 6 by default; ``--level-turns=K`` sets it, 0 turns nothing),
under the level convention only (where ``auto`` keeps the estimate without a gradient,
nothing is turned); a second line, "before turns", gives the same fit's lights before the
turns and its relighting with them, which is what no turns give, from one joint fit.
``--level-by=A[,B...]`` says what level means for the turns (``lightpos.LEVEL_BY``:
``base``, the default, ``agreed`` or ``median``); each after the first turns the same
fit's lights from where the first's started, on a line of its own.
``--levels`` prints, for each material, its true maps' slope by the median, the 10%
trimmed mean, the two's agreement (``selfcal.agreed_slope``) and the base plane
(``selfcal.base_slope``), and fits nothing.

``--outlier=K`` and ``--robust=C`` set ``lightpos.OUTLIER`` and ``ROBUST``. ``--seed=S``
draws another dome for each material (the LEDs' offsets and brightnesses and the camera's
noise; the materials stay the same); 0, the default, is the draw of the tables in docs/rti-record.md.
``--held-out`` runs bench/selfcal.py's 13 held-out materials instead of the four, and
``--others`` the 8 of its 12 that are not among the four.

Run by hand: .venv/bin/python bench/nearcal.py [--joint|--bound|--at-bound=R|--full|--matte] [--prior=K]
[--pairs=K] [--pairs-radial] [--pairs-iterated] [--replica-fence=K] [--pair-seed=K] [--replica-searched] [--parts]
[--second-order] [--shared-f0|--own-f0] [--split] [--record] [--gradient=A] [--drawn-gradient]
[--[no-]level] [--level-start] [--level-turns=K] [--level-by=A,B] [--grey-f0] [--hold-f0] [--no-fallback] [--gains-only]
[--tilt=DEG] [--levels] [--choose] [--versus-choose]
[--versus-tie=G] [--slopes] [--steps=N] [--side=N] [--seed=S]
[--oracle-pair] [--hybrid-pair=maps[:PART]|lights|stats] [--from-truth[=S|shot|steps]] [--reduced] [--no-reseed]
[--pin-roughness] [--f0-grid=V,...]
[--true-start] [--start-prior=K] [--start-roughness-prior=K] [--weak-start=K] [--weak-margin=M] [--weak-own]
[--ends-by=A] [--ends] [--place-prior=S] [--polish=K] [--polish-margin=M]
[--variants] [--validate-choice] [--held-gains] [--profile]
[--calibrated-on=NAME,...] [--then-fit] [--calibrated-spread=S] [--calibrated-common[=always]] [--merge-weighted]
[--calibrations-only]
[--calibration-cache=DIR] [--held-out|--others] [--only=NAMES]
[SIZE]   (default 128)
"""

from __future__ import annotations

import contextlib
import importlib
import json
import math
import pathlib
import sys
import time
from collections.abc import Callable
from dataclasses import replace

import torch

from matscan.anyrig import tilted
from matscan.capture import Capture
from matscan.capture.folder import Correction
from matscan.capture.virtual import CameraModel, apply_camera, simulate_images
from matscan.color import linear_to_srgb
from matscan.mapset import MapSet
from matscan.materials.artist import artist_material
from matscan.materials.photos import photo_material
from matscan.materials.procedural import generate
from matscan.reconstruct import ReconstructConfig, lightpos, lm, reconstruct_capture
from matscan.reconstruct import selfcal as estimator
from matscan.reconstruct.lightpos import estimate_positions, fit_positions
from matscan.reconstruct.lm import SolverConfig
from matscan.reconstruct.selfcal import DIFFUSE_SHARE, LIT, estimate_gains, with_gains
from matscan.render import render_maps, surface_points
from matscan.rig import LightSet, builtin_rig

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from selfcal import led_gains, novel_psnr  # noqa: E402


def moved(lights: LightSet, delta: torch.Tensor) -> LightSet:
    """The lights moved by delta (L, 3) mm, their axes still aimed at the origin."""
    pos = lights.position + delta
    return replace(lights, position=pos, axis=-pos / pos.norm(dim=-1, keepdim=True))


def shading(pos: torch.Tensor, exponent: torch.Tensor, ref_mm: float, pts: torch.Tensor) -> torch.Tensor:
    """(R/d)² · lobe · l for lights at pos (L, 3) aimed at the origin, at points (P, 3): (L, P, 3)."""
    lv = pos[:, None, :] - pts[None]
    d2 = (lv * lv).sum(-1)
    l = lv / d2.sqrt()[..., None]
    axis = -pos / pos.norm(dim=-1, keepdim=True)
    lobe = (-(l * axis[:, None, :]).sum(-1)).clamp_min(1e-12) ** exponent[:, None]
    return (ref_mm**2 / d2 * lobe)[..., None] * l


def varpro_positions(cap: Capture, fit, rounds: int = 6, prior: float = 0.0, tolerance_mm: float = 5.0) -> torch.Tensor:
    """Light positions (L, 3) minimising the Lambertian misfit with ρ·n projected out,
    plus ``prior`` × Σ (offset / tolerance_mm)² against the misfit at the rig file's places."""
    n = len(cap.files)
    lights = cap.lights
    with torch.no_grad():
        pred = render_maps(fit.maps, lights, cap.field_mm, fit.intensity_scale)
        matte = MapSet(**{**fit.maps.present(), "specular": torch.zeros_like(fit.maps.specular)})
        diffuse = render_maps(matte, lights, cap.field_mm, fit.intensity_scale)
    photo = cap.linear(list(range(n)))
    use = ((~cap.saturation(list(range(n)))).expand_as(pred) & (pred > LIT) & (diffuse > DIFFUSE_SHARE * pred)).all(1)
    h, w = photo.shape[-2:]
    pts = surface_points(cap.field_mm, (h, w), dtype=torch.float64).reshape(-1, 3)
    y = photo.double().mean(1).reshape(n, -1)
    wt = use.reshape(n, -1).double()
    keep = wt.sum(0) >= 8  # a pixel seen lit and diffuse in at least 8 photos
    y, wt, pts = y[:, keep], wt[:, keep], pts[keep]
    p0 = lights.position.double()
    exponent = lights.exponent.double()
    dz = torch.zeros(n, 3, dtype=torch.float64, requires_grad=True)
    log_gain = torch.zeros(n, dtype=torch.float64, requires_grad=True)

    def misfit() -> torch.Tensor:
        s = (
            shading(p0 + dz, exponent, lights.reference_distance_mm, pts)
            * (log_gain - log_gain.mean()).exp()[:, None, None]
        )
        a = torch.einsum("np,npi,npj->pij", wt, s, s) + 1e-9 * torch.eye(3, dtype=torch.float64)
        b = torch.linalg.solve(a, torch.einsum("np,npi,np->pi", wt, s, y))
        e = y - torch.einsum("npi,pi->np", s, b)
        return (wt * e * e).sum() / wt.sum()

    scale = float(misfit().detach())  # L-BFGS stops early on a misfit of order 1e-5 unless scaled

    def objective() -> torch.Tensor:
        return misfit() / scale + prior * (dz / tolerance_mm).square().sum()

    opt = torch.optim.LBFGS(
        [dz, log_gain], max_iter=200, line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-15
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    for _ in range(rounds):
        opt.step(closure)
    return (p0 + dz).detach().float()


def full_positions(cap: Capture, rounds: int = 6, hold: float = 1e-4) -> torch.Tensor:
    """Light positions (L, 3) minimising the misfit of the solver's per-pixel model fitted
    at them (``--full``, module doc)."""
    n = len(cap.files)
    lights = cap.lights
    y = cap.linear(list(range(n))).reshape(n, 3, -1)
    valid = (~cap.saturation(list(range(n)))).float().reshape(n, 1, -1)
    h, w = cap.size
    pts = surface_points(cap.field_mm, (h, w)).reshape(-1, 3)
    base = SolverConfig(censored=False)  # saturated values dropped, as when its results were measured
    cfg = replace(
        base,
        prior_diffuse=base.prior_diffuse * hold,
        prior_specular=base.prior_specular * hold,
        prior_roughness=base.prior_roughness * hold,
        prior_normal=base.prior_normal * hold,
    )
    p_count = y.shape[-1]
    rho0, f00 = torch.full((3, p_count), 0.5), torch.full((3, p_count), 0.04)
    theta0 = torch.tensor([0.5, 0.0, 0.0])[:, None].expand(3, p_count).clone()
    p0 = lights.position.clone()

    def problem(pos: torch.Tensor):
        return lm._problem(y, valid, lm.geometry(moved(lights, pos - p0), pts), rho0, f00, theta0, cfg, 1.0)

    def fit(pos: torch.Tensor, theta: torch.Tensor | None, iterations: int) -> torch.Tensor:
        with torch.no_grad():
            p = problem(pos)
            theta = lm.grid_start(p, theta0.clone()) if theta is None else theta
            return lm.levenberg_marquardt(p, theta, iterations)[0]

    def misfit(pos: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        r, _, _ = lm.residuals(problem(pos), theta)
        return (r * r).sum()

    dz = torch.zeros(n, 3, requires_grad=True)
    state = {"theta": fit(p0, None, 30)}
    scale = float(misfit(p0, state["theta"]))
    opt = torch.optim.LBFGS(
        [dz], max_iter=20, history_size=20, line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-15
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        state["theta"] = fit((p0 + dz).detach(), state["theta"], 8)
        loss = misfit(p0 + dz, state["theta"]) / scale
        loss.backward()
        return loss

    for _ in range(rounds):
        opt.step(closure)
    return (p0 + dz).detach()


def camera_variance(x: torch.Tensor, camera: CameraModel) -> torch.Tensor:
    """The variance of a stored linear value around x: shot and read noise (apply_camera's
    model) and the uniform error of rounding to an sRGB code, through the decoding's slope."""
    top = (1 << camera.bits) - 1
    v = linear_to_srgb(x.clamp(0, 1))
    slope = torch.where(v > 0.04045, 2.4 / 1.055 * ((v + 0.055) / 1.055) ** 1.4, torch.full_like(v, 1 / 12.92))
    return x.clamp_min(0) / camera.full_well + camera.read_noise**2 + (slope / top) ** 2 / 12


def bound(maps: MapSet, true: LightSet, gains: torch.Tensor, rig, camera: CameraModel) -> tuple[float, float]:
    """The Cramér–Rao bound of the LED positions given these photos: the RMS error (mm) of
    an unbiased estimator that fits positions, gains and every pixel's maps, and with the
    rig file's ±5 mm as a prior (uniform, σ 5/√3 per axis) as well."""
    s = information(maps, true, gains, rig, camera)
    k = 3 * len(gains)
    photos_alone = torch.linalg.pinv(s, hermitian=True, rtol=1e-12)[:k, :k]
    s[:k, :k] += torch.eye(k, dtype=torch.float64) / (5 / 3**0.5) ** 2
    with_prior = torch.linalg.pinv(s, hermitian=True, rtol=1e-12)[:k, :k]
    n = len(gains)
    return float(photos_alone.trace() / n) ** 0.5, float(with_prior.trace() / n) ** 0.5


def information(maps: MapSet, true: LightSet, gains: torch.Tensor, rig, camera: CameraModel) -> torch.Tensor:
    """The Fisher information of the lights' 6N numbers (positions, then log gains, as
    ``lightpos.normal_equations`` orders them) in these photos, every pixel's 9 numbers
    eliminated (their Schur complement)."""
    f64 = torch.float64
    h, w = maps.size
    pts = surface_points(rig.field_mm, (h, w), dtype=f64).reshape(-1, 3)
    spec = maps.specular.double().reshape(maps.specular.shape[0], -1).expand(3, -1)
    theta = lm._theta_of(maps.roughness.double(), maps.normal.double()).reshape(3, -1)
    th = torch.cat([maps.diffuse.double().reshape(3, -1), spec, theta])
    lights = replace(
        true,
        position=true.position.double(),
        axis=true.axis.double(),
        intensity=true.intensity.double(),
        exponent=true.exponent.double(),
        camera=true.camera.double(),
        camera_w=true.camera_w.double(),
        w=true.w.double(),
    )
    aims = torch.zeros(len(gains), 3, dtype=f64)  # dome24 aims every LED at the origin
    m = lightpos._render(th, lightpos._placed(lights, aims, lights.position, gains.double()), pts)
    wt = torch.where(m < 1, 1 / camera_variance(m, camera), torch.zeros_like(m))  # saturated: nothing
    a, gp, b, c, gl = lightpos.normal_equations(th, lights, aims, gains.double(), pts, wt, m)
    return lightpos.reduced_system(a, gp, b, c, gl, 0.0)[1]


def at_bound(name: str, cap: Capture, cfg, maps: MapSet, true: LightSet, gains, rig, draws: int, seed: int) -> None:
    """What an estimator at the bound would relight at: lights drawn ``draws`` times from
    the bound's joint distribution of positions and log gains (photos and the rig file's
    ±5 mm, the gains' overall factor per channel held, as the joint fit holds it), the
    maps fitted at each as the final reconstruction fits them. Prints the ideal dome's
    PSNR, the draws' mean and worst, how many came within 0.5 dB of the ideal, the
    draws' mean position error, and the bound's RMS."""
    f64 = torch.float64
    n = len(gains)
    s = held_information(maps, true, gains, rig, CameraModel(read_noise=0.002))
    val, vec = torch.linalg.eigh(s)
    root = vec * val.clamp_min(1e-12 * float(val.max())).rsqrt()  # δ = root · z has the covariance s⁻¹
    z = torch.randn(6 * n, draws, generator=torch.Generator().manual_seed(seed), dtype=f64)
    deltas = (root @ z).T
    ideal = reconstruct_capture(with_gains(lightpos._lit_from(cap, true.position), gains), cfg)
    best = novel_psnr(ideal.maps, ideal.intensity_scale, maps, rig.field_mm)
    psnr, err = [], []
    for d in deltas:
        pos = true.position + d[: 3 * n].reshape(n, 3).float()
        g = gains * d[3 * n :].reshape(n, 3).float().exp()
        res = reconstruct_capture(with_gains(lightpos._lit_from(cap, pos), g), cfg)
        psnr.append(novel_psnr(res.maps, res.intensity_scale, maps, rig.field_mm))
        err.append(float((pos - true.position).norm(dim=1).mean()))
    rms = float(torch.linalg.pinv(s, hermitian=True)[: 3 * n, : 3 * n].trace() / n) ** 0.5
    within = sum(p >= best - 0.5 for p in psnr)
    print(
        f"{name:16s} {best:6.2f} {sum(psnr) / draws:7.2f} {min(psnr):7.2f} {within:4d} of {draws}"
        f" {sum(err) / draws:7.2f} {rms:6.2f}",
        flush=True,
    )


def variants(
    name: str, cap: Capture, g1: torch.Tensor, cfg, maps: MapSet, true: LightSet, gains, rig, level: bool
) -> None:
    """The joint fit run as ``estimate_positions`` runs it, then scored four ways: its end
    (the bias left in), the pair's correction applied to the positions and log gains (as
    ``BIAS_PAIRS`` does), to the positions alone and to the gains alone: positions' mean
    error (mm), the gains' RMS error (%, their overall factor and tilt removed) and the
    novel-light PSNR (dB). ``level``: the intensities' convention (their record's)."""
    debiased, got = lightpos._debiased, {}

    def spy(photos, fit, pairs, iterations, progress=None):
        pos, lg, rec = debiased(photos, fit, pairs, iterations, progress)
        got.update(fit=fit, pos=pos, lg=lg)
        return pos, lg, rec

    lightpos._debiased = spy
    try:
        estimate_positions(cap, g1, cfg, level=level)
    finally:
        lightpos._debiased = debiased
    fit = got["fit"]
    scores = []
    for pos, lg in ((fit.pos, fit.lg), (got["pos"], got["lg"]), (got["pos"], fit.lg), (fit.pos, got["lg"])):
        lights = lightpos._lit_from(cap, pos.float()).lights
        g = estimator.gauged(lg.exp().float(), cap.lights, level)
        res = reconstruct_capture(with_gains(replace(cap, lights=lights), g), cfg)
        off = (g / gains).log()
        off = off - off.mean(0)
        psnr = novel_psnr(res.maps, res.intensity_scale, maps, rig.field_mm)
        err = float((pos.float() - true.position).norm(dim=1).mean())
        scores.append(f"{err:5.2f} {100 * float(off.square().mean().sqrt()):5.2f} {psnr:6.2f}")
    print(f"{name:16s} " + "  |  ".join(scores), flush=True)


def mean_slope(maps: MapSet) -> tuple[float, float]:
    """The mean of the normals' slopes (n_x / n_z, n_y / n_z) over the image: how far a
    fit tilted the sample as a whole."""
    n = maps.normal.reshape(3, -1)
    return float((n[0] / n[2]).mean()), float((n[1] / n[2]).mean())


def versus(name: str, cap: Capture, cfg: ReconstructConfig, maps: MapSet, true: LightSet, gains, rig, sides) -> None:
    """``--versus-choose`` and ``--versus-tie``: the intensities of two ways (``sides``, a
    name for each with its ``led_gradient`` and the selfcal settings it runs under) and,
    where they differ, both reconstructions with the positions fitted, as reconstruct does.
    Each convention's rounds run once and serve both ways (they are deterministic)."""
    ends, rounds, real = {}, {}, estimator._rounds

    def once(small, fit_cfg, level, count):
        if level not in rounds:
            rounds[level] = real(small, fit_cfg, level, count)
        return rounds[level]

    for side, (way, settings) in sides.items():
        was = {k: getattr(estimator, k) for k in settings}
        for k, v in {**settings, "_rounds": once}.items():
            setattr(estimator, k, v)
        try:
            g1, record = estimate_gains(cap, replace(cfg, self_calibrate=True, led_gradient=way))
        finally:
            for k, v in {**was, "_rounds": real}.items():
                setattr(estimator, k, v)
        kept = record["convention"] if record["updated"] else "none read"
        ends[side] = (g1, record, kept + (" (fallback)" if "fallback" in record else ""))
    (a, (ga, _, ka)), (b, (gb, rb, kb)) = ends.items()
    rmse = rb.get("choice")  # each convention's re-rendering RMSE, the numbers compared, and the level gradient
    if rmse is None:
        raise SystemExit(f"{name}: the second way ran one convention only (--no-level?): nothing to compare")
    line = (
        f"{name:16s} {a} {ka:24s} {b} {kb:14s} (RMSE {rmse['level sample']:.5f} / {rmse['no gradient']:.5f}, "
        f"gradient {rmse['level gradient']:.3f})"
    )
    if torch.equal(ga, gb):
        print(f"{line} same intensities", flush=True)
        return
    psnr = []
    for g1, record, _ in ends.values():
        capture = cap
        if record["updated"]:  # as reconstruct does: the positions fitted under the kept convention
            lights, g1, _, _ = estimate_positions(cap, g1, cfg, level=record["convention"] == "level sample")
            capture = replace(cap, lights=lights)
        fit = reconstruct_capture(with_gains(capture, g1), cfg)
        psnr.append(novel_psnr(fit.maps, fit.intensity_scale, maps, rig.field_mm))
    ideal = reconstruct_capture(replace(cap, lights=true, correction=Correction(None, gains, (None,) * 24)), cfg)
    best = novel_psnr(ideal.maps, ideal.intensity_scale, maps, rig.field_mm)
    gap = psnr[1] - psnr[0]
    print(f"{line} PSNR ideal {best:6.2f} {a} {psnr[0]:6.2f} {b} {psnr[1]:6.2f} ({gap:+.2f})", flush=True)


def slopes(name: str, cap: Capture, cfg: ReconstructConfig, gains: torch.Tensor, tilt: float) -> None:
    """``--slopes``: the intensities estimated under each convention alone ("fit", "none"),
    their re-rendering RMSEs and ratio (none / level, what ``choose`` compares), and the
    gradient across the dome (``selfcal.gradient``'s length, mean over channels) of the
    level estimate's gains and of the true ones: a tilt the level convention reads as a
    gradient, beside the LEDs' own."""

    ends = [estimate_gains(cap, replace(cfg, self_calibrate=True, led_gradient=w)) for w in ("fit", "none")]
    (gl, rl), (_, rn) = ends
    a, b = rl["rerender_rmse"]["after"], rn["rerender_rmse"]["after"]
    read = f"{estimator.steepness(gl, cap.lights):.4f}" if rl["updated"] else "-     "
    print(
        f"{name:16s} tilt {tilt:3.1f} RMSE level {a:.5f} none {b:.5f} ratio {b / a:.4f}  "
        f"gradient level {read} true {estimator.steepness(gains, cap.lights):.4f}",
        flush=True,
    )


def turned(pos: torch.Tensor, true: torch.Tensor) -> tuple[float, float, float]:
    """How much of the positions' error ``pos`` − ``true`` (N, 3, mm) is one turn of the
    whole dome about the sample's centre (a tilt of the sample, which the photos cannot
    tell from it): the angle (degrees) of the rotation that brings ``pos`` nearest
    ``true`` (Kabsch, no shift), and the error's mean and largest once it is removed."""
    p, t = pos.double(), true.double()
    u, _, vt = torch.linalg.svd(p.T @ t)
    d = torch.ones(3, dtype=torch.float64)
    d[2] = torch.sign(torch.linalg.det(u @ vt))
    r = u @ torch.diag(d) @ vt  # p @ r ≈ t
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(r)) - 1) / 2))))
    left = (p @ r - t).norm(dim=1)
    return angle, float(left.mean()), float(left.max())


def positions_and_unturned(cap: Capture, g1: torch.Tensor, cfg: ReconstructConfig, level: bool):
    """``estimate_positions``'s lights, gains and record, and the arguments of
    ``lightpos.LEVEL_TURNS``'s turns (None where nothing was turned): the fitted positions
    before the turns first. The turns come after the fit and change nothing else, so
    those are the positions the default gives, and other turns can start from them."""
    seen = []
    turn, solve = lightpos._turned_level, lightpos._solve
    SOLVED.clear()

    def watched(*args):
        seen.append(args)
        return turn(*args)

    def solved(*args, **kwargs):
        SOLVED.append(solve(*args, **kwargs))
        return SOLVED[-1]

    lightpos._turned_level, lightpos._solve = watched, solved
    try:
        lights, g2, fitted, _ = estimate_positions(cap, g1, cfg, level=level)
    finally:
        lightpos._turned_level, lightpos._solve = turn, solve
    return lights, g2, fitted, seen[0] if seen else None


#: The joint fit's ends (``lightpos._Solved``) from each of its starts, in the order it ran them,
#: as the last ``positions_and_unturned`` saw them (``--ends`` prints them).
SOLVED: list = []


def print_ends(true: LightSet, nominal: LightSet) -> None:
    """``--ends``: each start's end: its misfit, its lights' mean error (mm, before the
    turns) and root mean square distance from the rig file's places (``nominal``, as
    ``lightpos.ENDS_BY`` weighs it), the share of its pixels sharing one F0 and that F0,
    its pixels' median roughness."""
    parts = []
    for end in SOLVED:
        err = float((end.pos.float() - true.position).norm(dim=1).mean())
        moved = float((end.pos.float() - nominal.position).norm(dim=1).square().mean().sqrt())
        share = 0.0 if end.shared is None else float(end.shared.double().mean())
        f0 = f"{float(end.th[3, end.shared][0]):.4f}" if share > 0 else "-"
        parts.append(
            f"misfit {end.cost:.4f} {err:.2f} mm (moved rms {moved:.2f}) share {share:.2f} F0 {f0} "
            f"roughness {float(end.th[6].median()):.3f}"
        )
    print(f"{'':16s} ends: " + " | ".join(parts), flush=True)


def oracle_pair(cap: Capture, maps: MapSet, gains: torch.Tensor, size: int) -> str:
    """``--oracle-pair``: the joint fit's steps from the true lights, gains and maps of
    ``cap`` (its lights the true ones) replaced by none, so that the pair of replicas
    (``BIAS_PAIRS`` = 1, ``BIAS_RADIAL``) is rendered from the truth and measures the
    bias there; the replicas themselves take the fit's steps."""
    if size > lightpos.POSITION_SIDE:
        raise SystemExit(f"--oracle-pair: at most {lightpos.POSITION_SIDE}², where the joint fit uses every pixel")
    solve, debiased, inside = lightpos._solve, lightpos._debiased, []

    def start_only(photos, th, lg, iterations, progress=None, **kw):
        if inside:
            return solve(photos, th, lg, iterations, progress, **kw)
        at = solve(photos, th, lg, 0, progress, **kw)
        return replace(at, cost=math.inf) if kw.get("searched") else at  # the true roughness kept

    def marked(*args, **kwargs):
        inside.append(1)
        return debiased(*args, **kwargs)

    was = lightpos.BIAS_RADIAL
    lightpos._solve, lightpos._debiased, lightpos.BIAS_RADIAL = start_only, marked, True
    try:
        _, _, record = fit_positions(cap, maps, gains, bias_pairs=1)
    finally:
        lightpos._solve, lightpos._debiased, lightpos.BIAS_RADIAL = solve, debiased, was
    bias = record["bias"]
    return f"radial {bias['radial_mm']:+.3f} mm, each light's {bias['removed_mm']['mean']:.3f} mean"


@contextlib.contextmanager
def hybrid_pair(kind: str, name: str, maps: MapSet, true: LightSet, gains: torch.Tensor):
    """``--hybrid-pair=maps|lights``: within it, the pair (``--pairs=1``) that measures the
    joint fit's bias renders its replicas from the fit's end with either its maps replaced
    by the true ones (scaled by the fitted gains' overall factor per channel, which the
    rendering multiplies) or its lights' places replaced by the true ones, and prints the
    radial bias it measures: which of the two sets the pair's measure at the fitted end
    apart from its measure at the truth (docs/rti-record.md)."""
    rows = {"diffuse": slice(0, 3), "f0": slice(3, 6), "roughness": slice(6, 7), "normal": slice(7, 9)}
    kind, _, part = kind.partition(":")  # maps:PART: that part of the maps alone the true one
    if kind not in ("maps", "lights", "stats") or (part and (kind != "maps" or part not in rows)):
        raise SystemExit(f"--hybrid-pair: maps[:{'|'.join(rows)}], lights or stats, not {kind!r}")
    debiased = lightpos._debiased

    def swapped(photos, fit, pairs, iterations, progress=None):
        if kind == "stats":  # the fitted and true roughness's quantiles, and no pair
            q = torch.tensor([0.05, 0.25, 0.5, 0.75, 0.95], dtype=torch.float64)
            for label, r in (("fitted", fit.th[6]), ("true", lightpos._numbers(maps)[6, fit.used])):
                at = " ".join(f"{float(v):.3f}" for v in torch.quantile(r, q))
                print(f"{name:16s} {label} roughness at 5/25/50/75/95%: {at}", flush=True)
            return fit.pos, fit.lg, {"pairs": 0}
        if kind == "maps":
            th = lightpos._numbers(maps)[:, fit.used]
            c = (fit.lg - gains.to(torch.float64).log()).mean(0).exp()  # the fitted gains' overall factor (3,)
            th[0:6] = th[0:6] / torch.cat([c, c])[:, None]
            if part:
                th = torch.cat([th[v] if k == part else fit.th[v] for k, v in rows.items()])
            fit = replace(fit, th=th)
        else:
            fit = replace(fit, pos=torch.where(photos.near[:, None], true.position.to(torch.float64), fit.pos))
        pos, lg, record = debiased(photos, fit, pairs, iterations, progress)
        radial = record.get("radial_mm", 0.0)
        print(f"{name:16s} the pair with the true {part or kind}: radial {radial:+.3f} mm", flush=True)
        return pos, lg, record

    lightpos._debiased = swapped
    try:
        yield
    finally:
        lightpos._debiased = debiased


@contextlib.contextmanager
def true_start(maps: MapSet, size: int):
    """``--true-start``: within it, ``estimate_positions`` starts the joint fit from the true
    maps at the pixels it fits (every ⌈size / ``POSITION_SIDE``⌉-th, as ``selfcal.reduced``
    picks them) instead of the ``lm`` solver's at the rig file's places; the solver's fits after
    it (the turns') are left alone."""
    from matscan.reconstruct import job

    f = max(1, math.ceil(size / lightpos.POSITION_SIDE))
    picked = MapSet(**{k: v[..., f // 2 :: f, f // 2 :: f].contiguous() for k, v in maps.present().items()})
    solver, calls = job.reconstruct_capture, []

    def first_replaced(*args, **kwargs):
        fit = solver(*args, **kwargs)
        calls.append(1)
        return replace(fit, maps=picked) if len(calls) == 1 else fit

    job.reconstruct_capture = first_replaced
    try:
        yield
    finally:
        job.reconstruct_capture = solver


def level_stats(maps: MapSet) -> dict[str, torch.Tensor]:
    """``--levels``: the maps' slope (x, y) by the median, the 10% trimmed mean and the two's
    agreement and the base plane (``selfcal.median_slope``, ``trimmed_slope``,
    ``agreed_slope``, ``base_slope``)."""
    return {
        "median": estimator.median_slope(maps),
        "trimmed": estimator.trimmed_slope(maps),
        "agreed": estimator.agreed_slope(maps),
        "base": estimator.base_slope(maps),
    }


def profiles(cap: Capture, cfg, maps: MapSet, true: LightSet, gains, held, rig, level: bool) -> None:
    """``--profile``: the joint fit's ends from the rig file's places with the ``held``
    gains and from the true places with the true and the held gains, each end's error,
    relighting and profile misfit (gains and maps fitted again, the lights held), and the
    profile misfit at the true places and the rig file's, all on the pixels and noise
    model of the fit from the truth with the true gains."""
    solve, calls = lightpos._solve, []

    def watched(*args, **kwargs):
        calls.append((args, solve(*args, **kwargs)))
        return calls[-1][1]

    at_truth = lightpos._lit_from(cap, true.position)
    starts = {"truth, true gains": (at_truth, gains), "truth, held gains": (at_truth, held)}
    starts["rig file, held"] = (cap, held)
    ends, reference = {}, None
    lightpos._solve = watched
    try:
        for label, (c, g) in starts.items():
            calls.clear()
            lights, g2, fitted, _ = estimate_positions(c, g, cfg, level=level)
            fit = reconstruct_capture(with_gains(replace(cap, lights=lights), g2), cfg)
            best = min((s for _, s in calls), key=lambda s: s.cost)  # the end kept, before any turns
            ends[label] = (best.pos, best.lg, novel_psnr(fit.maps, fit.intensity_scale, maps, rig.field_mm))
            # each of its starts' ends' own misfit, with the pixels' numbers its path found, in the units
            # of this fit's noise model (its starts share it; the first fit's is the profiles' own)
            print(f"{'':16s} from {label}: {json.dumps(fitted['misfit_per_value'])}", flush=True)
            reference = reference or calls[0]
    finally:
        lightpos._solve = solve
    (photos, th, lg), first = reference[0][:3], reference[1]
    photos = replace(photos, near=torch.zeros_like(photos.near))  # every light held where it is put
    ends["the truth"] = (true.position.double(), lg, None)
    ends["the rig file"] = (cap.lights.position.double(), lg, None)
    values = float(photos.valid[..., first.used].sum())
    for label, (pos, lg_end, psnr) in ends.items():
        placed = replace(photos, lights=replace(photos.lights, position=pos))
        misfit = solve(placed, th, lg_end, 30, fixed=(first.noise, first.used), shared_f0=lightpos.SHARED_F0).cost
        err = float((pos - true.position.double()).norm(dim=1).mean())
        relit = "" if psnr is None else f", relit {psnr:.2f} dB"
        line = f"profile at {label:18s} {misfit:.6f} per value of {values:.0f}, {err:.2f} mm off{relit}"
        print(f"{'':16s} {line}", flush=True)


def radial_parts(error: torch.Tensor, true: torch.Tensor) -> dict[str, torch.Tensor]:
    """The lights' position ``error`` (N, 3) in parts: along each light's direction from
    the sample's centre (the frame's origin) at its ``true`` place, across it, the mean
    shift, the mean radial shift (each light along its own direction), the vertical."""
    u = true / true.norm(dim=1, keepdim=True)
    along = (error * u).sum(1, keepdim=True)
    vertical = torch.zeros_like(error)
    vertical[:, 2] = error[:, 2]
    return {
        "radial": along * u,
        "tangential": error - along * u,
        "mean shift": error.mean(0, keepdim=True).expand_as(error),
        "mean radial": along.mean() * u,
        "vertical": vertical,
    }


def print_parts(cap: Capture, cfg, maps: MapSet, true: LightSet, pos: torch.Tensor, g2: torch.Tensor, rig) -> None:
    """``--parts``: the novel-light PSNR of the maps fitted with the fitted gains ``g2`` at
    the true places moved by each part of the fitted places' (``pos``) error alone."""
    scores = []
    for k, v in {"all": pos - true.position, **radial_parts(pos - true.position, true.position)}.items():
        fit = reconstruct_capture(with_gains(lightpos._lit_from(cap, true.position + v), g2), cfg)
        psnr = novel_psnr(fit.maps, fit.intensity_scale, maps, rig.field_mm)
        size = f"{float(v.norm(dim=1).mean()):.2f}"
        if k == "mean radial":  # signed: + the fitted dome too large
            size = f"{float((v * true.position).sum(1).div(true.position.norm(dim=1)).mean()):+.2f}"
        scores.append(f"{k} {size} mm {psnr:.2f}")
    fit = reconstruct_capture(with_gains(lightpos._lit_from(cap, true.position), g2), cfg)
    scores.append(f"true places {novel_psnr(fit.maps, fit.intensity_scale, maps, rig.field_mm):.2f} dB")
    print(f"{'':16s} parts: " + ", ".join(scores), flush=True)


def held_information(maps: MapSet, true: LightSet, gains: torch.Tensor, rig, camera: CameraModel) -> torch.Tensor:
    """:func:`information` with the rig file's ±5 mm as a prior and the overall factor of
    each channel's gains, which the maps take up, held at 0 (as the joint fit holds it)."""
    f64, n = torch.float64, len(gains)
    s = information(maps, true, gains, rig, camera)
    s[: 3 * n, : 3 * n] += torch.eye(3 * n, dtype=f64) / (5 / 3**0.5) ** 2
    for ch in range(3):
        u = torch.zeros(6 * n, dtype=f64)
        u[3 * n + ch :: 3] = 1 / n
        s += 1e3 * float(s.diagonal().max()) * torch.outer(u, u)
    return s


def radial_bound(maps: MapSet, true: LightSet, gains: torch.Tensor, rig, camera: CameraModel) -> float:
    """The Cramér–Rao bound's standard deviation (mm) of the lights' mean radial shift,
    with the rig file's ±5 mm as a prior and the gains' overall factor held."""
    f64, n = torch.float64, len(gains)
    s = held_information(maps, true, gains, rig, camera)
    v = torch.zeros(6 * n, dtype=f64)
    v[: 3 * n] = (true.position.double() / true.position.double().norm(dim=1, keepdim=True) / n).reshape(-1)
    return float(v @ torch.linalg.pinv(s, hermitian=True, rtol=1e-12) @ v) ** 0.5


def calibration_of(cap: Capture, cfg, true: LightSet, gains, rig, other, seed: int, cache=None):
    """The dome self-calibrated (``--self-calibrate-positions``, its defaults) on the photos
    of another material ``other`` (name, maps) under the same LEDs, with its own noise:
    its lights, gains, the intensities' record and the positions' record. ``cache`` (a
    file): read from it where it exists, else written to it (the bench's lists share a
    dome by their materials' index: ``--calibration-cache``)."""
    if cache is not None and cache.is_file():
        return torch.load(cache, weights_only=False)
    lit = true.with_intensity(true.intensity * gains)
    photos = simulate_images(other[1], lit, rig.field_mm, CameraModel(read_noise=0.002), seed=seed)
    saturated = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
    on = replace(cap, images=photos, saturated=saturated)
    g1, record = estimate_gains(on, cfg)
    lights, g2, fitted = cap.lights, g1, {}
    if record["updated"]:
        lights, g2, fitted, _ = estimate_positions(on, g1, cfg, level=record["convention"] == "level sample")
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        torch.save((lights, g2, record, fitted), cache)
    return lights, g2, record, fitted


def off_by(pos: torch.Tensor, true: torch.Tensor) -> str:
    """Places' mean distance from the true ones and their mean shift along the true
    places' directions from the origin (the dome's scale: + too far; mm)."""
    u = true / true.norm(dim=1, keepdim=True)
    return f"{float((pos - true).norm(dim=1).mean()):.2f} ({float(((pos - true) * u).sum(1).mean()):+.2f})"


def calibrated_on(
    name: str, cap: Capture, cfg, maps: MapSet, true: LightSet, gains, rig, others, seed, caches, fit, alone=False
):
    """This material's photos fitted with the dome calibrated on the photos of ``others``
    (``calibration_of`` each; more than one merged by ``matscan.calibrate.merge_calibrations``,
    those whose intensities could not be read left out, as ``reconstruct`` warns of
    them), the calibration given to the capture as ``reconstruct --calibration`` gives it
    (``apply_calibration``): its lights' places and scales. With ``fit`` the capture is
    then self-calibrated from there too (``--self-calibrate-positions``, as
    ``reconstruct --calibration FILE --self-calibrate-positions`` runs it). Prints the
    calibration's position error, this material's novel-light PSNR with the ideal dome and
    with the calibration, how far below the ideal that is (with ``fit``, then the fit's
    position error, PSNR and shortfall), and each calibration's record (read or not, the
    turns, its misfit) or, merged, how many went in, their errors and their spread."""
    from matscan.calibrate import apply_calibration, merge_calibrations

    fits = [calibration_of(cap, cfg, true, gains, rig, o, seed, c) for o, c in zip(others, caches, strict=True)]
    read = [(n, f) for (n, _), f in zip(others, fits, strict=True) if f[2]["updated"]] or [(others[0][0], fits[0])]
    names, read = [n for n, _ in read], [f for _, f in read]
    docs = [
        {
            "format": "matscan-calibration/1",
            "light_scales": {str(k): g[k].tolist() for k in range(len(g))},
            "light_positions_mm": {str(k): lt.position[k].tolist() for k in range(len(g))},
        }
        for lt, g, _, _ in read
    ]
    m = merge_calibrations(docs, names)
    if alone:  # --calibrations-only: each calibration's places and the merge's, no fit
        merged = torch.tensor([m.document["light_positions_mm"][str(k)] for k in range(len(gains))])
        each = "  ".join(f"{n}: {off_by(f[0].position, true.position)}" for (n, _), f in zip(others, fits, strict=True))
        unread = [n for (n, _), f in zip(others, fits, strict=True) if not f[2]["updated"]]
        said = f"   unread: {', '.join(unread)}" if unread else ""
        said += f"   astray: {', '.join(m.left_out)}" if m.left_out else ""
        print(f"{name:16s} merged {off_by(merged.to(true.position.dtype), true.position)}   {each}{said}", flush=True)
        return
    if len(others) == 1:
        _, _, record, fitted = fits[0]
        turns = len([t for t in fitted.get("level_turns", []) if t.get("made")])
        said = f"read {record['updated']}, {record['convention']}, {turns} turns, "
        said += f"misfit {fitted.get('misfit_per_value', {}).get('end')}"
    else:
        each = ", ".join(f"{float((f[0].position - true.position).norm(dim=1).mean()):.2f}" for f in read)
        said = f"{m.files} of {len(fits)} merged (their own errors {each} mm; spread {m.position_spread_mm:.2f}"
        said += f"; {len(m.left_out)} left out as astray)" if m.left_out else ")"
    given = apply_calibration(replace(cap, calibration=m.document))
    ideal = reconstruct_capture(replace(cap, lights=true, correction=Correction(None, gains, (None,) * 24)), cfg)
    runs = [reconstruct_capture(given, cfg)]
    if fit:
        runs.append(reconstruct_capture(given, replace(cfg, self_calibrate=True, self_calibrate_positions=True)))
    psnr = [novel_psnr(r.maps, r.intensity_scale, maps, rig.field_mm) for r in (ideal, *runs)]
    line = f"{name:16s} {float((given.lights.position - true.position).norm(dim=1).mean()):12.2f} "
    line += f"{float((given.lights.position - true.position).norm(dim=1).max()):6.2f}   {psnr[0]:7.2f} "
    line += f"{psnr[1]:7.2f} {psnr[0] - psnr[1]:7.2f}"
    if fit:
        placed = runs[1].lights.position if runs[1].lights is not None else given.lights.position
        line += f"   then fitted {float((placed - true.position).norm(dim=1).mean()):5.2f} mm {psnr[2]:7.2f} "
        record = runs[1].self_calibration
        kept = "" if runs[1].lights is not None else " (held)" if "held_gains" in record else " (kept)"
        line += f"{psnr[0] - psnr[2]:7.2f}" + kept + (" refused" if "rejected" in record else "")
    print(f"{line}   {said}", flush=True)


def report(name: str, pos: torch.Tensor, true: LightSet, maps: MapSet, rig, fits) -> None:
    err = (pos - true.position).norm(dim=1)
    psnr = [novel_psnr(r.maps, r.intensity_scale, maps, rig.field_mm) for r in fits]
    print(
        f"{name:16s} {float(err.mean()):12.2f} {float(err.max()):6.2f}   " + " ".join(f"{v:7.2f}" for v in psnr),
        flush=True,
    )


def listed(size: int) -> dict[str, list[tuple[str, Callable[[], MapSet]]]]:
    """The bench's three lists of materials at ``size``², each entry a name and a function
    that makes its maps: "main" (the four), "held-out" (bench/selfcal.py's 13, on which
    ``lightpos.OUTLIER`` and ``ROBUST`` came after two failed) and "others" (the 8 of
    bench/selfcal.py's 12 not among the four). The lists share domes by index."""
    held = ("woven_twill", "woven_satin", "leather_embossed", "weave_heavy", "corrugated")
    held += ("metallic_print", "worn", "varnished_wood", "dark_glossy", "glossy_coat")

    def procedural(family: str, seed: int) -> tuple[str, Callable[[], MapSet]]:
        return family, lambda: generate(family, size, seed)

    def photo(name: str) -> tuple[str, Callable[[], MapSet]]:
        return f"{name} (photo)", lambda: photo_material(name, size)

    def artist(name: str) -> tuple[str, Callable[[], MapSet]]:
        return f"{name} (artist)", lambda: artist_material(name, size)

    return {
        "main": [procedural("paper", 1), photo("brick"), procedural("leather", 1), procedural("plastic", 1)],
        "held-out": [procedural(f, 2) for f in held] + [photo("grass"), artist("embossed-coins"), artist("worn-metal")],
        "others": [procedural(f, 1) for f in ("woven_plain", "knit", "painted", "metal_brushed")]
        + [photo("gravel"), artist("foil-print"), artist("black-leather"), artist("lacquer")],
    }


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    torch.set_num_threads(2)
    prior = 0.0
    level_by = [lightpos.LEVEL_BY]
    for a in sys.argv[1:]:
        if a.startswith("--prior="):
            prior = float(a.split("=", 1)[1])
        if a.startswith("--outlier="):  # the joint fit's pixel rule (lightpos.OUTLIER)
            lightpos.OUTLIER = float(a.split("=", 1)[1])
        if a.startswith("--robust="):  # the joint fit's loss scale (lightpos.ROBUST)
            lightpos.ROBUST = float(a.split("=", 1)[1])
        if a.startswith("--side="):  # pixels on the longer side of the joint fit (lightpos.POSITION_SIDE)
            lightpos.POSITION_SIDE = int(a.split("=", 1)[1])
        if a.startswith("--pairs="):  # the joint fit's antithetic bias replicas (lightpos.BIAS_PAIRS; 0: none)
            lightpos.BIAS_PAIRS = int(a.split("=", 1)[1])
        if a == "--pairs-radial":  # only the common radial part of the pairs' bias removed (lightpos.BIAS_RADIAL)
            lightpos.BIAS_RADIAL = True
        if a == "--replica-searched":  # each replica also fitted from a searched start (REPLICA_SEARCHED)
            lightpos.REPLICA_SEARCHED = True
        if a.startswith("--replica-fence="):  # the replicas' roughness outliers set to the median (REPLICA_FENCE)
            lightpos.REPLICA_FENCE = float(a.split("=", 1)[1])
        if a == "--pairs-iterated":  # the pair's bias measured again at its replicas' ends (BIAS_ITERATED)
            lightpos.BIAS_ITERATED = True
        if a.startswith("--pair-seed="):  # the seed of the pairs' noise (lightpos.PAIR_SEED)
            lightpos.PAIR_SEED = int(a.split("=", 1)[1])
        if a.startswith("--steps="):  # the joint fit's Gauss–Newton steps (ITERATIONS, SHARED_ITERATIONS)
            lightpos.ITERATIONS = lightpos.SHARED_ITERATIONS = int(a.split("=", 1)[1])
        if a == "--second-order":  # the joint fit's bias removed by its second-order formula (lightpos.SECOND_ORDER)
            lightpos.SECOND_ORDER = True
        if a == "--shared-f0":  # one F0 for the dielectric pixels in the joint fit (lightpos.SHARED_F0)
            lightpos.SHARED_F0 = True
        if a == "--own-f0":  # each pixel's own F0 in the joint fit, as before SHARED_F0 was the default
            lightpos.SHARED_F0 = False
        if a == "--level-start":  # the joint fit started from levelled maps (lightpos.LEVEL_START)
            lightpos.LEVEL_START = True
        if a.startswith("--level-turns="):  # the fitted dome turned until the maps lie level (lightpos.LEVEL_TURNS)
            lightpos.LEVEL_TURNS = int(a.split("=", 1)[1])
        if a.startswith("--level-by="):  # what level means for the turns (lightpos.LEVEL_BY); more: each reported
            level_by = a.split("=", 1)[1].split(",")
            if not set(level_by) <= set(lightpos._LEVELS):
                raise SystemExit(f"--level-by: one of {', '.join(lightpos._LEVELS)} (comma-separated)")
            lightpos.LEVEL_BY = level_by[0]
        if a == "--grey-f0":  # the shared F0 one number for the three channels (lightpos.GREY_F0)
            lightpos.GREY_F0 = True
        if a.startswith("--start-prior="):  # the start's solver priors times K (lightpos.START_PRIOR)
            lightpos.START_PRIOR = float(a.split("=", 1)[1])
        if a.startswith("--start-roughness-prior="):  # its roughness prior alone (lightpos.START_ROUGHNESS_PRIOR)
            lightpos.START_ROUGHNESS_PRIOR = float(a.split("=", 1)[1])
        if a.startswith("--weak-start="):  # a third start, the solver's priors times K (lightpos.WEAK_START)
            lightpos.WEAK_START = float(a.split("=", 1)[1])
        if a.startswith("--weak-margin="):  # kept only where it fits better by this share (lightpos.WEAK_MARGIN)
            lightpos.WEAK_MARGIN = float(a.split("=", 1)[1])
        if a == "--weak-own":  # the third start with its own sharing pixels and scan (lightpos.WEAK_SAME)
            lightpos.WEAK_SAME = False
        if a.startswith("--ends-by="):  # which start's end is kept (lightpos.ENDS_BY)
            lightpos.ENDS_BY = a.split("=", 1)[1]
        if a == "--hold-f0":  # the shared F0 held at its scan's value through the steps (lightpos.HOLD_F0)
            lightpos.HOLD_F0 = True
        if a.startswith("--polish="):  # LM steps for each pixel's other roughness valley when searched (POLISH)
            lightpos.POLISH = int(a.split("=", 1)[1])
        if a.startswith("--polish-margin="):  # kept only where the misfit falls by more (POLISH_MARGIN)
            lightpos.POLISH_MARGIN = float(a.split("=", 1)[1])
        if a.startswith("--calibrated-spread="):  # a calibration's places as a prior (CALIBRATED_SPREAD_MM)
            lightpos.CALIBRATED_SPREAD_MM = float(a.split("=", 1)[1])
        if a == "--merge-weighted":  # the calibrations' places merged weighted (calibrate.MERGE_WEIGHTED)
            importlib.import_module("matscan.calibrate").MERGE_WEIGHTED = True
        if a.startswith("--calibrated-common"):  # a calibration's places moved only together (CALIBRATED_COMMON)
            lightpos.CALIBRATED_COMMON = a.split("=", 1)[1] if "=" in a else "confirmed"
        if a.startswith("--place-prior="):  # the rig file's places as a prior, S mm per axis (PLACE_SPREAD_MM)
            lightpos.PLACE_SPREAD_MM = float(a.split("=", 1)[1])
        if a == "--level":  # the sample level, the gains' gradient fitted (selfcal.LEVEL)
            estimator.LEVEL = True
        if a == "--no-level":  # the former convention: the LEDs without a gradient
            estimator.LEVEL = False
        if a == "--no-fallback":  # no second estimate where the level one is refused (selfcal.FALLBACK)
            estimator.FALLBACK = False
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    matte = "--matte" in sys.argv
    draw = next((1000 * int(a.split("=", 1)[1]) for a in sys.argv[1:] if a.startswith("--seed=")), 0)
    only = [n for a in sys.argv[1:] if a.startswith("--only=") for n in a.split("=", 1)[1].split(",")]
    hybrid = next((a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--hybrid-pair=")), None)
    size = int(args[0]) if args else 128
    lists = listed(size)
    which = "held-out" if "--held-out" in sys.argv else "others" if "--others" in sys.argv else "main"
    materials = [(n, make()) for n, make in lists[which]]
    named = next((a.split("=", 1)[1].split(",") for a in sys.argv[1:] if a.startswith("--calibrated-on=")), [])
    every = [entry for k in ("main", "held-out", "others") for entry in lists[k]]
    found = [next(((n, make) for n, make in every if n.startswith(k)), None) for k in named]
    if None in found:
        unknown = [k for k, f in zip(named, found, strict=True) if f is None]
        raise SystemExit(f"--calibrated-on: {', '.join(unknown)}: not among the bench's materials")
    on = [(n, make()) for n, make in found] or None
    cached = next((a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--calibration-cache=")), None)
    cfg = ReconstructConfig(model="none", refine="on", solver="lm")
    if "--choose" in sys.argv:  # both conventions, the better re-rendering kept (led_gradient "choose")
        cfg = replace(cfg, self_calibrate=True, led_gradient="choose")
    rig = builtin_rig("dome24")
    nominal = rig.light_set()
    t0 = time.perf_counter()
    truth_noise = None
    gradient = tilt = 0.0
    for a in sys.argv[1:]:
        if a.startswith("--tilt="):  # degrees
            tilt = float(a.split("=", 1)[1])
        if a.startswith("--gradient="):  # the LEDs' log brightness rises by this per unit of x direction
            gradient = float(a.split("=", 1)[1])
    tie = next((float(a.split("=", 1)[1]) for a in sys.argv[1:] if a.startswith("--versus-tie=")), None)
    at = next((int(a.split("=", 1)[1]) for a in sys.argv[1:] if a.startswith("--at-bound=")), None)
    for a in sys.argv[1:]:
        if a.startswith("--from-truth"):  # 0.0: the camera's; S: Gaussian on float photos; shot; steps
            v = a.split("=", 1)[1] if "=" in a else "0"
            truth_noise = v if v in ("shot", "steps") else float(v)
        if a.startswith("--f0-grid="):  # the shared F0's scan (lightpos._F0_GRID); one value, --hold-f0: held there
            lightpos._F0_GRID = torch.tensor([float(v) for v in a.split("=", 1)[1].split(",")], dtype=torch.float64)
    if "--no-reseed" in sys.argv or "--pin-roughness" in sys.argv:  # no pixel's roughness searched again
        lightpos._reseeded = lambda th, *args: th
    if "--pin-roughness" in sys.argv:  # each pixel's roughness held at its start: SECOND_ORDER's hold, no formula
        lightpos._SPREAD = torch.tensor([1e3] * 6 + [1e-5, 1e3, 1e3], dtype=torch.float64)
        lightpos.SECOND_ORDER = True
        lightpos._second_order = lambda photos, fit: (fit.pos, fit.lg, {"pairs": 0})
    if truth_noise is not None:
        print(f"{'material':16s} {'pos err mean':>12s} {'max':>6s}   (mm, the joint fit started at the truth)")
    elif "--variants" in sys.argv:
        print(f"{'material':16s} (mm, gains %, dB): bias left in  |  pair on both  |  on positions  |  on gains")
    elif "--versus-choose" in sys.argv or tie is not None:
        print(f"{'material':16s} the conventions kept and, where they differ, the final novel-light PSNR (dB)")
    elif "--slopes" in sys.argv:
        print(f"{'material':16s} each convention's re-rendering RMSE; the level gains' gradient and the true one")
    elif "--levels" in sys.argv:
        print(f"{'material':16s} the true maps' slope (x, y) by each statistic")
    elif "--bound" in sys.argv:
        print(
            f"{'material':16s} {'photos alone':>12s} {'+ rig file':>12s} {'mean radial':>12s} {'rig file':>12s}"
            "   (RMS position error of the bound; its sd of the mean radial shift; the rig file's, mm)"
        )
    elif at is not None:
        print(f"{'material':16s}  ideal    mean   worst  within 0.5 dB   mm   bound (dB; lights drawn at the bound)")
    elif on is not None:
        print(
            f"{'material':16s} {'pos err mean':>12s} {'max':>6s}   PSNR ideal  reused  below   "
            f"(mm, dB; the dome self-calibrated on {' and '.join(named)}'s photos, reused)"
        )
    else:
        print(f"{'material':16s} {'pos err mean':>12s} {'max':>6s}   PSNR ideal nominal  gains +positions (dB)")
    for i, (name, maps) in enumerate(materials):
        if only and not any(name.startswith(o) for o in only):
            continue
        if matte:
            maps = MapSet(**{**maps.present(), "specular": torch.zeros_like(maps.specular)})
        if tilt:  # the sample lies tilted toward +x, which the level convention takes as a gradient
            maps = MapSet(**{**maps.present(), "normal": tilted(maps.normal, tilt, 0.0)})
        if "--levels" in sys.argv:  # the true maps' tilt by the median, trimmed mean and their agreement
            f = "  ".join(f"{k} ({v[0]:+.4f}, {v[1]:+.4f})" for k, v in level_stats(maps).items())
            print(f"{name:16s} {f}", flush=True)
            continue
        gains = led_gains(100 + i + draw, gradient="--drawn-gradient" in sys.argv)
        if gradient:  # brighter toward +x across the dome, which the self-calibration takes as none
            gains = gains * torch.exp(gradient * nominal.position[:, :1] / nominal.position.norm(dim=1, keepdim=True))
        delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + draw)) * 2 - 1) * 5
        true = moved(nominal, delta)
        if "--bound" in sys.argv:
            alone, prior = bound(maps, true, gains, rig, CameraModel(read_noise=0.002))
            radial = radial_bound(maps, true, gains, rig, CameraModel(read_noise=0.002))
            u = true.position / true.position.norm(dim=1, keepdim=True)
            off = float(((nominal.position - true.position) * u).sum(1).mean())
            print(f"{name:16s} {alone:12.2f} {prior:12.2f} {radial:12.3f} {off:+12.3f}", flush=True)
            continue
        lit = true.with_intensity(true.intensity * gains)
        photos = simulate_images(maps, lit, rig.field_mm, CameraModel(read_noise=0.002), seed=i + draw)
        saturated = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
        files = tuple(f"led_{k:02d}.png" for k in range(24))
        if "--oracle-pair" in sys.argv:  # the pair's bias measured at the truth
            cap = Capture(rig, rig.field_mm, "srgb", photos, saturated, tuple(range(24)), true, files)
            print(f"{name:16s} {oracle_pair(cap, maps, gains, size)}", flush=True)
            continue
        if truth_noise is not None:  # --from-truth: the fit started at the truth, 30 steps
            encoding = "srgb"
            if "--reduced" in sys.argv:  # as many pixels as the joint fit uses (every ⌈size / POSITION_SIDE⌉-th)
                f = max(1, math.ceil(size / lightpos.POSITION_SIDE))
                maps = MapSet(**{k: v[..., ::f, ::f].contiguous() for k, v in maps.present().items()})
                photos = simulate_images(maps, lit, rig.field_mm, CameraModel(read_noise=0.002), seed=i + draw)
                saturated = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
            if truth_noise in ("shot", "steps"):  # the camera's noise in 16-bit linear files; its 8-bit steps alone
                camera = CameraModel(read_noise=0.002, bits=16, encoding="linear") if truth_noise == "shot" else None
                radiance = render_maps(maps, lit, rig.field_mm)
                camera, encoding = (camera, "linear") if camera else (CameraModel(read_noise=0.0), "srgb")
                photos = apply_camera(radiance, camera, torch.Generator().manual_seed(i + draw))
                saturated = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
            elif truth_noise > 0:
                photos = render_maps(maps, lit, rig.field_mm)
                z = torch.randn(photos.shape, generator=torch.Generator().manual_seed(1))
                photos, encoding = (photos + truth_noise * z).clamp(0, 1), "linear"
                saturated = (photos >= 1).any(1, keepdim=True)
            cap = Capture(rig, rig.field_mm, encoding, photos, saturated, tuple(range(24)), true, files)
            pos, _, record = fit_positions(cap, maps, gains, iterations=30, bias_pairs=0)
            err = (pos - true.position).norm(dim=1)
            u = true.position / true.position.norm(dim=1, keepdim=True)
            radial = f"  mean radial {float(((pos - true.position) * u).sum(1).mean()):+.3f} mm"
            shared = record.get("shared_f0") or {}
            f0 = f"  shared F0 {shared.get('value')} scanned {shared.get('scanned')} se {shared.get('se')}"
            print(f"{name:16s} {float(err.mean()):12.2f} {float(err.max()):6.2f}" + radial + f0, flush=True)
            continue
        cap = Capture(rig, rig.field_mm, "srgb", photos, saturated, tuple(range(24)), nominal, files)
        if on is not None:  # the dome calibrated on other materials' photos under the same LEDs
            files = [None] * len(on)
            if cached:  # the bench's lists share a dome by index: one calibration per index and draw
                files = [pathlib.Path(cached) / f"{k}-{size}-seed{draw // 1000}-{i}.pt" for k in named]
            fit = "--then-fit" in sys.argv
            alone = "--calibrations-only" in sys.argv
            calibrated_on(name, cap, cfg, maps, true, gains, rig, on, 700 + i + draw, files, fit, alone)
            continue
        if at is not None:  # what an estimator at the bound would relight at
            at_bound(name, cap, cfg, maps, true, gains, rig, at, seed=300 + i + draw)
            continue
        if "--slopes" in sys.argv:  # each convention's estimate, and the level one's gradient
            slopes(name, cap, cfg, gains, tilt)
            continue
        if "--gains-only" in sys.argv:  # which estimates are kept, refused or taken by the fallback
            g1, record = estimate_gains(cap, cfg)
            off = (g1 / gains).log()
            off = float((off - off.mean(0)).square().mean().sqrt()) * 100
            rmse = record["rerender_rmse"]
            print(
                f"{name:16s} {record['convention']:13s} updated {record['updated']!s:5s} "
                f"rejected {'rejected' in record!s:5s} fallback "
                + (f"{record['fallback']['rerender_rmse']:.5f}" if "fallback" in record else "-      ")
                + f"  RMSE {rmse['before']:.5f} -> {rmse['after']:.5f}  gains' RMS error {off:.2f}%"
                + (
                    f"  choice {record['choice']['level sample']:.5f} / {record['choice']['no gradient']:.5f}"
                    if "choice" in record
                    else ""
                ),
                flush=True,
            )
            continue
        if "--versus-choose" in sys.argv:  # "auto" as before selfcal.CHOOSE (level, with its fallback) and "choose"
            sides = {"auto": ("auto", {"CHOOSE": False}), "choose": ("choose", {"TIE_GRADIENT": None})}
            versus(name, cap, cfg, maps, true, gains, rig, sides)
            continue
        if tie is not None:  # "auto" with and without the tie-breaker
            sides = {"margin": ("auto", {"TIE_GRADIENT": None}), "tie": ("auto", {"TIE_GRADIENT": tie})}
            versus(name, cap, cfg, maps, true, gains, rig, sides)
            continue
        ideal = reconstruct_capture(replace(cap, lights=true, correction=Correction(None, gains, (None,) * 24)), cfg)
        plain = reconstruct_capture(cap, cfg)
        g1, record = estimate_gains(cap, cfg)
        if "fallback" in record:  # the level convention's gains were refused (selfcal.FALLBACK)
            rmse = record["rerender_rmse"]
            print(
                f"{name:16s} fallback: the level sample's gains refused (RMSE {record['fallback']['rerender_rmse']:.5f}"
                f" against {rmse['before']:.5f}); without a gradient {rmse['after']:.5f}, "
                + ("kept" if record["updated"] else "refused too" if "rejected" in record else "unread"),
                flush=True,
            )
        gains_only = reconstruct_capture(with_gains(cap, g1), cfg)
        if "--joint" in sys.argv and not record["updated"]:  # the rig file's places, as reconstruct keeps them
            report(f"{name} *", nominal.position, true, maps, rig, (ideal, plain, gains_only, gains_only))
            if "--held-gains" in sys.argv:  # the unread intensities from the joint fit, the lights held
                g, _ = lightpos.estimate_held_gains(cap, g1, cfg, level=record["convention"] == "level sample")
                fit = reconstruct_capture(with_gains(cap, g), cfg)
                off = (g / gains).log()
                off = float((off - off.mean(0)).square().mean().sqrt()) * 100
                report(f"{'':4s}held gains", nominal.position, true, maps, rig, (ideal, plain, fit, fit))
                ones = torch.ones_like(g)
                rmse = [estimator._fit_error(cap, v, replace(cfg, validate=0)) for v in (ones, g)]
                print(
                    f"{'':16s} the gains' RMS error {off:.2f}% (overall factor removed); re-rendering RMSE "
                    f"{rmse[0]:.5f} at the rig file's intensities, {rmse[1]:.5f} with these",
                    flush=True,
                )
            if "--profile" in sys.argv:  # whether placing these lights fails by its start or its misfit
                level = record["convention"] == "level sample"
                g = g if "--held-gains" in sys.argv else lightpos.estimate_held_gains(cap, g1, cfg, level=level)[0]
                profiles(cap, cfg, maps, true, gains, g, rig, level)
            continue
        if "--variants" in sys.argv:  # the pair's correction applied in parts (with --steps=30 --pairs=1)
            variants(name, cap, g1, cfg, maps, true, gains, rig, record["convention"] == "level sample")
            continue
        if "--joint" in sys.argv:  # what reconstruct --self-calibrate-positions runs
            level = record["convention"] == "level sample"
            if "--true-start" in sys.argv:  # a diagnostic: the joint fit started from the true maps
                with true_start(maps, size):
                    lights, g2, fitted, unturned = positions_and_unturned(cap, g1, cfg, level)
            elif hybrid:  # a diagnostic: the pair at the fit's end with its maps or places the true ones
                with hybrid_pair(hybrid, name, maps, true, gains):
                    lights, g2, fitted, unturned = positions_and_unturned(cap, g1, cfg, level)
            else:
                lights, g2, fitted, unturned = positions_and_unturned(cap, g1, cfg, level)
            both = reconstruct_capture(with_gains(replace(cap, lights=lights), g2), cfg)
            report(name, lights.position, true, maps, rig, (ideal, plain, gains_only, both))
            if "--parts" in sys.argv:  # which part of the lights' error costs the relighting
                print_parts(cap, cfg, maps, true, lights.position, g2, rig)
            if unturned is not None:  # the same fit without the turns (LEVEL_TURNS = 0), paired with the line above
                before = lightpos._lit_from(cap, unturned[1])
                fit = reconstruct_capture(with_gains(before, g2), cfg)
                report(f"{'':4s}before turns", before.lights.position, true, maps, rig, (ideal, plain, gains_only, fit))
                for by in level_by[1:]:  # the same fit turned level by another LEVEL_BY
                    lightpos.LEVEL_BY, was = by, lightpos.LEVEL_BY
                    try:
                        pos, done = lightpos._turned_level(*unturned)
                    finally:
                        lightpos.LEVEL_BY = was
                    fit = reconstruct_capture(with_gains(lightpos._lit_from(cap, pos), g2), cfg)
                    report(f"{'':4s}by {by}", pos, true, maps, rig, (ideal, plain, gains_only, fit))
                    print(f"{'':16s} {json.dumps(done)}", flush=True)
            if "--validate-choice" in sys.argv:  # the photos left out, predicted with either set of lights
                from matscan.reconstruct.job import leave_out_validation

                sides = {"positions": with_gains(replace(cap, lights=lights), g2), "rig file": with_gains(cap, g1)}
                scores = {k: leave_out_validation(c, 6, cfg, None) for k, c in sides.items()}
                print(
                    f"{'':16s} 6 photos left out, RMSE / PSNR: "
                    + ", ".join(f"{k} {v['rmse_left_out']:.6f} / {v['psnr_left_out']:.2f}" for k, v in scores.items()),
                    flush=True,
                )
            if "--ends" in sys.argv:  # each start's end
                print_ends(true, nominal)
            if "--record" in sys.argv:  # what the joint fit found besides the lights
                keys = ("pixels_used", "misfit_per_value", "ends_moved_mm", "shared_f0", "level_turns", "bias")
                shown = {k: fitted[k] for k in keys if k in fitted}
                angle, mean, most = turned(lights.position, true.position)
                print(
                    f"{'':16s} {json.dumps(shown)}; the positions turned {angle:.3f}° about the sample's centre, "
                    f"the error without that turn {mean:.2f} mm mean, {most:.2f} max",
                    flush=True,
                )
            if "--split" in sys.argv:  # which of the two, positions or gains, the relighting follows
                ratio = (g2 / gains).log()
                spread = float((ratio - ratio.mean(0, keepdim=True)).square().mean().sqrt()) * 100
                parts = [with_gains(replace(cap, lights=lights), gains), with_gains(replace(cap, lights=true), g2)]
                psnr = [
                    novel_psnr(r.maps, r.intensity_scale, maps, rig.field_mm)
                    for r in map(reconstruct_capture, parts, [cfg] * 2)
                ]
                print(
                    f"{'':16s} gains' RMS error {spread:.2f}% (overall factor removed); PSNR with the fitted positions "
                    f"and true gains {psnr[0]:.2f}, with the true positions and fitted gains {psnr[1]:.2f}",
                    flush=True,
                )
                tilts = " and ".join(
                    f"({mean_slope(r.maps)[0]:+.4f}, {mean_slope(r.maps)[1]:+.4f})" for r in (gains_only, both)
                )
                print(
                    f"{'':16s} the maps' mean normal slope (x, y) with the intensities {tilts} with the positions too; "
                    f"true ({mean_slope(maps)[0]:+.4f}, {mean_slope(maps)[1]:+.4f})",
                    flush=True,
                )
            mpv = fitted["misfit_per_value"]
            ends = mpv.get("ends", {})
            default = "searched" if ends.get("searched", math.inf) < ends.get("start", math.inf) else "start"
            if mpv.get("kept", default) != default:  # the same photos as the defaults fit them
                chosen = (lightpos.WEAK_START, lightpos.ENDS_BY)
                lightpos.WEAK_START, lightpos.ENDS_BY = 0.0, "misfit"
                try:
                    with true_start(maps, size) if "--true-start" in sys.argv else contextlib.nullcontext():
                        other, g3, _, _ = estimate_positions(cap, g1, cfg, level=level)
                finally:
                    lightpos.WEAK_START, lightpos.ENDS_BY = chosen
                fit = reconstruct_capture(with_gains(replace(cap, lights=other), g3), cfg)
                label = "without weak" if chosen[1] == "misfit" else "as default"
                report(f"{'':4s}{label}", other.position, true, maps, rig, (ideal, plain, gains_only, fit))
            continue
        if "--full" in sys.argv:
            pos = full_positions(with_gains(cap, g1))
        else:
            pos = varpro_positions(with_gains(cap, g1), gains_only, prior=prior)
        if not bool(torch.isfinite(pos).all()):
            print(f"{name:16s} the positions diverged", flush=True)
            continue
        cap2 = replace(cap, lights=moved(nominal, pos - nominal.position))
        g2, _ = estimate_gains(cap2, cfg)
        both = reconstruct_capture(with_gains(cap2, g2), cfg)
        report(name, pos, true, maps, rig, (ideal, plain, gains_only, both))
    ran = sum(1 for name, _ in materials if not only or any(name.startswith(o) for o in only))
    print(f"{ran} materials at {size}² in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
