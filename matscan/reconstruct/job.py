"""The ``reconstruct`` job: checks, run, write, record.

1. **Check** the capture (:func:`check_capture`): saturated or black photos,
   lights missing from the rig's full set, what reading and calibrating found;
   each becomes a warning that says what to do.
2. **Networks** (:mod:`matscan.reconstruct.networks`): the start, and the prior.
3. **Solver** (:mod:`matscan.reconstruct.solver`): refinement by inverse rendering.
4. **Surface** (:mod:`matscan.reconstruct.surface`): alpha, height, metal/rough.

:func:`reconstruct` claims its output before reading anything
(:mod:`matscan.outputs`), then writes the maps (design.md conventions), the
exports, the report and ``matscan.json`` (rig, inputs, model, conventions,
timings, mm per pixel, version) atomically.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from matscan import __version__
from matscan.capture import Capture, load_capture
from matscan.color import linear_to_srgb
from matscan.errors import MatscanError
from matscan.hsh import HSH_TERMS, fit_hsh, relight_hsh
from matscan.jsonfile import dumps
from matscan.losses import ssim
from matscan.mapset import CONVENTIONS, MapSet, write_maps
from matscan.nets import MapNets
from matscan.outputs import RECORD
from matscan.reconstruct.lm import SolverConfig
from matscan.reconstruct.networks import capture_mirrors, predict_maps
from matscan.reconstruct.solver import clips_are_bounds, flat_start, refine_maps, rerender_error, solve_maps
from matscan.reconstruct.surface import alpha_from_backlight, height_from_normals
from matscan.render import render_maps
from matscan.rig import LightSet

if TYPE_CHECKING:
    from matscan.anyrig import AnyRigNet

REFINE_CHOICES = ("auto", "on", "off")
#: The self-calibration's light scales, as a calibration file later captures can name.
SELF_CALIBRATION = "self_calibration.json"
#: Every self-calibration setting off: the fits the self-calibration makes, and the one after it.
SELF_CALIBRATION_OFF = {
    "self_calibrate": False,
    "self_calibrate_positions": False,
    "shared_f0": None,
    "led_gradient": "auto",
}
#: ``ReconstructConfig.led_gradient``'s values (selfcal.fits_gradient).
LED_GRADIENTS = ("auto", "fit", "none", "choose")
SOLVERS = ("lm", "adam")


@dataclass(frozen=True)
class ReconstructConfig:
    """How a capture is reconstructed."""

    model: str = "default"
    # where the model does not read the rig, start from an any-rig network: "default" (the
    # shipped one) or a weights file; "none": flat maps
    anyrig: str = "none"
    refine: str = "auto"  # "auto": by photo count and evidence (reconstruct_capture); "on"; "off"
    solver: str = "lm"  # "lm": second-order, with confidence maps; "adam": first-order (fits emissive too)
    lm: SolverConfig = SolverConfig()
    refine_steps: int = 150  # the settings below are the adam solver's
    refine_lr: float = 0.02
    prior_weight: float = 0.05
    smooth_weight: float = 0.01
    tile: int = 512
    overlap: int = 64
    mirrors: bool = False  # average the networks' maps over the rig's mirrors that keep the lit lights (networks.py)
    refine_tile: int = 128
    saturation_warn: float = 0.05
    emissive: bool = False  # also fit an emissive map (light the sample gives off under any LED)
    validate: int = 0  # leave this many photos out, reconstruct, and report their re-rendering error
    self_calibrate: bool = False  # estimate each light's RGB intensity with the maps (selfcal)
    self_calibrate_positions: bool = False  # and the near lights' positions (lightpos); needs self_calibrate
    # in that fit, one F0 for the dielectric pixels (True) or each pixel's own (False); None:
    # lightpos.SHARED_F0 (one, docs/rti-record.md says why); other than None needs self_calibrate_positions
    shared_f0: bool | None = None
    # what fixes the self-calibrated gains' gradient across the dome, which a tilted sample
    # photographs like (selfcal.fits_gradient): "fit" (the sample lies level, the gradient is
    # fitted), "none" (the LEDs have none), "choose" (both estimated, the one that re-renders
    # the photos better kept: a sample that may not lie level), "auto" ("choose" as
    # selfcal.LEVEL and CHOOSE say, "none" where the capture's calibration scales every
    # light; where the level gains are kept but refused, the other's, selfcal.FALLBACK);
    # other than "auto" needs self_calibrate
    led_gradient: str = "auto"
    exr: bool = False  # also write every map as float EXR under exr/
    directx_normals: bool = False  # also write normal_directx.png
    # a calibration file read instead of the one the capture names (or none): another
    # capture's self_calibration.json, say, where that capture's photos placed the lights
    # better than this one's can (docs/rti.md, "A dome calibrated once"); used by
    # reconstruct(), not by reconstruct_capture(), which takes the capture as calibrated
    calibration: str | None = None

    def __post_init__(self) -> None:
        """Refuse settings no reconstruction can use, before any work."""
        if self.refine not in REFINE_CHOICES:
            raise MatscanError(f"refine: {self.refine!r} is not one of {', '.join(REFINE_CHOICES)}")
        if self.solver not in SOLVERS:
            raise MatscanError(f"solver: {self.solver!r} is not one of {', '.join(SOLVERS)}")
        if not isinstance(self.lm, SolverConfig):
            raise MatscanError(f"lm: expected a SolverConfig, got {type(self.lm).__name__}")
        for name, low in (("refine_steps", 1), ("tile", 16), ("overlap", 0), ("refine_tile", 8), ("validate", 0)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise MatscanError(f"{name}: {value!r} must be an integer of at least {low}")
        for name in ("refine_lr", "prior_weight", "smooth_weight", "saturation_warn"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise MatscanError(f"{name}: {value!r} must be a finite number of at least 0")
        if self.refine_lr == 0:
            raise MatscanError("refine_lr: must be above 0")
        if self.self_calibrate_positions and not self.self_calibrate:
            raise MatscanError(
                "self_calibrate_positions: needs self_calibrate (the positions are fitted with the gains)"
            )
        if self.calibration is not None and (not isinstance(self.calibration, str) or not self.calibration):
            raise MatscanError(f"calibration: {self.calibration!r} must be a file name or None")
        if self.shared_f0 is not None and not isinstance(self.shared_f0, bool):
            raise MatscanError(f"shared_f0: {self.shared_f0!r} must be True, False or None (lightpos.SHARED_F0)")
        if self.shared_f0 is not None and not self.self_calibrate_positions:
            raise MatscanError("shared_f0: needs self_calibrate_positions (it is a setting of the positions' fit)")
        if self.emissive and self.refine == "off":
            raise MatscanError("emissive: the emissive map is fitted by refinement; drop --emissive or --refine off")
        if self.led_gradient not in LED_GRADIENTS:
            raise MatscanError(f"led_gradient: {self.led_gradient!r} is not one of {', '.join(LED_GRADIENTS)}")
        if self.led_gradient != "auto" and not self.self_calibrate:
            raise MatscanError("led_gradient: needs self_calibrate (it is a setting of the intensities' fit)")


#: ``--refine auto`` refines captures with at least this many photos, per solver. With the
#: networks on a fixed-light rig the lm solver's choice is made below (ONE_PHOTO,
#: EVIDENCE_PHOTOS); this table then holds for adam, and for lm where no choice is made.
#: adam, measured in docs/results.md (11 materials, Table 4 subsets): from 10 photos up
#: refinement lowers every error of the networks' maps but specular's (a tie) and halves
#: the re-rendering error under novel lights; with 1–3 it raises nearly all of them.
#: lm, measured on five map sets unlike the training set (two texture-photograph sets,
#: metallic print, embossed leather, dark glossy; 128², 8-bit sRGB): mean novel-light
#: RMSE of the networks' maps → refined, 1 photo 0.0672 → 0.0673, 2 photos 0.0588 →
#: 0.0510, 3 photos 0.0499 → 0.0476, 6 photos 0.0436 → 0.0295, 24 photos 0.0340 → 0.0059
#: (adam's refinement: 0.0104 at 24).
REFINE_AUTO_PHOTOS = {"lm": 2, "adam": 10}


@dataclass
class Result:
    """What :func:`reconstruct_capture` found: the maps, warnings, timings, the fitted
    intensity scale, and (from the ``lm`` solver) a confidence map per map in [0, 1]."""

    maps: MapSet
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    intensity_scale: float = 1.0
    refine_history: list[float] = field(default_factory=list)
    refined: bool = False
    confidence: dict[str, Tensor] = field(default_factory=dict)
    choice: dict[str, Any] | None = None  # what ``--refine auto`` compared, when it compared
    start: str = "flat"  # what the maps started from: "networks", "any-rig network" or "flat"
    mirrors: int = 0  # views the networks' maps are the mean of (1: the capture itself; 0: no networks)
    light_gains: Tensor | None = None  # (N, 3) per-photo gains found by self-calibration
    lights: LightSet | None = None  # the photos' lights, where self-calibration moved them
    self_calibration: dict[str, Any] | None = None  # its record


#: From this many photos the dome24 networks' start takes the ``lm`` solver's steps on
#: where pixels still converge (``SolverConfig.more_iterations``), as every other start
#: does from ``more_from``; with fewer, the fixed steps' hold on the networks' maps
#: relit better (at 2, 3 and 10 lights of the engine study; runs/lm-converge/README.md).
#: None: never. runs/lm-converge-nets/README.md has the rule.
NETWORKS_MORE_FROM: int | None = None


#: Prior strength of the ``lm`` solver when it starts from flat maps (no networks):
#: the start knows nothing, so the photos decide nearly everything.
FLAT_START_PRIOR = 0.2
#: Prior strength of the ``lm`` solver when it starts from the any-rig network's maps, by
#: the capture's photo count: (up to this many photos, strength), in order
#: (:func:`anyrig_hold`). Tuned per count on a dome neither benchmark uses, procedural and
#: photo-built materials (``bench/anyrig.py --hold``): from 2 to 4 photos holding the
#: network's maps hard is 3–4% better than the flat start's hold, from 6 up the photos
#: should decide (runs/anyrig-render3-cpu/README.md, the fourth rule).
ANYRIG_HOLD: tuple[tuple[float, float], ...] = ((2.45, 2.0), (4.24, 4.0), (math.inf, FLAT_START_PRIOR))


def anyrig_hold(photos: int) -> float:
    """The solver's hold on the any-rig network's maps from ``photos`` photos (``ANYRIG_HOLD``).
    Leave-out validation refits from the photos it keeps, so with their count's hold, as a
    capture of that many photos would be reconstructed."""
    return next(strength for top, strength in ANYRIG_HOLD if photos <= top)


#: The any-rig network starts the solver from this many photos up. From one photo every
#: any-rig network trained so far started it worse than flat maps on the unseen simulated
#: dome (novel-light RMSE 0.1273, 0.1404, 0.1604 against 0.1209), while from 2 to 12
#: photos the latest is 8–26% better (runs/anyrig-one-cpu/README.md).
ANYRIG_MIN_PHOTOS = 2


#: A photo whose 99th-percentile linear value is below this is black: 8-bit sRGB code 4 is
#: linear 0.0012, so nothing in it rose above the sensor's noise (a lens cap, an LED that did not light).
DARK_PHOTO = 0.002


#: More photos than this with some pixels saturated are warned about in one line.
SATURATION_LINES = 3


def _bright_fraction(capture: Capture, i: int) -> float:
    """The fraction of photo ``i``'s values at or above :data:`DARK_PHOTO`, a strip at a time."""
    count = 0
    for rows in capture.strips(photos=1):
        count += int((capture.linear([i], rows) >= DARK_PHOTO).sum())
    return count / capture.images[i].numel()


#: ``check_capture`` warns where a pixel's width and height (the field over the photos'
#: size) differ by more than this share: photos framed otherwise than the rig's field.
ASPECT_TOLERANCE = 0.01


def calibration_name(capture: Capture, capture_path: Path, out: Path) -> str | None:
    """The calibration a reconstruction applied, for its record: the file (relative to
    ``out``, as the record's other paths are), "inline in capture.json" where the capture
    holds it, or None for none."""
    if capture.calibration is None:
        return None
    if capture.calibration_file is None:
        return f"inline in {os.path.relpath((capture_path / 'capture.json').resolve(), out)}"
    return os.path.relpath(Path(capture.calibration_file).resolve(), out)


def check_capture(capture: Capture, cfg: ReconstructConfig) -> list[str]:
    """Warnings about a capture, each saying what to do: saturated or black photos,
    missing lights, and what reading and calibrating it found (``capture.meta["warnings"]``)."""
    warnings = list(capture.meta.get("warnings", []))
    dark, partly = [], []
    for i, (file, sat) in enumerate(zip(capture.files, capture.saturated, strict=True)):
        frac = float(sat.float().mean())
        if frac > 0.5:
            warnings.append(
                f"{file}: {frac:.0%} of pixels saturated, so it says almost nothing; lower the exposure and retake it"
            )
        elif frac > cfg.saturation_warn:
            partly.append((file, frac))
        # the 99th percentile is below DARK_PHOTO exactly when under 1% of the values reach it
        if _bright_fraction(capture, i) < 0.01:
            dark.append(file)
    # what the fit makes of them: the lm solver reads them as lower bounds where they are
    # (clips_are_bounds); the adam solver (and so --emissive) leaves them out
    if cfg.refine == "off":
        read = ""
    elif cfg.solver == "lm" and not cfg.emissive and cfg.lm.censored and clips_are_bounds(capture):
        read = " (the fit reads them only as at least that bright)"
    else:
        read = " (they are left out of the fit)"
    if len(partly) > SATURATION_LINES:  # one line for many: an RTI dome's low ring saturates a glossy panel
        least, most = min(f for _, f in partly), max(f for _, f in partly)
        warnings.append(
            f"{len(partly)} of {len(capture.files)} photos have {least:.1%} to {most:.1%} of their "
            "pixels saturated ("
            + ", ".join(f"{file} {frac:.1%}" for file, frac in partly)
            + f"); lower the exposure{read}"
        )
    else:
        warnings += [f"{f}: {frac:.1%} of pixels saturated; lower the exposure{read}" for f, frac in partly]
    if dark and len(dark) == len(capture.files):
        warnings.append(
            "every photo is black (was the lens cap on, or the lights off?); the maps mean nothing — retake the capture"
        )
    else:
        warnings += [f"{f}: the photo is black (did its light fail?); retake it or leave it out" for f in dark]
    (px, py), (h, w) = capture.mm_per_pixel, capture.size
    if abs(px / py - 1) > ASPECT_TOLERANCE:
        warnings.append(
            f"the photos are {w}×{h} px but the field is {capture.field_mm[0]:g}×{capture.field_mm[1]:g} mm, so a "
            f"pixel is {px:.3g}×{py:.3g} mm, not square: frame the camera so that the photos cover the rig's field "
            "exactly (docs/hardware.md), or the maps are stretched"
        )
    if not capture.rig.per_image_geometry:
        missing = sorted(set(range(len(capture.rig.lights))) - {k for k in capture.light_indices if k is not None})
        if missing:
            warnings.append(
                f"lights {', '.join(map(str, missing))} of rig {capture.rig.name} are missing; "
                "reconstructing from the other photos"
            )
    return warnings


def unnamed_subset(capture: Capture) -> str | None:
    """A warning when the capture's lights are neither all of its rig's nor one of its
    named subsets (dome24: the paper's Table 4), which the rig's networks were trained on
    most: at the same count other lights give them measurably worse maps (docs/results.md,
    "Which lights"). None when they are, or when the rig names no subsets."""
    rig = capture.rig
    if rig.per_image_geometry or not rig.subsets:
        return None
    lit = {k for k in capture.light_indices if k is not None}
    if lit == set(range(len(rig.lights))) or any(lit == set(members) for members in rig.subsets.values()):
        return None
    names = ", ".join(sorted(rig.subsets, key=lambda k: len(rig.subsets[k])))
    return (
        f"lights {', '.join(map(str, sorted(lit)))} are not one of rig {rig.name}'s named subsets ({names}), "
        "which its networks were trained on most; a named subset of as many lights gives better maps "
        "(docs/results.md, 'Which lights')"
    )


#: ``--refine auto`` (with the lm solver) chooses by evidence (:func:`choose_by_evidence`)
#: for captures with at least EVIDENCE_PHOTOS[0] and fewer than EVIDENCE_PHOTOS[1] photos:
#: there the networks + solver win on some materials and the solver alone on others (the
#: networks mislead on dark glossy ones), and the photos left out tell which (docs/results.md:
#: with 2 and 3 photos the choice beat every single method). From 4 photos the networks +
#: solver are used: with a single photo left out of 6 the choice was noisier than the
#: differences it had to find. One photo leaves none to judge by: see ONE_PHOTO.
EVIDENCE_PHOTOS = (2, 4)

#: The candidates ``--refine auto`` compares: (networks used, refine). The first is the
#: default, the better in the mean on every set measured (docs/results.md).
CANDIDATES = {"networks+solver": (True, "on"), "solver": (False, "on")}

#: The solver alone is chosen only where it re-renders the left-out photos at least this
#: fraction better (RMSE) than the networks + solver. Each fold reconstructs from fewer
#: photos than the capture has (of two, from one), so small differences in that score do
#: not carry over to the full capture: on gold foil print, 0.1393 against 0.1397 chose the
#: solver, whose maps then relit 74% worse. Chosen on a selection set of 16 procedural
#: materials that neither training nor the published studies use (docs/results.md, "A
#: margin for the evidence"): mean novel-light RMSE at 2 and 3 photos, with two weights
#: files (``tools/evidence_margin.py``), 0.0668 with no margin, 0.0647 at 2.5%, 0.0587
#: from 5% to 10%, 0.0594 at 15%, 0.0589 at 20% (the networks + solver always: 0.0614);
#: the smallest margin within 0.5% of the best.
EVIDENCE_MARGIN = 0.05


def evidence_winner(scores: dict[str, float], margin: float = EVIDENCE_MARGIN) -> str:
    """The candidate to use given each one's left-out RMSE: the default (the first of
    :data:`CANDIDATES`) unless another beats it by more than ``margin`` (a fraction of the
    default's error); of several such, the lowest."""
    default = next(iter(CANDIDATES))
    rivals = [k for k in scores if k != default and scores[k] < (1 - margin) * scores[default]]
    return min(rivals, key=lambda k: scores[k]) if rivals else default


#: What ``--refine auto`` does with one photo (lm solver): the networks' maps, unrefined.
#: Measured in docs/results.md (256², 8-bit sRGB, novel-light RMSE, weights a42bd4d2): on
#: 8 map sets unlike the training set the networks 0.0606, the solver from a flat start
#: 0.0653, the networks refined 0.0618; on 8 procedural ones 0.0614, 0.0591 and 0.0609.
#: The networks win on 11 of the 16 and in the mean of both sets; where they lose, the
#: solver's maps are the trivial baseline's (one photo fixes nothing else), and refining
#: the networks' maps from that one photo moves them toward it. With weights 7ae143b9
#: (G_g from runs/dome24-mix6-cpu) the networks give 0.0592 and 0.0571.
ONE_PHOTO = "networks"
ALL_CANDIDATES = {"networks": (True, "off"), **CANDIDATES}


def held_out_positions(n: int, count: int) -> list[int]:
    """``count`` positions spread evenly over ``n`` photos."""
    return sorted({round((i + 0.5) * n / count - 0.5) for i in range(count)})


def evidence_folds(n: int) -> list[list[int]]:
    """The photos each candidate must predict without seeing them: a sixth of them (at
    least one, spread evenly); of two photos, each from the other."""
    return [[0], [1]] if n == 2 else [held_out_positions(n, max(1, round(n / 6)))]


def choose_by_evidence(capture: Capture, cfg: ReconstructConfig, nets: MapNets) -> tuple[str, dict[str, Any]]:
    """Which candidate (:data:`CANDIDATES`) predicts photos it has not seen best: each
    reconstructs from the capture without the photos of a fold (:func:`evidence_folds`)
    and is scored by the RMSE of re-rendering those, averaged over folds; the default wins
    unless another is better by :data:`EVIDENCE_MARGIN` (:func:`evidence_winner`). Returns
    the winner and the record of the comparison (photos left out, each candidate's RMSE,
    the margin)."""
    n = len(capture.files)
    folds = evidence_folds(n)
    scores = dict.fromkeys(CANDIDATES, 0.0)
    for left in folds:
        kept = capture.select([i for i in range(n) if i not in left])
        for name, (use_nets, refine) in CANDIDATES.items():
            res = reconstruct_capture(kept, replace(cfg, refine=refine), nets if use_nets else None)
            scores[name] += rerender_error(res.maps, capture, left, res.intensity_scale) / len(folds)
    best = evidence_winner(scores)
    left_out = [capture.files[i] for fold in folds for i in fold]
    return best, {
        "chosen": best,
        "left_out": left_out,
        "folds": len(folds),
        "rmse_left_out": scores,
        "margin": EVIDENCE_MARGIN,
    }


def networks_misfit(nets: MapNets, capture: Capture) -> str | None:
    """Why the networks cannot read this capture (None when they can): they take one
    fixed rig's light slots, so not per-image geometry nor another number of lights."""
    if capture.rig.per_image_geometry:
        return f"rig {capture.rig.name}: the networks do not apply to per-image geometry"
    if nets.n_lights != len(capture.rig.lights):
        return (
            f"rig {capture.rig.name}: the networks are trained for {nets.n_lights} light slots, "
            f"the rig has {len(capture.rig.lights)}"
        )
    return None


def reconstruct_capture(
    capture: Capture,
    cfg: ReconstructConfig = ReconstructConfig(),
    nets: MapNets | None = None,
    progress: bool = False,
    anyrig: AnyRigNet | None = None,
) -> Result:
    """Maps from a loaded capture (no files written). Networks that do not fit the
    capture's rig (:func:`networks_misfit`) are set aside with a warning. Without
    networks the solver starts from the maps of ``anyrig`` (an any-rig network, which
    reads any rig) when given and there are at least ``ANYRIG_MIN_PHOTOS`` photos, else
    from flat maps, and refines them (``refine`` "auto" or "on") held near them with
    :func:`anyrig_hold` or the flat start's weak prior (``FLAT_START_PRIOR``; docs/rti.md
    measures both starts)."""
    if cfg.self_calibrate:
        from matscan.reconstruct.selfcal import CHOOSE_MARGIN, estimate_gains, with_gains

        t0 = time.perf_counter()
        gains, record = estimate_gains(capture, cfg)
        lights, notes, held = None, [], False
        # where a calibration placed the lights and its intensities were right already (the
        # estimate refused as no better), the places are fitted from the calibration's all
        # the same where lightpos.CALIBRATED_SPREAD_MM or CALIBRATED_COMMON is on (off by default)
        from matscan.reconstruct import lightpos

        placed = "light_positions_mm" in (capture.calibration or {})
        if lightpos.CALIBRATED_COMMON not in lightpos._COMMON:
            raise ValueError(f"lightpos.CALIBRATED_COMMON: one of {', '.join(lightpos._COMMON)}")
        common = placed and lightpos.CALIBRATED_COMMON != "off"
        refit = placed and "rejected" in record and (lightpos.CALIBRATED_SPREAD_MM > 0 or common)
        scaled = (capture.calibration or {}).get("light_scales", {})
        calibrated = bool(scaled) and all(k is None or str(k) in scaled for k in capture.light_indices)
        # a calibration's scales that re-render the photos as well as the estimate are kept as
        # they are, where the capture's own intensities re-estimated with the lights held cost a
        # simulated paper and twill 0.10 and 0.14 dB (docs/rti.md, "A dome calibrated once");
        # the rig file's refused (a knit's: the estimate too poor) are fitted with the lights held
        kept = calibrated and "rejected" in record and not refit
        from matscan.reconstruct import selfcal

        if selfcal.HELD_GAINS not in ("off", "unread", "always"):
            raise ValueError(f"selfcal.HELD_GAINS: off, unread or always, not {selfcal.HELD_GAINS!r}")
        # --self-calibrate alone fits the unread intensities with the lights held too
        # (selfcal.HELD_GAINS; runs/selfcal-held/README.md)
        unread_held = cfg.self_calibrate_positions or selfcal.HELD_GAINS != "off"
        if kept:
            if cfg.self_calibrate_positions:
                notes.append(
                    "--self-calibrate-positions: the calibration's intensities are kept, and so are "
                    + ("the calibration's positions" if placed else "the rig file's positions")
                    + " (fitted from these photos where the intensities were right already, a simulated brick's "
                    "lights went 1.39 mm astray: docs/rti.md)"
                )
        elif unread_held and not record["updated"] and not refit:
            from matscan.reconstruct.lightpos import estimate_held_gains

            gains, record["held_gains"] = estimate_held_gains(
                capture, gains, cfg, progress, record["convention"] == "level sample"
            )
            held = True
            why = (
                "the intensities estimated from the photos re-render them no better than the capture's own"
                if "rejected" in record
                else f"only {record['photos_read']} of {len(capture.files)} photos show enough diffuse reflection to "
                "read their light's intensity (a metal or a black fabric shows too little)"
            )
            if not cfg.self_calibrate_positions:
                notes.append(
                    f"--self-calibrate: {why}, so they were fitted with the maps, every light held at its place "
                    "(docs/rti.md)"
                )
            else:
                notes.append(
                    f"--self-calibrate-positions: {why}, so they were fitted with the maps, every light held at its "
                    "place; "
                    + ("the calibration's" if placed else "the rig file's")
                    + " positions are kept (placed from such photos, a simulated knit, worn print and brushed metal's "
                    "lights went 20-87 mm astray: docs/rti-record.md)"
                    + (
                        ""
                        if placed
                        else "; to place them, give --calibration the places of this dome merged from captures of "
                        "samples that show them (matscan calibrate --merge of their self_calibration.json: "
                        'docs/rti.md, "A dome calibrated once")'
                    )
                )
        elif cfg.self_calibrate_positions:
            from matscan.reconstruct.lightpos import estimate_positions

            level = record["convention"] == "level sample"
            together = common and ("rejected" in record or lightpos.CALIBRATED_COMMON == "always")
            lights, gains, record["positions"], notes = estimate_positions(
                capture, gains, cfg, progress, level, together=together
            )
            if lights is not None:
                capture = replace(capture, lights=lights)
        elif selfcal.HELD_GAINS == "always":
            from matscan.reconstruct.lightpos import estimate_held_gains

            gains, record["held_gains"] = estimate_held_gains(
                capture, gains, cfg, progress, record["convention"] == "level sample"
            )
        seconds = time.perf_counter() - t0
        result = reconstruct_capture(
            with_gains(capture, gains),
            replace(cfg, **SELF_CALIBRATION_OFF),
            nets,
            progress,
            anyrig,
        )
        result.light_gains, result.lights, result.self_calibration = gains, lights, record
        result.warnings.extend(notes)
        result.timings["self_calibration_s"] = seconds
        if calibrated:
            result.warnings.append(
                "--self-calibrate: the calibration already scales every light; re-estimated from the photos, "
                "right scales cost up to 0.01 dB on average and 0.08 dB at most on simulated domes (docs/rti.md): "
                "self-calibrate only if the lights have changed since"
            )
        before, after = record["rerender_rmse"]["before"], record["rerender_rmse"]["after"]
        chose = record.get("choice", {})
        if cfg.led_gradient == "auto" and chose and record["convention"] == "no gradient" and record["updated"]:
            nog, lev = f"RMSE {chose['no gradient']:.4g}", f"{chose['level sample']:.4g}"
            how = (
                f"re-render the photos better ({nog}) than those that take the sample as lying level ({lev})"
                if chose["no gradient"] < chose["level sample"]
                else f"re-render the photos within {CHOOSE_MARGIN:.0%} as well ({nog}) as those that take the sample "
                f"as lying level ({lev}), whose gains need a brightness gradient of "
                f"{chose['level gradient']:.3g} across the dome"
            )
            result.warnings.append(
                f"--self-calibrate: the intensities estimated for a dome without a brightness gradient {how}, and "
                "are kept: the sample may not lie level, or the lights' frame is not the sample's (a handheld light's)"
            )
        if "fallback" in record:
            tried = record["fallback"]["rerender_rmse"]
            result.warnings.append(
                f"--self-calibrate: the intensities that take the sample as lying level re-render the photos no "
                f"better than the capture's own (RMSE {tried:.4g} against {before:.4g}): the lights' frame may not "
                "be the sample's (a handheld light's); estimated again for a dome without a brightness gradient"
                + (f", they are kept (RMSE {after:.4g})" if record["updated"] else "")
            )
        if not held:  # where the intensities were fitted with the lights held, notes says so
            if "rejected" in record and "fallback" in record:
                result.warnings.append(
                    f"--self-calibrate: estimated without a gradient, the intensities re-render the photos no better "
                    f"either (RMSE {after:.4g} against {before:.4g}); the capture's own are kept"
                )
            elif "rejected" in record:
                result.warnings.append(
                    f"--self-calibrate: the intensities estimated from the photos re-render them no better than the "
                    f"capture's own (RMSE {after:.4g} against {before:.4g}), which are kept: they were right already, "
                    "or too little of the sample reflects diffusely to read them (a black fabric)"
                )
            elif not record["updated"]:
                result.warnings.append(
                    f"--self-calibrate: only {record['photos_read']} of {len(capture.files)} photos show enough "
                    "diffuse reflection to read their light's intensity (a metal or a black fabric shows too little); "
                    "the rig file's intensities are kept"
                )
        return result
    n = len(capture.files)
    misfit = networks_misfit(nets, capture) if nets is not None else None
    if misfit is not None:
        nets = None
    auto = cfg.refine == "auto" and cfg.solver == "lm" and nets is not None
    if auto and n < EVIDENCE_PHOTOS[1]:
        t0 = time.perf_counter()
        if n >= EVIDENCE_PHOTOS[0]:
            chosen, choice = choose_by_evidence(capture, cfg, nets)
        else:
            chosen, choice = ONE_PHOTO, {"chosen": ONE_PHOTO, "rule": "one photo (docs/results.md)"}
        seconds = time.perf_counter() - t0
        use_nets, refine = ALL_CANDIDATES[chosen]
        # the emissive map is fitted by refinement; a choice not to refine fits none (said below)
        emissive = cfg.emissive and refine != "off"
        sub = replace(cfg, refine=refine, emissive=emissive)
        result = reconstruct_capture(capture, sub, nets if use_nets else None, progress)
        if cfg.emissive and not emissive:
            result.warnings.append(
                f"--emissive needs refinement, which {choice['rule']} leaves out: no emissive map was fitted"
            )
        result.choice = choice
        result.timings["choice_s"] = seconds
        return result
    timings: dict[str, float] = {}
    warnings = check_capture(capture, cfg)
    if anyrig is not None and nets is None and n < ANYRIG_MIN_PHOTOS:
        anyrig = None
        warnings.append("one photo: starting from flat maps, not the any-rig network's (docs/rti.md)")
    if misfit is not None:
        if anyrig is None:  # with the any-rig network asked for, this is its use: no warning
            warnings.append(f"{misfit}; starting refinement from flat maps")
    elif nets is not None and (unnamed := unnamed_subset(capture)) is not None:
        warnings.append(unnamed)
    t0 = time.perf_counter()
    if nets is not None:
        start, begun = predict_maps(nets, capture, cfg.tile, cfg.overlap, progress, cfg.mirrors), "networks"
        views = len(capture_mirrors(capture)) if cfg.mirrors else 1
    elif anyrig is not None:
        from matscan.anyrig import predict_capture

        start = MapSet(**predict_capture(anyrig, capture, cfg.tile, cfg.overlap, progress))
        begun = "any-rig network"
    else:
        start, begun = flat_start(capture), "flat"
    timings["networks_s"] = time.perf_counter() - t0
    used_nets = nets is not None
    refine = cfg.refine == "on" or (
        cfg.refine == "auto" and (not used_nets or len(capture.files) >= REFINE_AUTO_PHOTOS[cfg.solver])
    )
    result = Result(start, warnings, timings, start=begun, mirrors=views if nets is not None else 0)
    if refine and cfg.solver == "lm" and not cfg.emissive:
        t0 = time.perf_counter()
        strength = 1.0 if used_nets else anyrig_hold(n) if begun == "any-rig network" else FLAT_START_PRIOR
        # the networks' start keeps the fixed steps' hold below NETWORKS_MORE_FROM photos
        held_start = used_nets and (NETWORKS_MORE_FROM is None or n < NETWORKS_MORE_FROM)
        lm_cfg = replace(cfg.lm, more_iterations=0) if held_start else cfg.lm
        result.maps, result.confidence, result.intensity_scale = solve_maps(
            start, capture, lm_cfg, strength, progress=progress
        )
        result.refined = True
        timings["refine_s"] = time.perf_counter() - t0
    elif refine:
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
        result.refined = True
    if cfg.emissive and not refine:
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
    return capture.select(positions)


def as_fitted(capture: Capture, res: Result) -> Capture:
    """The capture as the fit that gave ``res`` saw it: its photos divided by the gains
    self-calibration found, and its lights where it placed them (unchanged without)."""
    if res.light_gains is not None:
        from matscan.reconstruct.selfcal import with_gains

        capture = with_gains(capture, res.light_gains)
    if res.lights is not None:
        capture = replace(capture, lights=res.lights)
    return capture


def leave_out_validation(
    capture: Capture, count: int, cfg: ReconstructConfig, nets: MapNets | None, anyrig: AnyRigNet | None = None
) -> dict:
    """Self-validation without ground truth: reconstruct without ``count`` photos
    (spread evenly over the capture) and measure the re-rendering RMSE on them."""
    n = len(capture.files)
    if not 1 <= count <= n - 1:
        raise MatscanError(f"--validate: {count} must be between 1 and {n - 1} (the capture has {n} photos)")
    left = held_out_positions(n, count)
    kept = [i for i in range(n) if i not in left]
    subset = subset_capture(capture, kept)
    res = reconstruct_capture(subset, cfg, nets, anyrig=anyrig)
    # the fitted photos as the fit saw them (self-calibration's gains and places); the
    # left-out ones' gains are unknown, so taken as 1 (docs/rti.md)
    fitted = as_fitted(subset, res)
    record: dict[str, Any] = {
        "left_out": [capture.files[i] for i in left],
        "rmse_left_out": rerender_error(res.maps, capture, left, res.intensity_scale),
        "rmse_fitted": rerender_error(res.maps, fitted, list(range(len(kept))), res.intensity_scale),
    }
    record.update(
        photo_scores(
            capture,
            left,
            lambda i: display(render_maps(res.maps, capture.lights.select([i]), capture.field_mm, res.intensity_scale)),
        )
    )
    if not capture.rig.per_image_geometry and len(kept) >= HSH_TERMS:
        record["hsh"] = hsh_validation(capture, kept, left)
    return record


def display(linear: Tensor) -> Tensor:
    """Linear radiance as the photos display it: clipped to [0, 1], sRGB-encoded (the
    domain of the RTI field's PSNR and SSIM, and of its curve fits)."""
    return linear_to_srgb(linear.clamp(0, 1))


def photo_scores(capture: Capture, positions: list[int], predict: Callable[[int], Tensor]) -> dict[str, float]:
    """PSNR (dB) and SSIM of predicted photos against the captured ones at ``positions``,
    in the display domain (:func:`display`), every pixel counted, as RTI papers score
    relighting. ``predict(i)`` gives the display-domain image (1, 3, H, W) of photo i."""
    se, count, ssims = 0.0, 0, []
    for i in positions:
        truth = display(capture.linear([i]))
        with torch.no_grad():
            pred = predict(i)
        se += float((pred - truth).square().sum())
        count += truth.numel()
        ssims.append(float(ssim(pred, truth)))
    mse = se / count
    psnr = 10 * math.log10(1 / max(mse, 1e-12))
    return {"psnr_left_out": round(psnr, 3), "ssim_left_out": round(sum(ssims) / len(ssims), 4)}


def light_directions(lights) -> Tensor:
    """Unit directions (K, 3) toward each light from the field's centre (for a
    directional light, its direction)."""
    return lights.position / lights.position.norm(dim=-1, keepdim=True)


def hsh_validation(capture: Capture, kept: list[int], left: list[int]) -> dict[str, float]:
    """The RTI field's baseline on the same photos: an order-2 HSH fit (:mod:`matscan.hsh`)
    to the kept photos in the display domain, scored on the left-out ones."""
    coefficients = fit_hsh(display(capture.linear(kept)), light_directions(capture.lights.select(kept)))
    directions = light_directions(capture.lights)
    return photo_scores(capture, left, lambda i: relight_hsh(coefficients, directions[i : i + 1]))


def reconstruct(
    capture_path: str | Path,
    out: str | Path,
    cfg: ReconstructConfig = ReconstructConfig(),
    overwrite: bool = False,
    progress: bool = False,
    overwrite_any: bool = False,
) -> dict[str, Any]:
    """``matscan reconstruct``: read a capture (``"@sample"``: the built-in sample capture),
    write maps and ``matscan.json``; return the record.

    The output is checked and locked before anything is read
    (:func:`matscan.outputs.claim_output`): it never touches the capture, and
    ``overwrite`` replaces only a previous matscan output (any folder with
    ``overwrite_any`` too).
    """
    t_all = time.perf_counter()
    from matscan.calibrate import apply_calibration
    from matscan.capture.folder import with_calibration_file
    from matscan.outputs import calibration_inputs, capture_inputs, claim_output
    from matscan.samples import capture_folder
    from matscan.weights import anyrig_path, model_path

    capture_path = capture_folder(capture_path)
    inputs = capture_inputs(capture_path)
    if cfg.calibration is not None:
        inputs += calibration_inputs(Path(cfg.calibration))
    if cfg.model != "none":
        inputs.append(model_path(cfg.model))
    if cfg.anyrig != "none":
        inputs.append(anyrig_path(cfg.anyrig))
    with claim_output(out, "reconstruct", inputs, overwrite=overwrite, overwrite_any=overwrite_any) as claim:
        capture = load_capture(capture_path)
        if cfg.calibration is not None:
            capture = with_calibration_file(capture, cfg.calibration)
        capture = apply_calibration(capture)
        h, w = capture.size
        claim.check_space(output_bytes(h, w, cfg))
        nets, model_name, networks = None, "none", {}
        if cfg.model != "none":
            from matscan.weights import load_model
            from matscan.weights.format import training_record

            nets, model_meta = load_model(cfg.model)
            file = model_path(cfg.model).resolve()  # relative to this folder, so the record moves with it
            model_name, networks = os.path.relpath(file, claim.path), training_record(model_meta)
        anyrig, anyrig_name = None, None
        if cfg.anyrig != "none":  # read even where unused (2 MB): a damaged file is named, not passed over
            from matscan.weights import load_anyrig

            anyrig = load_anyrig(cfg.anyrig)
            if nets is None or networks_misfit(nets, capture) is not None:
                anyrig_name = os.path.relpath(anyrig_path(cfg.anyrig).resolve(), claim.path)
            else:
                anyrig = None
        t_validation = time.perf_counter()
        validation = leave_out_validation(capture, cfg.validate, cfg, nets, anyrig) if cfg.validate else None
        t_validation = time.perf_counter() - t_validation
        res = reconstruct_capture(capture, cfg, nets, progress, anyrig)
        if validation is not None:  # its own reconstruction, without the photos it leaves out
            res.timings["validation_s"] = t_validation
        calibrated = capture  # before the gains: self_calibration.json composes with its calibration
        capture = as_fitted(capture, res)  # the photos as the fit saw them, for every number below
        from matscan.report.html import per_light_rows, write_report

        # the report's per-photo re-renderings give the overall error too: one rendering pass
        light_rows = per_light_rows(capture, res.maps, res.intensity_scale)
        error = light_rows[1]
        record = {
            "format": "matscan-reconstruction/1",
            "matscan_version": __version__,
            "capture": os.path.relpath(capture_path.resolve(), claim.path),  # relative to this folder
            "rig": capture.rig.name,
            "inputs": [{"file": f, "light": k} for f, k in zip(capture.files, capture.light_indices, strict=True)],
            "size_px": [w, h],
            "field_mm": list(capture.field_mm),
            "mm_per_pixel": list(capture.mm_per_pixel),
            "model": {"name": cfg.model, "file": model_name, "networks": networks, "anyrig_file": anyrig_name},
            "start": res.start,
            "mirrors": res.mirrors,
            "config": asdict(cfg),
            "refined": res.refined,
            "solver": cfg.solver if res.refined else None,
            "choice": res.choice,
            "intensity_scale": res.intensity_scale,
            "rerender_rmse": error,
            "warnings": res.warnings,
            "conventions": CONVENTIONS,
            "timings_s": {k: round(v, 3) for k, v in res.timings.items()},
        }
        record["calibration"] = calibration_name(calibrated, capture_path, claim.path)
        if "exposure_ratio" in capture.meta:  # the calibration's scales, brought to this capture's exposure
            record["calibration_exposure_ratio"] = capture.meta["exposure_ratio"]
        if validation is not None:
            record["validation"] = validation
        if res.self_calibration is not None:
            record["self_calibration"] = {**res.self_calibration, "file": SELF_CALIBRATION}
        dumps(record, RECORD)  # a non-finite number is refused here, before any file is written
        with claim.folder() as tmp:
            write_maps(tmp, res.maps)
            from matscan.export import export_all

            record["exports"] = export_all(tmp, res.maps, capture.field_mm, cfg.exr, cfg.directx_normals)
            record["confidence"] = write_confidence(tmp, res.confidence)
            if res.light_gains is not None:
                from matscan.reconstruct.selfcal import calibration_document

                doc = calibration_document(calibrated, res.light_gains, res.lights)
                (tmp / SELF_CALIBRATION).write_text(dumps(doc, SELF_CALIBRATION), encoding="utf-8")
                record["exports"].append(SELF_CALIBRATION)
            write_report(
                tmp / "report.html", capture, res.maps, record, res.intensity_scale, res.confidence, light_rows
            )
            record["timings_s"]["total_s"] = round(time.perf_counter() - t_all, 3)
            (tmp / RECORD).write_text(dumps(record, RECORD), encoding="utf-8")
    return record


def write_confidence(folder: Path, confidence: dict[str, Tensor]) -> dict[str, Any]:
    """Write ``confidence_<map>.png`` (8-bit grey, linear: 1 = the photos determined the
    value, 0 = the networks' prior filled it in); return the record's entry."""
    from matscan.imagefile import write_image

    entry: dict[str, Any] = {}
    for name, t in confidence.items():
        file = f"confidence_{name}.png"
        write_image(folder / file, t.clamp(0, 1).permute(1, 2, 0).numpy(), bits=8, colourspace="linear")
        entry[name] = {"file": file, "mean": round(float(t.mean()), 4)}
    return entry


def output_bytes(h: int, w: int, cfg: ReconstructConfig) -> int:
    """A generous estimate of what a reconstruction of H×W pixels writes: about ten
    16-bit maps, their glTF textures (three times: beside the .gltf, inside the .glb and
    the .usdz), the report, and float EXRs when asked."""
    per_px = 96 + (60 if cfg.exr else 0)
    return h * w * per_px + (8 << 20)
