"""Self-calibration: each light's intensity (RGB) estimated with the maps, from the photos alone.

Real domes do not deliver the intensities their rig file states: LEDs age and differ,
a handheld RTI light is nearer or farther in every photo. With enough photos the
intensities and the maps are jointly determined up to one overall RGB factor (which
the albedo absorbs), as semi-calibrated photometric stereo shows. So, alternately:

1. fit the maps to the photos divided by the current gains (the ``lm`` solver, on every
   ``factor``-th pixel of the capture: the gains are global, and a sample of the pixels
   fits in a fraction of the time), holding roughness only weakly near its start
   (``ROUGHNESS_HOLD``): a lobe width set by the start would make the ratios below
   depend on the light's elevation;
2. for each photo and channel, the median ratio of the photo to the rendering of the
   fitted maps over pixels that are unsaturated, lit (rendering above ``LIT``) and mostly
   diffuse (``DIFFUSE_SHARE``), and multiply it in; a photo with too few such pixels
   (``MIN_SHARE``) keeps its gain, and if fewer than half the photos can be read
   (``MIN_PHOTO_SHARE``) the round keeps every gain. The median, not a least-squares
   ratio: pixels the fit gets wrong would bias a mean (on simulated dome24 captures the
   median's gain errors were 3 to 20 times smaller). Mostly diffuse pixels: a
   highlight's brightness depends on roughness and normal as much as on the light. The
   thresholds and the hold were chosen on bench/selfcal.py's 12 materials, and the hold
   and ``MIN_PHOTO_SHARE`` checked on 13 others (docs/rti.md);
3. fix by convention what the photos cannot tell (:func:`gauged`): divide the gains by
   their geometric mean over the photos, per channel (the overall factor stays in the
   maps, so a white-balanced capture stays white-balanced), and fix their gradient
   across the dome, which photographs like a tilted sample. The sample is taken as
   lying level (``LEVEL``, ``ReconstructConfig.led_gradient``): each round reads its
   ratios against the fitted maps levelled by their median slope (:func:`levelled`),
   so the gains take the gradient the photos show. Where the capture's calibration
   scales every light (a grey card measured the gradient), or with ``led_gradient``
   "none", the dome is taken instead as without a gradient and the gains' part linear
   in the lights' horizontal directions is removed (:func:`without_tilt`), so that a
   sample that does not lie flat keeps its tilt. LEDs drawn ±20% at random have a
   gradient (a slope of their log brightness of 0.057 in the median), under which the
   convention of no gradient placed bench/nearcal.py's lights 2.6-8.5 mm off (the level
   one 0.5-2.9 mm) and relit 0.8-2.0 dB worse on average over its 25 materials; without
   a gradient the two relight alike (docs/rti-record.md). But a sample that does not lie level
   breaks the level convention: tilted 5°, its gains pass the check below 10% off (RMS;
   3% without a gradient), and on a handheld light's RTI capture, whose frame need not
   be the sample's, they are refused (rti-icon leans 9.5° in its ``.lp`` frame). So
   ``led_gradient`` "choose", and "auto" where the level convention applies
   (``CHOOSE``), runs the rounds under both conventions and keeps the gains whose fit
   re-renders the photos better, the one without a gradient if by ``CHOOSE_MARGIN``,
   or within it where the level gains' gradient across the dome is steep
   (``TIE_GRADIENT``; the record's ``choice`` has both RMSEs and that gradient), at
   twice the time;
   where the level gains are kept but refused, the other's face the same check
   (``FALLBACK``).

Last, the maps are fitted once more with the gains, and if they re-render the sampled
photos (under the lights times the gains) no better than the first fit, at the capture's
own intensities (the rig file's, or its calibration's), did, the estimate went astray or
had nothing to correct, and the capture's own are kept (the record's ``rejected``).
Under the convention of no gradient, among 50 simulated dome24 captures
(bench/nearcal.py's 25 materials, two draws of the dome) that happened once: a black
knit lit enough in 16 of 24 photos to pass ``MIN_PHOTO_SHARE`` re-rendered 12% worse
with its gains (RMSE 0.00383 against 0.00342), which relit it 5.0 dB worse (37.61
against 42.65 dB) and, with the positions fitted from them, 9.0 dB worse. The 44
estimates kept re-rendered the photos at least 1% better, 29 of them at least twice as
well. On bench/selfcal.py's 50 uncalibrated captures it refused one estimate, which had
relit 0.22 dB worse than the rig file, and on its 50 captures calibrated with the right
scales it kept those on 24 (docs/rti.md).

The result is a per-photo gain, applied as the calibration's per-light scale
(photo = scale × model): :func:`with_gains` puts it into a capture's
:class:`~matscan.capture.folder.Correction`, and the reconstruction writes it as a
calibration file (``self_calibration.json``) that later captures on the same rig can
name. Near-light positions are estimated by :mod:`matscan.reconstruct.lightpos`
(``--self-calibrate-positions``), after the gains.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from matscan.capture.folder import Capture, Correction
from matscan.errors import MatscanError
from matscan.mapset import MapSet
from matscan.render import render_maps
from matscan.rig import LightSet

if TYPE_CHECKING:
    from matscan.reconstruct.job import ReconstructConfig

#: Fewer photos than this leave the gains and the maps undetermined together.
MIN_PHOTOS = 8
#: Gains are read where the diffuse reflection makes up at least this share of the
#: rendering: a highlight's brightness depends on roughness and normal as much as on
#: the light, and a fit can trade one for the other.
DIFFUSE_SHARE = 0.7
#: Rendered linear values below this are too dark to say much about a gain.
LIT = 0.02
#: A photo's channel needs this many lit, unsaturated, mostly diffuse pixels for its gain
#: to be updated, and at least this share of its pixels: a material with too little
#: diffuse reflection (a metal, black wool) keeps the rig file's intensities, which cost
#: it less than gains read from a few dark pixels.
MIN_PIXELS = 16
MIN_SHARE = 0.05
#: A round updates the gains only if at least this share of the photos could be read
#: (``MIN_SHARE``): where only one ring of a dome shows enough diffuse reflection (a black
#: knit, lit from above), the gains read there trade against the reflectance's angular
#: shape, and the normalisation of the gains would carry their error to every other photo.
MIN_PHOTO_SHARE = 0.5
#: The fits of the rounds hold roughness near their start this much more weakly than a
#: reconstruction does (``SolverConfig.prior_roughness`` times this). The start (0.5 on
#: flat maps) pulls the fitted lobe's width, and a lobe of the wrong width makes the
#: diffuse pixels' ratios depend on the light's elevation: with the reconstruction's
#: hold, a matte sample under true intensities read gains ordered by ring (+0.4% on the
#: 22.5° ring, −0.6% on the 67.5° one; docs/rti.md).
ROUGHNESS_HOLD = 0.01
#: Alternations of fitting and gain estimation (on simulated dome24 captures the gains
#: settle within three).
ROUNDS = 3
#: The capture is reduced to at most this many pixels on its longer side for the rounds.
ROUND_SIDE = 128
#: What fixes the gains' gradient across the dome, which a tilted sample photographs
#: like, where ``ReconstructConfig.led_gradient`` is "auto" (:func:`fits_gradient`):
#: True, the sample lies level (its median slope none, :func:`levelled`) and the gains
#: keep the gradient the photos show; False, the gains have none (:func:`without_tilt`).
#: True since it passed its rule on three draws of bench/nearcal.py's dome, with the
#: LEDs' own gradients and without (docs/rti-record.md).
LEVEL = True
#: Where the level convention's gains are kept but refused (they re-render the photos no
#: better than the capture's own intensities) and ``led_gradient`` is "auto" or "choose",
#: the gains under the convention of no gradient (run for the choice, or once more where
#: ``CHOOSE`` is off) are kept if they pass the same check (the record's ``fallback``). A
#: capture whose frame is not the sample's (a handheld light's, docs/rti-record.md) breaks the
#: level convention, not the other.
FALLBACK = True
#: ``led_gradient`` "choose" keeps the estimate without a gradient if its fit re-renders
#: the photos at least this share better than the level convention's, or within this share
#: either way where the level gains are steep (``TIE_GRADIENT``); else the level one, the
#: default convention. The two tie where the photos cannot tell a tilt from
#: a gradient, and a tie went the wrong way: level samples relit 3.66, 0.84 and 0.13 dB
#: worse (leather, gravel, paper). Over bench/nearcal.py's draws 0-2, on the 65 samples
#: tilted 5° where the estimate without a gradient re-rendered better it did so by 1.1% or
#: more; on the 30 of 150 level ones where it did, by 0-25%, 18 of them by under 1% (chosen
#: there; on draws 3 and 4, level, 3 of 100 estimates kept the other convention, which
#: relit them within ±0.15 dB: docs/rti-record.md).
CHOOSE_MARGIN = 0.01
#: Where ``led_gradient`` is "auto" and the level convention applies (:func:`fits_gradient`),
#: both conventions run, as under "choose" (at twice the time): the level convention's
#: gains pass the refusal check 10% off on a sample tilted 5°, and the other's relit such
#: samples 0.4-22 dB better. True since its third rule held on draws 3 and 4 of
#: bench/nearcal.py's dome, not used to set ``CHOOSE_MARGIN`` (docs/rti-record.md).
CHOOSE = True
#: Where the two estimates re-render the photos within ``CHOOSE_MARGIN`` of each other
#: either way (a tie), the one without a gradient is kept if the level estimate's gains
#: have a gradient across the dome (:func:`steepness`) of at least this: a tilt read as
#: the LEDs' own. On draws 0, 1 and 4 of bench/nearcal.py's dome the level gains'
#: gradient was 0.080-0.277 on samples tilted 5° and 0.005-0.142 on level ones, whose
#: LEDs' true gradients reach 0.121; the ties the margin handed to the level convention on
#: tilted samples were at 0.22-0.28 but one (docs/rti-record.md). Set by its fourth rule, which
#: held on draws 5 and 6 (not used to choose it): tilted 5°, it changed one material of
#: 50, +0.40 dB; level, with the LEDs' gradients and without, none of 100. None: off.
TIE_GRADIENT: float | None = 0.15
#: Where ``--self-calibrate`` without the positions fits the intensities jointly with the
#: maps, every light held at its place (:func:`matscan.reconstruct.lightpos.estimate_held_gains`):
#: "off", never (the estimate kept, or the capture's own intensities where it is not);
#: "unread", where ``--self-calibrate-positions`` does (the estimate not kept and the
#: capture's intensities not a calibration's that re-render as well); "always", there and
#: from every kept estimate too. runs/selfcal-held/README.md has the rule and the runs.
HELD_GAINS = "unread"


def reduced(capture: Capture, factor: int) -> Capture:
    """Every ``factor``-th pixel of the capture's photos in each direction (calibrated,
    linear float32), the one nearest each block's centre. Pixels are picked, not
    averaged: the average of a block's renderings is not the rendering of its averaged
    maps, and that difference would pass for a gain."""
    if factor <= 1:
        return capture
    o = factor // 2
    images = torch.cat([capture.linear([i])[..., o::factor, o::factor] for i in range(len(capture.files))])
    saturated = capture.saturated[..., o::factor, o::factor]
    return replace(capture, images=images, saturated=saturated, lut=None, correction=None, backlight={})


def with_gains(capture: Capture, gains: Tensor) -> Capture:
    """The capture with every photo divided by its gain (N, 3), on top of any calibration."""
    n = len(capture.files)
    c = capture.correction
    if c is None:
        c = Correction(None, torch.ones(n, 3), (None,) * n)
    return replace(capture, correction=Correction(c.matrix, c.gain * gains, c.flats))


def estimate_gains(capture: Capture, cfg: ReconstructConfig, rounds: int = ROUNDS) -> tuple[Tensor, dict[str, Any]]:
    """Per-photo RGB gains (N, 3) of a capture (module doc) and a record: the gains by
    photo, how many photos the last round could read, whether any round updated the
    gains, the convention that fixed their gradient, the re-rendering RMSE of the sampled
    pixels before and after, where the level convention's gains were refused the
    ``fallback`` (their RMSE), and where the gains kept are the capture's own, ``rejected``."""
    from matscan.reconstruct.job import SELF_CALIBRATION_OFF

    n = len(capture.files)
    if n < MIN_PHOTOS:
        raise MatscanError(
            f"--self-calibrate (which --self-calibrate-positions, --shared-f0 and --own-f0 imply): needs at "
            f"least {MIN_PHOTOS} photos to tell the lights from the maps, the capture has {n}"
        )
    h, w = capture.size
    factor = max(1, math.ceil(max(h, w) / ROUND_SIDE))
    small = reduced(capture, factor)
    # its fits drop saturated values and take the full level's fixed steps only, as when its
    # settings were chosen and measured (the censored ones moved a tilted sample's gains
    # 1.9% → 2.5% off; runs/lm-censored/README.md, runs/lm-converge/README.md)
    lm = replace(cfg.lm, prior_roughness=cfg.lm.prior_roughness * ROUGHNESS_HOLD, censored=False, more_iterations=0)
    level = fits_gradient(capture, cfg)
    fit_cfg = replace(cfg, refine="on", solver="lm", validate=0, lm=lm, **SELF_CALIBRATION_OFF)
    gains, read, updated, before, after = _rounds(small, fit_cfg, level, rounds)
    choice = other = None
    if cfg.led_gradient == "choose" or (cfg.led_gradient == "auto" and level and CHOOSE):
        other = _rounds(small, fit_cfg, False, rounds)  # both conventions; the one that re-renders better
        steep = steepness(gains, small.lights) if updated else 0.0
        choice = {"level sample": round(after, 6), "no gradient": round(other[4], 6), "level gradient": round(steep, 4)}
        if other[2] and (not updated or prefers_no_gradient(after, other[4], steep)):
            (gains, read, updated, _, after), level = other, False
    worse = updated and after >= before
    fallback = None
    if worse and level and (cfg.led_gradient == "auto" or other is not None) and FALLBACK:
        fallback = {"from": "level sample", "rerender_rmse": round(after, 6)}
        gains, read, updated, _, after = other if other is not None else _rounds(small, fit_cfg, False, rounds)
        level, worse = False, updated and after >= before
    if worse:  # the estimate explains the photos no better than the capture's own intensities
        gains, updated = torch.ones(n, 3), False
    record = {
        "light_gains": {f: [round(float(v), 5) for v in g] for f, g in zip(capture.files, gains, strict=True)},
        "rounds": rounds,
        "photos_read": int(read.sum()),  # in the last round
        "updated": updated,
        "reduced_by": factor,
        "convention": "level sample" if level else "no gradient",  # what fixed the gains' gradient
        "rerender_rmse": {"before": round(before, 6), "after": round(after, 6)},
    }
    if fallback is not None:
        record["fallback"] = fallback
    if choice is not None:
        record["choice"] = choice
    if worse:
        record["rejected"] = "the estimated intensities re-render the photos no better than the capture's own"
    return gains, record


def prefers_no_gradient(level_rmse: float, none_rmse: float, steep: float) -> bool:
    """Whether ``choose`` keeps the estimate without a gradient over the level one, given
    each one's re-rendering RMSE and the level gains' gradient (:func:`steepness`): where
    its fit re-renders at least ``CHOOSE_MARGIN`` better, or where the two tie (within the
    margin either way) and the level gains are at least ``TIE_GRADIENT`` steep."""
    if none_rmse < (1 - CHOOSE_MARGIN) * level_rmse:
        return True
    tie = none_rmse < (1 + CHOOSE_MARGIN) * level_rmse
    return tie and TIE_GRADIENT is not None and steep >= TIE_GRADIENT


def steepness(gains: Tensor, lights: LightSet) -> float:
    """The length of the gains' gradient across the dome (:func:`gradient`), the mean over
    the channels: the slope of their logarithm along the lights' horizontal directions."""
    return float(gradient(gains, lights).norm(dim=0).mean())


def _rounds(
    small: Capture, fit_cfg: ReconstructConfig, level: bool, rounds: int
) -> tuple[Tensor, Tensor, bool, float, float]:
    """The alternation of the module doc under one convention (``level``) on the reduced
    capture: the gains, which photos the last round read, whether any round updated the
    gains, and the re-rendering RMSE of the first fit (at the capture's own intensities)
    and of a fit with the gains."""
    from matscan.reconstruct.job import reconstruct_capture
    from matscan.reconstruct.solver import rerender_error

    n = len(small.files)
    gains = torch.ones(n, 3)
    before = None
    updated = False
    for _ in range(rounds):
        update = torch.ones(n, 3)
        read = torch.zeros(n, dtype=torch.bool)
        cap = with_gains(small, gains)
        res = reconstruct_capture(cap, fit_cfg, None)
        if before is None:
            before = rerender_error(res.maps, cap, list(range(n)), res.intensity_scale)
        shown = levelled(res.maps) if level else res.maps
        matte = MapSet(**{**shown.present(), "specular": torch.zeros_like(shown.specular)})
        for i in range(n):
            with torch.no_grad():
                pred = render_maps(shown, cap.lights.select([i]), cap.field_mm, res.intensity_scale)[0]
                diffuse = render_maps(matte, cap.lights.select([i]), cap.field_mm, res.intensity_scale)[0]
            photo = cap.linear([i])[0]
            use = (~cap.saturation([i])[0]).expand_as(pred) & (pred > LIT) & (diffuse > DIFFUSE_SHARE * pred)
            enough = max(MIN_PIXELS, MIN_SHARE * photo[0].numel())
            for c in range(3):
                ratio = photo[c][use[c]] / pred[c][use[c]]
                if ratio.numel() >= enough:
                    update[i, c] = ratio.median()
                    read[i] = True
        if int(read.sum()) < MIN_PHOTO_SHARE * n:
            update = torch.ones(n, 3)
        else:
            updated = True
        gains = gauged(gains * update.clamp(0.2, 5.0), small.lights, level)
    return gains, read, updated, float(before), _fit_error(small, gains, fit_cfg)


def fits_gradient(capture: Capture, cfg: ReconstructConfig) -> bool:
    """Whether the self-calibration fits the gains' gradient across the dome, the sample
    taken as lying level (``cfg.led_gradient``): "fit" yes, "choose" yes first (then the
    other, and the record says which was kept), "none" no, "auto" as ``LEVEL`` says, but
    no where the capture's calibration scales every light (a grey card measured the
    gradient: the gains then correct it, and a sample that does not lie flat keeps its
    tilt)."""
    if cfg.led_gradient != "auto":
        return cfg.led_gradient in ("fit", "choose")
    scaled = (capture.calibration or {}).get("light_scales", {})
    measured = bool(scaled) and all(k is None or str(k) in scaled for k in capture.light_indices)
    return LEVEL and not measured


def gauged(gains: Tensor, lights: LightSet, level: bool) -> Tensor:
    """Gains (N, 3) under the convention ``level`` chooses (``LEVEL``): divided by their
    geometric mean per channel, and without ``level`` their gradient across the dome
    removed too (:func:`without_tilt`)."""
    if not level:
        return without_tilt(gains, lights)
    log = gains.log().double()
    return (log - log.mean(dim=0, keepdim=True)).exp().float()


def levelled(maps: MapSet) -> MapSet:
    """The maps with the median of their normals' slopes (n_x / n_z, n_y / n_z) over the
    image subtracted from every pixel's: the relief kept, the sample laid level (a
    heightfield sheared). The median, not the mean: the mean slope is the height's
    drop from one edge of the field to the other over its width, which a relief cut by
    the field's edges makes large (a sheet embossed with coins 7 mm high: 0.045, where
    its flat ground lies level), and a fit's few wrong slopes (a steep flank's) move it;
    on bench/nearcal.py's 25 materials the true maps' median slope is within 0.011 of
    none."""
    n = maps.normal
    nz = n[2:3].clamp_min(0.2)
    slope = n[0:2] / nz
    slope = slope - median_slope(maps)[:, None, None]
    n = torch.cat([slope, torch.ones_like(nz)])
    return MapSet(**{**maps.present(), "normal": n / n.norm(dim=0, keepdim=True)})


def median_slope(maps: MapSet) -> Tensor:
    """The median over the image of the normals' slopes (n_x / n_z, n_y / n_z): (2,), the
    tilt :func:`levelled` removes."""
    n = maps.normal
    slope = n[0:2] / n[2:3].clamp_min(0.2)
    return slope.reshape(2, -1).median(dim=1).values


def trimmed_slope(maps: MapSet, share: float = 0.1) -> Tensor:
    """The mean over the image of the normals' slopes (n_x / n_z, n_y / n_z) after the
    lowest and highest ``share`` of each are dropped: (2,)."""
    n = maps.normal
    slope = (n[0:2] / n[2:3].clamp_min(0.2)).reshape(2, -1).sort(dim=1).values
    cut = int(share * slope.shape[1])
    return slope[:, cut : slope.shape[1] - cut].mean(dim=1)


def agreed_slope(maps: MapSet) -> Tensor:
    """The tilt of the maps that the median and the 10% trimmed mean of their slopes agree
    on: per axis the one nearer none where both lean the same way, else none (2,) (the
    minmod of the two). Neither alone finds the level of every sample: on
    bench/nearcal.py's 25 materials at 128² the true maps' median slope is 0.0104 off
    none on an embossed leather (0.0051 a heavy weave, 0.0062 a corrugated sheet), where
    the trimmed mean is within 0.0019, and the trimmed mean is 0.043 off on a sheet
    embossed with coins (the relief cut by the field's edge), where the median is within
    0.0005; where they agree the tilt is within 0.0019 on 24 of the 25 (a black
    leather's 0.0040, its median's)."""
    median, trimmed = median_slope(maps), trimmed_slope(maps)
    nearer = torch.where(median.abs() <= trimmed.abs(), median, trimmed)
    return torch.where(median * trimmed > 0, nearer, torch.zeros_like(nearer))


#: The share of a sample's surface taken to lie below its base plane (:func:`base_slope`).
BASE_SHARE = 0.1


def base_slope(maps: MapSet, share: float | None = None) -> Tensor:
    """The tilt (2,) of the maps' base plane, as slopes (n_x / n_z, n_y / n_z): the plane
    that only ``share`` (``BASE_SHARE``) of the height integrated from the normals
    (:func:`integrated_height`) lies below, by quantile regression (Koenker and Bassett
    1978). The ground between a relief's features, not a statistic of every normal: the
    median slope is that of the features' flanks too (an embossed leather's is 0.0104 off
    none lying level), and the mean slope is the height's drop from edge to edge, which
    features cut by the field's edges make large (a sheet embossed with coins: 0.045). On
    bench/nearcal.py's 25 materials at 128² the true maps' base plane is within 0.0017 of
    level on all of them (``--levels``)."""
    share = BASE_SHARE if share is None else share
    n = maps.normal.double()
    height = integrated_height(n[0:2] / n[2:3].clamp_min(0.2))
    rows, cols = height.shape
    y, x = torch.meshgrid(
        -torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64), indexing="ij"
    )
    design = torch.stack([torch.ones_like(height), x - x.mean(), y - y.mean()], -1).reshape(-1, 3)
    target = height.reshape(-1)
    coef = torch.linalg.lstsq(design, target[:, None]).solution[:, 0]
    for _ in range(50):  # iteratively reweighted least squares of the check loss
        r = target - design @ coef
        w = (torch.where(r > 0, share, 1 - share) / r.abs().clamp_min(1e-6)).sqrt()
        coef = torch.linalg.lstsq(design * w[:, None], (target * w)[:, None]).solution[:, 0]
    return (-coef[1:]).to(maps.normal.dtype)


def integrated_height(slope: Tensor) -> Tensor:
    """The height (H, W) in pixels, zero mean, whose differences between neighbouring
    pixels best fit, in least squares, the slopes (2, H, W) = (n_x / n_z, n_y / n_z)
    averaged over each pair (x right, y up: ∂h/∂x = −n_x / n_z), with the field's edges
    free (:func:`matscan.reconstruct.surface.integrate_differences`): a tilted plane comes
    back a plane."""
    from matscan.reconstruct.surface import integrate_differences

    dtype = slope.dtype
    slope = slope.double()
    along_x = -(slope[0][:, 1:] + slope[0][:, :-1]) / 2  # h[i, j + 1] − h[i, j]
    along_rows = (slope[1][1:] + slope[1][:-1]) / 2  # h[i + 1, j] − h[i, j] (rows run down)
    return integrate_differences(along_x, along_rows).to(dtype)


def without_tilt(gains: Tensor, lights: LightSet) -> Tensor:
    """Gains (N, 3) with the part of their logarithm that is linear in the lights'
    horizontal directions removed, and divided by their geometric mean, per channel.

    A gain that grows toward one side of the dome and a sample tilted toward that side
    photograph alike (measured: left in, the estimated gains of a simulated dome24
    capture were off by a cosine of the LED azimuth, ±9%). The sample lies flat on the
    stage, so the tilt is taken as none, and the dome's LEDs as having no brightness
    gradient from one side to the other that a flat target would not show."""
    design, coef = _linear_part(gains, lights)
    log = gains.log().double() - design[:, 1:] @ coef[1:]
    log = log - log.mean(dim=0, keepdim=True)
    return log.exp().float()


def gradient(gains: Tensor, lights: LightSet) -> Tensor:
    """The gains' gradient across the dome (2, 3): the slope of their logarithm along the
    lights' horizontal directions x and y, per channel (what :func:`without_tilt` removes)."""
    return _linear_part(gains, lights)[1][1:].float()


def _linear_part(gains: Tensor, lights: LightSet) -> tuple[Tensor, Tensor]:
    """The design [1, x, y] of the lights' unit directions (N, 3) and the least-squares
    coefficients (3, 3) of the gains' logarithm on it (constant, x, y; per channel)."""
    d = lights.position / lights.position.norm(dim=-1, keepdim=True)
    design = torch.stack([torch.ones(len(d)), d[:, 0], d[:, 1]], dim=1).double()
    return design, torch.linalg.lstsq(design, gains.log().double()).solution


def _fit_error(capture: Capture, gains: Tensor, cfg: ReconstructConfig) -> float:
    """Re-rendering RMSE of a fit to all the photos divided by ``gains``, rendered under
    the lights times ``gains`` and compared with the photos themselves (so that it
    compares with the fit at the rig file's intensities, gains of 1)."""
    from matscan.reconstruct.job import reconstruct_capture
    from matscan.reconstruct.solver import rerender_error

    res = reconstruct_capture(with_gains(capture, gains), cfg, None)
    lit = replace(capture, lights=capture.lights.with_intensity(capture.lights.intensity * gains))
    return rerender_error(res.maps, lit, list(range(len(capture.files))), res.intensity_scale)


def calibration_document(capture: Capture, gains: Tensor, lights: LightSet | None = None) -> dict[str, Any]:
    """The gains as a calibration file (matscan.calibrate's format, ``light_scales`` per
    rig light, RGB), so that a later capture on the same rig can name it. ``capture`` is
    the capture as calibrated before self-calibration: its own calibration (colour
    matrix, scales, flat fields, light positions) is carried over with the gains
    multiplied into its scales (:func:`matscan.calibrate.with_light_gains`). ``lights``,
    where the positions were self-calibrated too, gives the near lights' positions
    (``light_positions_mm``, replacing any the calibration had)."""
    from matscan.calibrate import with_light_gains

    doc = with_light_gains(capture, gains)
    if lights is not None:
        placed = dict(doc.get("light_positions_mm", {}))
        for i, k in enumerate(capture.light_indices):
            if k is not None and float(lights.w[i]) > 0.5:
                placed[str(k)] = [round(float(v), 3) for v in lights.position[i]]
        if placed:
            doc["light_positions_mm"] = dict(sorted(placed.items(), key=lambda kv: int(kv[0])))
    return doc
