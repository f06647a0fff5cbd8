"""Near lights' positions from the photos alone, fitted jointly with the intensities and the maps.

``--self-calibrate-positions`` (after :mod:`matscan.reconstruct.selfcal` has estimated the
intensities): every near light's position (3 numbers), every photo's RGB gain and, at a
sample of the pixels, every pixel's maps (ρ and F0 per channel, roughness and the normal's
two slopes: 9 numbers) are fitted together to the photos, by Gauss–Newton with
Levenberg–Marquardt damping, as bundle adjustment fits cameras and points (Triggs et al.
2000, "Bundle adjustment — a modern synthesis"). Each pixel's 9 × 9 block is eliminated
(the Schur complement), so a step solves one system over the lights only (6 numbers a
light). The misfit is weighted by the photos' noise, var = a·m + b (shot and read
noise), with a and b read from the start's residuals (the median of the squared residual
in bins of brightness): relative residuals, which the solver uses, weigh the dark pixels
too much, and the positions came out 2 to 6 mm off (docs/rti-record.md). Where the model cannot
follow the photos the lights must not move to explain them: pixels the start misfits
more than ``OUTLIER`` times the median pixel are left out, and the rest are weighed by
Cauchy's loss (``ROBUST``). Without the two, a heavy weave and a corrugated sheet (flanks
of 30°-50°) drew the LEDs 30 mm away.

What the photos cannot tell is fixed by convention, as for the intensities: the gains'
overall RGB factor (the albedo takes it) and their gradient across the dome (a tilted
sample looks the same). Where the sample is taken as lying level
(:func:`matscan.reconstruct.selfcal.fits_gradient`) the steps fit the gradient with the
gains and hold the sum of the kept pixels' slopes where the start put it (two Lagrange
multipliers beside the lights' numbers, :func:`_with_level`): with the gradient held at
the intensities' estimate instead, made at the rig file's places, a photographed brick's
lights ended 3.5 mm off (0.86 mm held so). That start is the ``lm`` solver's maps fitted
at the rig file's places, which are not quite level (a leather's median slope −0.004):
the fit then turns the whole dome to keep their tilt, and ``LEVEL_START`` lays them level
first (their median slope removed, as the intensities' rounds lay theirs), or
``LEVEL_TURNS`` turns the fitted dome afterwards until the solver's maps at it lie level
(:func:`_turned_level`; the former off, the latter on, docs/rti-record.md says why). Otherwise
the steps keep the gradient the intensities came with, none. A pixel's step is kept only
where it lowers that pixel's misfit, so a few pixels whose linearisation is poor (a
highlight's edge) cannot reject the lights' step for all.

The fit is biased. Each pixel brings 9 unknowns of its own, fitted from its own few
values (3 a photo: 72 on dome24), and where the model bends (a highlight's shape, the
normal) the noise shifts them in one direction; the lights, shared by all pixels, take
up the shift (the Neyman–Scott problem: more pixels do not remove it). Started at the
true positions of simulated paper and grass, the fit drifted 0.6 and 1.2 mm with the
camera's noise, 0.2 mm with a fifth of its variance (noise 0.002); from the rig file,
grass came to 0.86 mm at 128² and 0.90 at 256² with every pixel used. So the bias is
measured by simulation (a parametric bootstrap: Efron & Tibshirani 1993, "An
introduction to the bootstrap", ch. 10) and removed: the fit's own end (its positions,
gains and every kept pixel's 9 numbers) is rendered, noise of the fit's noise model is
added to one replica and subtracted from the other (an antithetic pair: Hammersley &
Morton 1956), and each replica is fitted as the photos were, started at that truth. To
first order the noise moves the two fits by equal and opposite amounts, which cancel in
their mean; what is left is the bias, even in the noise, which is subtracted from the
positions and log gains (``BIAS_PAIRS``). The fit must then run until it settles
(``ITERATIONS`` = 30), so that the replicas measure the bias of the estimate the photos
got: stopped after 10 steps, it ends part way between the rig file and its biased end.
From the rig file, 128² photographed grass came to 0.37 mm (1.15 after 30 steps without
the replicas, 0.86 after 10), a black leather 0.66 (1.20; 1.22) and paper 0.57 (0.89;
0.78), against Cramér–Rao bounds of 0.50, 0.47 and 0.76 mm. It is off by default
(``BIAS_PAIRS`` = 0, ``ITERATIONS`` = 10): on 22 simulated materials it gained 0.20 dB on
average (grass 2.0, gravel 1.4, paper 0.8) but a corrugated sheet lost 0.12 dB, and on a
second draw of the dome a woven twill ended 0.35 dB farther below the ideal dome's
relighting (its positions no better, its gains moved), each failing the rule set before
the measurement (docs/rti-record.md); and it takes 90 steps where the default takes 10.
Replicas rendered from maps the ``lm`` solver fitted at the fitted lights instead
(tried first, with four times the noise variance, not kept) moved that black leather
from 1.22 to 2.43 mm (docs/rti-record.md).

The bias can also be computed, at one Gauss–Newton step's cost (``SECOND_ORDER``; Box
1971, "Bias in nonlinear estimation"): each pixel's numbers spread about their truth with
covariance A⁻¹, and where the model bends that spread leaves a residual of mean
−½ Σᵢⱼ Cᵢⱼ ∂²m/∂θᵢ∂θⱼ; the lights' step towards it, pixels eliminated, is the bias. The
spread is capped at the numbers' physical range (``_SPREAD``) in the formula and, as a
prior about the start, in the fit, so that both describe one estimator. On the first
draw of bench/nearcal.py it brought paper, a leather, grass and gravel 0.8-1.8 dB nearer
the ideal dome, but it put a heavy weave's bias at 39 mm (the model's kinks, where n·l
crosses 0, are not curvature), and on the second draw paper and the leather lost 1.0 and
0.6 dB: it failed the rule set before the run and is off (docs/rti-record.md).

Most of the bias is the dielectrics' F0, which each pixel fits from a faint, wide
highlight: started at the truth of simulated grass, the fit drifted 1.23 mm, 0.28 mm with
F0 held at the truth. A dielectric's F0 is set by its refractive index and changes
little across one material, so with ``SHARED_F0`` the pixels whose start's F0 is a
dielectric's share one F0 (RGB), fitted with the lights as three more numbers of their
system: from the truth it drifted 0.29 mm (a pilot without the search below), and 19 of
bench/nearcal.py's 25 materials have one F0. Pixels whose roughness the start left in
another valley of their
misfit (the shared F0 moves far from the start's) are searched again over a grid of
roughness half way through the steps. Over three draws of bench/nearcal.py's dome it
brought a leather, grass and gravel within 0.5 dB of the ideal dome's relighting on each
and paper on two, but drew the lights of glossy dielectrics (a varnish, a lacquer: sharp
highlights) 2-9 mm away: it failed the rule set before
the run and stayed off (docs/rti-record.md). A trace showed why: the shared F0 started at the
mean of the start's, which read those F0 low (a lacquer's 0.001 for 0.04), and the steps
moved the lights rather than the shared F0. It now starts where a scan of the photos puts
it (``_F0_GRID``), is not shared where that is below any dielectric's (``SHARED_MIN``),
and the fit runs from two starts, keeping the end that fits better. Over the three draws
this brought 24, 22 and 21 of the 25 within 0.5 dB of the ideal dome (shipped: 19, 17,
16) and the 22 fitted 0.25-0.38 dB nearer on average, but a gold foil on paper relit
about 0.2 dB worse on each draw, though its lights and gains came out nearer the truth:
it failed the rule set before the run by that one material. All of that was under the
convention that the LEDs have no brightness gradient across the dome. Under the level
convention (``selfcal.LEVEL``, the default since) and LEDs with their own gradients, its
rule, written again before the runs, held on three draws: the mean relighting 0.16-0.27
dB better, 1-4 more of the 25 within 0.5 dB of the ideal dome on each, no material more
than 0.09 dB farther below its ideal on average (the foil print 0.03; docs/rti-record.md). So
it is on by default, with ``SHARED_ITERATIONS`` steps; ``reconstruct --own-f0``
(``ReconstructConfig.shared_f0`` False) fits each pixel's own F0, in ``ITERATIONS``
steps, as before. The record gives the shared F0's standard error (``se``, from the
fit's own system: :func:`_f0_spread`), the spread the photos' noise alone leaves it,
which replicas of a glossy plastic's photos confirm (tests; under the convention of no
gradient). It does not measure the bias: a rough paper (roughness about 0.9, drawn at
256²) has its F0 at 0.056 for a true 0.033 with an ``se`` of 0.0015 (a photographed
brick's 0.0002-0.0003, a leather's 0.0001; docs/rti-record.md).

The start decides where that paper ends: the ``lm`` solver's maps, fitted from flat maps,
keep its roughness near the flat start (median 0.68 for 0.89), and from there the lights
end 1.88 mm off, 6.4 dB below the ideal dome's relighting. A third start (``WEAK_START``,
off) fits those maps with the solver's priors weakened (0.01 of them: 0.90 mm, 1.6 dB),
and is fitted from on the first start's pixels under its noise model; its end is kept
where it fits best, by more than ``WEAK_MARGIN``. It failed its rule: a photographed
grass's third end fitted 0.12% better and relit 3.3 dB worse, its F0 shared among fewer
pixels (its own dielectric pixels), so with more unknowns. With the same unknowns
(``WEAK_SAME``) it failed again: a heavy weave's third end fitted 0.32% better with its
lights 1.2 mm farther off, 0.55 dB lower, where the paper's won by 0.02% (docs/rti-record.md).

Measured on simulated dome24 captures whose LEDs are ±5 mm off (``bench/nearcal.py``,
docs/rti.md): the Cramér–Rao bound of such photos puts the positions within about
0.5-1 mm, and this fit comes within about that, where four estimators that fitted the
lights apart from the maps, or with the solver's holds on the maps, drifted 2-50 mm.
Each LED stays aimed where the rig file aims it (as ``calibrate --positions``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor
from tqdm import tqdm

from matscan.capture.folder import Capture
from matscan.mapset import MapSet
from matscan.reconstruct import lm, selfcal
from matscan.render import surface_points
from matscan.rig import LightSet

if TYPE_CHECKING:
    from matscan.reconstruct.job import ReconstructConfig

F64 = torch.float64
#: Gauss–Newton steps. With 10 the fit stops part way between the rig file and its end;
#: to measure its bias (``BIAS_PAIRS``) it must run until it settles: on simulated dome24
#: captures the positions move little after 30 (module doc).
ITERATIONS = 10
#: Under the level convention, start the joint fit from the ``lm`` solver's maps laid
#: level (their median slope removed, :func:`matscan.reconstruct.selfcal.levelled`), so
#: that the slopes' sum it holds is a level sample's. The solver's maps, fitted at the rig
#: file's places, come out tilted (a leather's median slope (−0.0042, −0.0016), 0.26°),
#: and the fit then turns the whole dome to match: 0.5° on that leather, most of its 1.9
#: mm error.
#: Off (the solver's maps as they come): on the first draw of its rule's runs it brought
#: that leather 0.51 dB nearer its ideal dome but sent a varnished wood's lights 7 mm off,
#: and the mean relighting of 25 materials did not move (docs/rti-record.md).
LEVEL_START = False
#: Under the level convention, after the joint fit, turn the fitted near lights about the
#: sample's centre until the ``lm`` solver's maps at them lie level (as ``LEVEL_BY`` means
#: it, :func:`_level_turn`), at most this many times: a turn of the whole dome with
#: the normals turned alike photographs nearly the same, so the photos leave it to the
#: convention, and the fit keeps the tilt of its start (``LEVEL_START``). Unlike laying
#: the start level, the fit's path is not changed: on the leather of bench/nearcal.py's
#: draw 0, turning the fitted lights so, three times, brought it 53.40 → 53.93 dB at 128²
#: (ideal 54.44) and 46.33 → 47.70 at 256² (ideal 47.75) (docs/rti-record.md). Level by the
#: median alone (``LEVEL_BY``) failed its rule: on draw 1 the fitted materials' mean
#: light error rose (1.090 → 1.094 mm: the embossed leather, coins and black leather,
#: 1.5-1.7 → 2.1-2.5 mm; the first and last have a median normal not vertical when they
#: lie level). Level
#: where the median and the trimmed mean agree passed its rule on draws 0-2 of 25
#: materials (mean relighting +0.008 to +0.032 dB, one more within 0.5 dB of the ideal
#: dome on each, the lights' mean error 4-7% lower; the leather 0.50, 0.11, −0.02 dB
#: below its ideal against 1.02, 0.80, 0.64): 6, the default since; 0 turns nothing.
LEVEL_TURNS = 6
#: What "the maps lie level" means for the turns: "median", their median slope is none
#: (:func:`matscan.reconstruct.selfcal.median_slope`); "agreed", the tilt that their
#: median and their 10% trimmed mean agree on is none
#: (:func:`matscan.reconstruct.selfcal.agreed_slope`): the median alone turned a heavy
#: weave, an embossed leather and a black leather, whose median normal is not vertical
#: when they lie level (docs/rti-record.md); "base", the default, the plane of the height
#: integrated from them that only a tenth of it lies below is level
#: (:func:`matscan.reconstruct.selfcal.base_slope`: the ground between a relief's
#: features; on the 25 true maps of bench/nearcal.py within 0.0017 of level, where the
#: agreed tilt is 0.0040 off a black leather's). Against "agreed" it passed its rule on
#: draws 0-2 (mean relighting +0.006 to +0.018 dB, as many within 0.5 dB of the ideal
#: dome, the lights' mean error 1-7% lower; the embossed coins, turned wrongly before,
#: within 0.03 dB of their ideal; docs/rti-record.md).
LEVEL_BY = "base"
#: A turn smaller than this (degrees) is not made: the maps already lie level.
LEVEL_TURN_MIN = 0.01
#: The capture is reduced to at most this many pixels on its longer side (every
#: ``factor``-th pixel, as the intensity rounds pick them).
POSITION_SIDE = 128
#: Residuals beyond about this many noise deviations weigh less and less (Cauchy's loss,
#: c² log(1 + r²/c²)): where the model cannot follow the photos (steep flanks a low
#: light grazes), the lights must not move to explain them.
ROBUST = 3.0
#: Pixels whose start misfits the photos more than this many times the median pixel's
#: are left out: there the start's maps are wrong (a steep flank), not the lights.
OUTLIER = 4.0
#: A light moved farther than this from the rig file's place is reported (as
#: ``calibrate --positions`` does): a wrong rig file, or a fit that went astray.
MOVED_WARN_MM = 20.0
#: Antithetic pairs of replicas whose fits measure the fit's bias (:func:`fit_positions`,
#: module doc; 0: the bias is left in, the default, docs/rti-record.md says why; measured with
#: each pixel's own F0 and ``ITERATIONS`` = 30, as ``bench/nearcal.py --own-f0 --steps=30
#: --pairs=1`` sets them: the replicas refit each pixel's own F0; where the fit shares an
#: F0 the replicas share it too, started at the fit's, their roughness searched as the
#: photos' was). Each
#: pair's noise, added to one replica and subtracted from the other, moves their fits by
#: equal and opposite amounts to first order, which cancel in the mean: what is left is
#: the bias, which is even in the noise.
BIAS_PAIRS = 0
#: With ``BIAS_PAIRS``, remove only the bias's common radial part: every near light moved
#: along its own direction from the sample's centre by the mean of the pair's radial
#: shifts, and its gain changed as its distance changes the irradiance (1/d²). The dome's
#: scale is a collective mode the photos hold weakly and relighting feels (a woven
#: twill's fitted dome 0.62 mm too large, where the Cramér–Rao bound gives that mode 0.20
#: mm; docs/rti-record.md), and one number carries less of the replicas' noise than 144. Off:
#: it passed its rule on two draws of 25 materials (the twill 0.79 → 0.40 dB below its
#: ideal dome) and failed it on the third, where the pair's steady radial bias took a
#: paper and a leather 0.5 and 0.7 dB farther below their ideal (docs/rti-record.md).
BIAS_RADIAL = False
#: Fit each replica of the pair from a second start too, each pixel's roughness searched
#: at the shared F0's scan of the replica, and keep the end that fits it better, as the
#: photos' fit keeps the better of its two starts. At the true maps it brings the pair's
#: measure of a paper's scale bias to what its photos' fits show (−0.03 mm, against +0.34
#: from one start); at the fit's end it changed little (+0.34 for +0.39) and failed its
#: pilot (docs/rti-record.md, "The pair at the truth"). Off.
REPLICA_SEARCHED = False
#: With ``BIAS_PAIRS``, measure the pair's bias again at each replica's end, that replica
#: taken as the truth, and remove twice the first measure less the second (Hall & Martin
#: 1988, "On bootstrap resampling and iteration"): the pair renders its replicas from the
#: fit's maps, which carry each pixel's noise, and at them measures a bias the truth's maps
#: do not have (a paper's scale +0.34 mm at its fitted maps, −0.03 at its true ones,
#: docs/rti-record.md); the second measure, at maps noisier once more, tells how far that moves
#: it. Costs the pair's replicas twice more over. Off: on draw 0's paper the second measure
#: was +0.330 mm for the first's +0.341, so the maps' noise is not what moves it (their
#: roughness's low valley is: ``REPLICA_FENCE``), and its pilot failed (docs/rti-record.md,
#: "The pair measured again at its replicas' ends").
BIAS_ITERATED = False
#: With ``BIAS_PAIRS``, render the pair's replicas (and start their fits) from the fit's
#: maps with each pixel's roughness beyond Tukey's fences, this many interquartile ranges
#: outside the quartiles, set to the median (0: off). A paper's fit leaves more than 5% of
#: its pixels in another valley of their roughness (0.09 where the truth is 0.72 or more,
#: a narrow highlight that falls between the lights), and with those the pair measures
#: its scale's bias at +0.35 mm, with the true roughness alone +0.02, as at the truth
#: (docs/rti-record.md, "What in the fitted maps moves the pair"). Off: with 3 (and
#: ``BIAS_RADIAL``, ``REPLICA_SEARCHED``) the paper's pair measured +0.03 and relit it as
#: the default does, the twill came within 0.5 dB of its ideal dome, but a leather, whose
#: fitted roughness is its true one, lost 0.7 dB as before: its pilot failed.
REPLICA_FENCE = 0.0
#: The seed of the first pair's noise (pair k draws with ``PAIR_SEED`` + k): the same for
#: every capture, so that a fit is repeatable.
PAIR_SEED = 0
#: Remove the fit's bias by its second-order formula, each pixel's numbers then held near
#: their start with the spread ``_SPREAD`` during the fit (:func:`fit_positions`, module
#: doc; False: left in, the default, docs/rti-record.md says why; measured with each pixel's own
#: F0 and ``ITERATIONS`` = 30, as ``bench/nearcal.py --own-f0 --steps=30 --second-order``
#: sets them). ``BIAS_PAIRS`` above 0
#: takes precedence.
SECOND_ORDER = False
#: The ``lm`` solver's priors (``SolverConfig``'s ``prior_*``) in the fit of the maps that
#: start the joint fit, as a multiple of the solver's own (the maps after it keep
#: theirs), and its roughness prior once more times ``START_ROUGHNESS_PRIOR``. From flat
#: maps the roughness prior holds each pixel's roughness near the flat start, which on a
#: rough paper drawn at 256² (true roughness 0.89) left it at 0.68, and from there the
#: joint fit ended with the lights 1.88 mm off, 6.4 dB below the ideal dome. With 0.01 of
#: every prior it came to 1.6 dB below (draw 2: 0.8), with 0.01 of the roughness prior
#: alone to 0.45 dB (draw 2: 4.7); but a photographed brick then lost 6.0 and 3.1 dB.
#: So 1 and 1, the solver's own, are the defaults (docs/rti-record.md).
START_PRIOR = 1.0
START_ROUGHNESS_PRIOR = 1.0
#: A third start for the joint fit: the ``lm`` solver's maps fitted with every prior times
#: this (0: none), fitted from as the other two, on the same pixels under the same noise
#: model, and kept where its end fits the photos better (``fit_positions``' ``alternate``).
#: Off: with 0.01 it failed its rule on draw 1 of bench/nearcal.py at 256², with its own
#: unknowns and with the first start's (``WEAK_SAME``), and with ``ENDS_BY`` "nearest" on
#: draw 1 at 128² (docs/rti-record.md).
WEAK_START = 0.0
#: The weak start's end is kept only where its misfit is lower than the others' best by more
#: than this share of it: on draw 1 of bench/nearcal.py at 256² a photographed grass's
#: third end fitted 0.12% better with its lights 1.44 mm off for 0.74, 3.3 dB lower.
WEAK_MARGIN = 0.0
#: The weak start's F0 is shared by the first start's pixels, started at its scan's value
#: (True), so that all three ends fit the same unknowns; False: by the pixels its own maps
#: call dielectric, at its own scan's value (on draw 1 at 256² the grass's and gravel's
#: third ends then shared among 88% of the pixels, the others among all, docs/rti-record.md).
WEAK_SAME = True
#: Which start's end the joint fit keeps: ``"misfit"``, the one that fits the photos best
#: (the weak start's by more than ``WEAK_MARGIN``); ``"nearest"``, the one whose lights lie
#: nearest the rig file's places (root mean square over the near lights). The rig file is
#: a measurement of the LEDs made apart from the photos: where the ends' errors do not
#: depend on how far each LED is off, the ends' squared distances from it differ by what
#: their squared errors differ. On eleven materials of draw 1 of bench/nearcal.py at 256²
#: the nearest end was within 0.12 mm of the best, the best-fitting one up to 1.37 mm from
#: it (docs/rti-record.md). An end that stopped short of where the photos put it would lie
#: nearer too, which the misfit would not prefer. With ``WEAK_START`` 0.01 it failed its
#: rule on draw 1 at 128²: the mean PSNR 0.022 dB lower, a photographed brick 1.14 dB
#: and a gravel 0.23 dB (its lights nearer the truth) lower, the woven twill 0.61 higher.
ENDS_BY = "misfit"
_ENDS_BY = ("misfit", "nearest")
#: How far (mm, one standard deviation per axis) the rig file's places are taken to be
#: from the LEDs': a Gaussian prior on the near lights' positions about the places the fit
#: starts from (0: none). The rig file is a measurement of its own; ±5 mm uniform is
#: 2.9 mm, with which the Cramér–Rao bound of a black knit's places falls from 2.22 to
#: 1.30 mm. Off: on draw 1 of bench/nearcal.py (``--place-prior=2.9``) it moved the 25
#: materials' relighting by 0.009 dB on average (a woven twill +0.16, a photographed brick
#: −0.11), and from the rig file the knit's lights came to 4.6 mm, still relit below its
#: places held (docs/rti-record.md, "what it is not").
PLACE_SPREAD_MM = 0.0
#: Where the capture's calibration places the near lights (``light_positions_mm``: another
#: capture's self-calibration, or several merged, ``calibrate --merge``), how far (mm, one
#: standard deviation per axis) those places are taken to be from the LEDs': the prior
#: ``PLACE_SPREAD_MM`` is for the rig file's, about the calibration's places instead; and
#: where the intensities were right already (their estimate refused as no better) the
#: places are fitted all the same (0: off, the calibration's places held there, and with
#: their estimate kept, fitted without a prior). Off: piloted on draw 1 of
#: bench/nearcal.py from four captures' calibrations merged (``--calibrated-on=paper,
#: brick,leather,plastic --then-fit --calibrated-spread=S``; docs/rti.md "A dome calibrated
#: once"), no spread suited both a photographed brick and a gravel, dB below the ideal
#: dome: 0.3 mm 0.10 and 0.93, 0.5 mm 0.26 and 0.74, 1 mm 0.90 and 0.35 (the calibration
#: alone 0.03 and 1.11; their own fits 0.69 and 0.02).
CALIBRATED_SPREAD_MM = 0.0
#: Where the capture's calibration places the near lights, fit the places from the
#: calibration's moving the lights only together: one shift (3 numbers) and the dome's
#: scale (each light along its own direction from the origin by one amount), the
#: calibration's light-by-light pattern kept. "confirmed": only where the intensities
#: were right already (their estimate refused as no better; otherwise the places are
#: kept as they are), and the others fitted light by light; "always": every capture;
#: "off": neither. Off: "confirmed" took draw 2 of bench/nearcal.py's paper from 1.65 to
#: 0.59 dB below the ideal dome and its woven plain from 0.53 to 0.09, but draw 0's paper
#: from 0.50 to 0.70 and draw 1's brick from 0.03 to 0.31, failing its rules; "always"
#: took a photographed gravel 1.6-1.7 dB below on two draws (docs/rti.md, "Half the
#: merge's error is the dome's scale and shift").
CALIBRATED_COMMON = "off"
_COMMON = ("off", "confirmed", "always")
_PRIORS = ("prior_diffuse", "prior_specular", "prior_roughness", "prior_normal")
#: With ``SECOND_ORDER``, each pixel's numbers spread at most as if uniform over their
#: physical range (ρ and F0 in [0, 1], roughness in [0.02, 1], the slopes within ±√3,
#: normals within 60° of the sample's): a Gaussian prior of these deviations, centred on
#: the start, in the fit and in the formula. Where the photos do not determine a number
#: (a faint, wide highlight's F0 and roughness), the formula would otherwise spread it
#: without bound (paper's bias came out at 30 mm), and the fit would leave it where its
#: start put it, so that the formula, taken at the fit's end, described another fit than
#: the one made (docs/rti-record.md).
_SPREAD = torch.tensor([0.29] * 6 + [0.28, 1.0, 1.0], dtype=F64)
#: One F0 (RGB) shared by every pixel whose start gives a dielectric's (each channel below
#: ``SHARED_BELOW``), fitted with the lights, instead of each pixel's own (module doc;
#: the default since its rule held under the level convention, docs/rti-record.md; False: each
#: pixel its own, as ``reconstruct --own-f0`` and ``bench/nearcal.py --own-f0`` ask).
#: Each pixel's roughness is then searched again over a grid half way through the steps
#: and twice more, three steps apart (``_RESEED_GRID``).
SHARED_F0 = True
#: The shared F0 (``SHARED_F0``) is one number for all three channels, not one per channel:
#: a dielectric's F0 follows from its refractive index, which hardly changes across the
#: visible. Fitted per channel, a varnished wood's came out (0.042, 0.057, 0.093) for a
#: grey 0.0465 when the fit started from levelled maps (``LEVEL_START``), its lights 7 mm
#: off (docs/rti-record.md). Off: with the level start it failed its rule's pilot, the wood's
#: lights 7.2 mm off with its F0 grey (docs/rti-record.md); alone it was not run under a rule.
GREY_F0 = False
#: The shared F0 (``SHARED_F0``) held at the scan's value (``_F0_GRID``) through the steps,
#: not fitted with the lights. A diagnostic (``bench/nearcal.py --hold-f0``): on the
#: bench's paper at 256², a rough dielectric (roughness about 0.9) whose fitted F0 drifts
#: from the scan's 0.04 to 0.056 (true 0.033; as far with every pixel, further from the
#: truth), held it relit 2.5 dB better, still 1.7 dB below the intensities alone (docs/rti-record.md).
HOLD_F0 = False
#: Gauss–Newton steps of the fit with one shared F0, from each of its two starts, as
#: :func:`estimate_positions` runs it (``ITERATIONS`` with each pixel's own F0): measured
#: with 20 (docs/rti-record.md).
SHARED_ITERATIONS = 20
#: The start's F0 below which a pixel shares the one F0 (``SHARED_F0``): dielectrics are
#: about 0.02-0.08; a metal's or a foil's pixels keep their own.
SHARED_BELOW = 0.1
#: Roughness values each pixel is tried at when searched again (``SHARED_F0``): the start
#: (the ``lm`` solver's maps) and the shared F0's first steps leave some pixels in another
#: valley of their misfit, where the Gauss–Newton steps cannot leave (a photographed
#: brick's lights stayed 1.5 mm off, 0.45 mm with the search).
_RESEED_GRID = torch.linspace(0.05, 1.0, 20, dtype=F64)
#: The shared F0's values tried before the steps (``SHARED_F0``), each pixel's roughness
#: searched again at each (``_RESEED_GRID``): the start's own F0 can be far from the
#: material's (a woven twill's 0.015 for a true 0.029, a varnish's 0.020 for 0.047), and
#: from there the steps drew the lights away rather than move the shared F0 (docs/rti-record.md).
_F0_GRID = torch.tensor([0.0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03, 0.035, 0.04, 0.05, 0.06, 0.08], dtype=F64)
#: A dielectric's F0 is at least water's (n = 1.33: 0.02). Where the pixels kept fit best
#: with a lower shared F0 they show no dielectric's highlight (a lacquer's sharp ones are
#: among the pixels left out) and keep their own F0 (``SHARED_F0``).
SHARED_MIN = 0.02
#: Bounds of the per-pixel numbers during the fit. ρ and F0 may leave [0, 1] a little: held
#: in, pixels at a bound stalled the steps of the lights (their numbers are not kept).
_LOW = torch.tensor([-1.0, -1, -1, -1, -1, -1, 0.032, -3, -3], dtype=F64)[:, None]
_HIGH = torch.tensor([2.0, 2, 2, 2, 2, 2, 1, 3, 3], dtype=F64)[:, None]
_CHUNK = 4096  # pixels whose 9 × 9 blocks are eliminated at once


def _placed(lights: LightSet, aims: Tensor, pos: Tensor, gains: Tensor) -> LightSet:
    """The lights at ``pos`` (N, 3), aimed at ``aims`` (N, 3), their intensities × gains."""
    axis = aims - pos
    axis = axis / axis.norm(dim=1, keepdim=True)
    return replace(lights, position=pos, axis=axis, intensity=lights.intensity.to(F64) * gains)


def _double(lights: LightSet) -> LightSet:
    return replace(
        lights,
        position=lights.position.to(F64),
        axis=lights.axis.to(F64),
        intensity=lights.intensity.to(F64),
        exponent=lights.exponent.to(F64),
        camera=lights.camera.to(F64),
        camera_w=lights.camera_w.to(F64),
        w=lights.w.to(F64),
    )


def _render(th: Tensor, lights: LightSet, pts: Tensor) -> Tensor:
    """The model (N, 3, P) of pixels with numbers ``th`` (9, P) under ``lights``."""
    return _model(th, lm.geometry(lights, pts))


def _model(th: Tensor, geo: lm.Geometry) -> Tensor:
    """The model (N, 3, P) of pixels with numbers ``th`` (9, P) in the lights' geometry
    ``geo`` (:func:`matscan.reconstruct.lm.geometry`), computed once where many ``th``
    are tried under the same lights."""
    a, s1, s0 = lm.bases(th[6:9], geo)
    return th[None, 0:3] * a + th[None, 3:6] * s1 + s0


def _jacobians(th: Tensor, lights: LightSet, aims: Tensor, gains: Tensor, pts: Tensor):
    """The model m (N, 3, P) and its derivatives by each pixel's 9 numbers (N, 3, P, 9)
    and by each light's position (N, 3, P, 3); by the log gains it is m itself."""
    base = _placed(lights, aims, lights.position, gains)
    geo = lm.geometry(base, pts)
    a, s1, s0 = lm.bases(th[6:9], geo)
    m = th[None, 0:3] * a + th[None, 3:6] * s1 + s0
    n, p = m.shape[0], m.shape[2]
    jp = torch.zeros(n, 3, p, 9, dtype=F64)
    for c in range(3):
        jp[:, c, :, c] = a[:, c]
        jp[:, c, :, 3 + c] = s1[:, c]
    for j in range(3):  # roughness and slopes: central differences
        hi, lo = th.clone(), th.clone()
        hi[6 + j] += 1e-6
        lo[6 + j] -= 1e-6
        jp[..., 6 + j] = (_model(hi, geo) - _model(lo, geo)) / 2e-6
    jl = torch.zeros(n, 3, p, 3, dtype=F64)
    for j in range(3):
        d = torch.zeros(n, 3, dtype=F64)
        d[:, j] = 1e-5
        hi = _render(th, _placed(lights, aims, lights.position + d, gains), pts)
        lo = _render(th, _placed(lights, aims, lights.position - d, gains), pts)
        jl[..., j] = (hi - lo) / 2e-5
    return m, jp, jl


def normal_equations(
    th: Tensor, lights: LightSet, aims: Tensor, gains: Tensor, pts: Tensor, wt: Tensor, y: Tensor, jac=None
):
    """The Gauss–Newton normal equations of the weighted misfit Σ wt (y − m)² over each
    pixel's 9 numbers and the lights' (positions, then log gains; 6N): per pixel the
    block A (P, 9, 9) and gradient g_p (P, 9), the coupling B (P, 9, 6N), the lights'
    block C (6N, 6N) and gradient g_l (6N) (gradients of −½ the misfit). With y = m they
    are the Fisher information of photos of noise variance 1 / wt. ``jac``: the model
    and its derivatives (:func:`_jacobians`) where already computed."""
    m, jp, jl = _jacobians(th, lights, aims, gains, pts) if jac is None else jac
    n, p_count = m.shape[0], m.shape[2]
    r = y - m
    jw = jp.permute(2, 0, 1, 3).reshape(p_count, 3 * n, 9)  # (P, 3N, 9): a batch of matrix products
    a = torch.bmm(jw.transpose(1, 2), jw * wt.permute(2, 0, 1).reshape(p_count, 3 * n, 1))
    gp = torch.einsum("kcp,kcpi,kcp->pi", wt, jp, r)
    b = torch.cat(
        [
            torch.einsum("kcp,kcpi,kcpj->pikj", wt, jp, jl).reshape(p_count, 9, 3 * n),
            torch.einsum("kcp,kcpi,kcp->pikc", wt, jp, m).reshape(p_count, 9, 3 * n),
        ],
        2,
    )
    c = torch.zeros(6 * n, 6 * n, dtype=F64)
    cpp = torch.einsum("kcp,kcpi,kcpj->kij", wt, jl, jl)
    cpg = torch.einsum("kcp,kcpi,kcp->kic", wt, jl, m)
    for k in range(n):
        c[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = cpp[k]
        c[3 * k : 3 * k + 3, 3 * n + 3 * k : 3 * n + 3 * k + 3] = cpg[k]
        c[3 * n + 3 * k : 3 * n + 3 * k + 3, 3 * k : 3 * k + 3] = cpg[k].T
    cgg = torch.einsum("kcp,kcp,kcp->kc", wt, m, m).reshape(-1)
    c[3 * n :, 3 * n :] += torch.diag(cgg + 1e-9 * float(cgg.mean()))  # the overall factor: the albedo's
    gl = torch.cat(
        [
            torch.einsum("kcp,kcpj,kcp->kj", wt, jl, r).reshape(-1),
            torch.einsum("kcp,kcp,kcp->kc", wt, m, r).reshape(-1),
        ]
    )
    return a, gp, b, c, gl


def reduced_system(a: Tensor, gp: Tensor, b: Tensor, c: Tensor, gl: Tensor, mu: float):
    """The pixels' blocks damped by ``mu`` (Levenberg–Marquardt, on the diagonal), and the
    lights' system with every pixel eliminated (the Schur complement C − Σ Bᵀ A⁻¹ B, and
    its right side g_l − Σ Bᵀ A⁻¹ g_p): (damped A, S, rhs)."""
    eye9 = torch.eye(9, dtype=F64)
    diag_a = a.diagonal(dim1=1, dim2=2)
    ad = a + (mu * diag_a + 1e-12 * diag_a.mean(1, keepdim=True))[:, :, None] * eye9
    s = c + mu * torch.diag(c.diagonal())
    rhs = gl.clone()
    k = b.shape[2]
    for i in range(0, len(a), _CHUNK):
        bi = b[i : i + _CHUNK]
        x = torch.linalg.solve(ad[i : i + _CHUNK], torch.cat([bi, gp[i : i + _CHUNK, :, None]], 2))
        flat = bi.reshape(-1, k)  # one matrix product over every pixel's 9 rows: 3x the einsum's speed
        s -= flat.T @ x[..., :-1].reshape(-1, k)
        rhs -= flat.T @ x[..., -1].reshape(-1)
    return ad, s, rhs


def _noise_weights(y: Tensor, m: Tensor, valid: Tensor) -> tuple[Tensor, tuple[float, float]]:
    """1 / var per value, var = a·m + b fitted to the squared residuals' medians in 20
    bins of m (the median of a χ²₁ is 0.455 of its mean), relative errors minimised."""
    keep = valid > 0
    mm, rr = m[keep], (y - m)[keep].square()
    step = max(1, mm.numel() // 200_000)
    edges = torch.quantile(mm[::step].float(), torch.linspace(0, 1, 21)).to(F64)
    xs, vs = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (mm >= lo) & (mm < hi)
        if int(sel.sum()) > 100:
            xs.append(float(mm[sel].mean()))
            vs.append(float(rr[sel].median()) / 0.4549)
    if len(xs) < 2:
        a, b = 0.0, float(rr.mean().clamp_min(1e-12))
    else:
        x, v = torch.tensor(xs, dtype=F64), torch.tensor(vs, dtype=F64).clamp_min(1e-12)
        design = torch.stack([x, torch.ones_like(x)], 1) / v[:, None]
        coef = torch.linalg.lstsq(design, torch.ones_like(v)[:, None]).solution[:, 0]
        a, b = float(coef[0].clamp_min(0)), float(coef[1].clamp_min(1e-10))
    return valid / (a * y.clamp_min(0) + b), (a, b)


def _free_directions(lights: LightSet, near: Tensor, gradient: bool = False, common: bool = False) -> Tensor:
    """An orthonormal basis (6N, D) of the steps allowed over (positions, log gains): no
    position step for directional lights, and unless ``gradient``, no gradient of the log
    gains across the dome. With ``common`` the near lights move only together: one shift
    (3 numbers) and the dome's scale, each light along its own direction from the origin
    by one common amount (``CALIBRATED_COMMON``)."""
    n = len(near)
    d = lights.position / lights.position.norm(dim=1, keepdim=True)
    if common and bool(near.any()):
        on = near.to(F64)[:, None]
        moves = [(on * torch.eye(3, dtype=F64)[j]).reshape(-1) for j in range(3)] + [(on * d).reshape(-1)]
        places = torch.linalg.qr(torch.stack(moves, 1))[0]
        gains = _free_directions(lights, torch.zeros_like(near), gradient)[3 * n :]
        return torch.block_diag(places, gains)
    fixed = []
    for i in range(n):
        if not bool(near[i]):
            for j in range(3):
                e = torch.zeros(6 * n, dtype=F64)
                e[3 * i + j] = 1
                fixed.append(e)
    for j in range(0 if gradient else 2):
        for c in range(3):
            g = torch.zeros(n, 3, dtype=F64)
            g[:, c] = d[:, j]
            fixed.append(torch.cat([torch.zeros(3 * n, dtype=F64), g.reshape(-1)]))
    if not fixed:
        return torch.eye(6 * n, dtype=F64)
    q = torch.linalg.qr(torch.stack(fixed, 1))[0]
    u, s, _ = torch.linalg.svd(torch.eye(6 * n, dtype=F64) - q @ q.T)
    return u[:, : 6 * n - q.shape[1]]


@dataclass(frozen=True)
class _Photos:
    """What the joint fit fits: the lights (float64; positions where the fit starts), each
    near light's aim point (N, 3), which lights are near (N,), the pixels' surface points
    (P, 3), their values (N, 3, P) and which of them are usable (N, 3, P; 1 or 0), and
    whether the gains' gradient is fitted with the pixels' slopes' sum held where the
    start put it (``level``, :func:`_with_level`) or the gradient kept."""

    lights: LightSet
    aims: Tensor
    near: Tensor
    pts: Tensor
    y: Tensor
    valid: Tensor
    level: bool = False
    spread: float = 0.0  # the near lights' places' prior about the start (mm per axis; 0: none)
    common: bool = False  # the near lights moved only together: one shift and the dome's scale


@dataclass(frozen=True)
class _Solved:
    """The joint fit's end: positions, log gains, the kept pixels (P,) and their numbers
    (9, kept), the noise model (a, b), the misfit per value at the start and end, and
    which kept pixels shared one F0 (None: each its own)."""

    pos: Tensor
    lg: Tensor
    used: Tensor
    th: Tensor
    noise: tuple[float, float]
    first: float
    cost: float
    shared: Tensor | None = None  # which kept pixels share one F0 (``SHARED_F0``)
    scan: tuple[Tensor, float] | None = None  # the shared F0's scan (:func:`_shared_start`)
    f0_spread: Tensor | None = None  # the shared F0's standard error (:func:`_f0_spread`)


def _with_shared_f0(a: Tensor, gp: Tensor, b: Tensor, c: Tensor, gl: Tensor, shared: Tensor, grey: bool = False):
    """The normal equations (:func:`normal_equations`) with the F0 of the pixels ``shared``
    (P,) replaced by one F0 (RGB; with ``grey`` one number for all three channels) for all
    of them, appended to the lights' numbers: the pixels' blocks keep their other numbers,
    their F0 rows move to the coupling and the lights' block, summed over the pixels that
    share it (and, grey, over the channels: the Jacobian of a grey F0 is the sum of the
    three channels')."""
    s = shared.to(F64)
    # the shared F0's columns in each pixel's 3 F0 numbers: the identity, or (1, 1, 1) grey
    k = torch.ones(3, 1, dtype=F64) if grey else torch.eye(3, dtype=F64)
    bf = (a[:, :, 3:6] @ k) * s[:, None, None]  # (P, 9, K): each pixel's numbers × the shared F0
    cff = (k.T @ a[:, 3:6, 3:6] @ k * s[:, None, None]).sum(0)
    clf = torch.einsum("pjk,jf,p->kf", b[:, 3:6, :], k, s)  # (6N, K): the lights × the shared F0
    glf = (gp[:, 3:6] @ k * s[:, None]).sum(0)
    a, gp, b = a.clone(), gp.clone(), b.clone()
    a[shared, 3:6, :] = 0
    a[shared, :, 3:6] = 0
    a[shared, 3:6, 3:6] = torch.eye(3, dtype=F64)
    gp[shared, 3:6] = 0
    b[shared, 3:6, :] = 0
    bf[shared, 3:6, :] = 0
    c = torch.cat([torch.cat([c, clf], 1), torch.cat([clf.T, cff], 1)], 0)
    return a, gp, torch.cat([b, bf], 2), c, torch.cat([gl, glf])


def _with_level(b: Tensor, c: Tensor, gl: Tensor, moved: Tensor):
    """The normal equations (:func:`normal_equations`) with the step held to bring the
    pixels' slopes' sum (x and y) back by ``moved`` (2,), how far it has moved from the
    start: two Lagrange multipliers appended to the lights' numbers, coupled to every
    pixel's two slopes, with no block of their own, and whose right side is −``moved``
    (``selfcal.LEVEL``: the fit keeps the sample's tilt where its start put it, laid
    level with ``LEVEL_START``)."""
    e = torch.zeros(b.shape[0], 9, 2, dtype=F64)
    e[:, 7, 0] = 1
    e[:, 8, 1] = 1
    c = torch.block_diag(c, torch.zeros(2, 2, dtype=F64))
    return torch.cat([b, e], 2), c, torch.cat([gl, -moved])


def _reseeded(th: Tensor, misfit, geo: lm.Geometry, y: Tensor, wt: Tensor, polish: int = 0) -> Tensor:
    """``th`` (9, P) with each pixel's roughness at the value of ``_RESEED_GRID`` whose
    fit (ρ by weighted least squares, F0 and normal kept) lowers the pixel's ``misfit``
    (a function of th giving (P,), under the lights of ``geo``) most, where one does.
    With ``polish`` steps, each pixel's best grid value at least ``_AWAY`` from its own
    roughness is then fitted by that many Levenberg–Marquardt steps over its ρ, roughness
    and normal (:func:`_polished`), and kept where it ends below the pixel's misfit: a
    valley of the roughness whose normal differs from the pixel's (``POLISH``)."""
    own = th[6].clone()
    best, th = misfit(th), th.clone()
    away, alt = torch.full_like(best, math.inf), th.clone()
    for r in _RESEED_GRID:
        t = th.clone()
        t[6] = r
        a, s1, s0 = lm.bases(t[6:9], geo)
        rest = y - t[None, 3:6] * s1 - s0
        t[0:3] = ((wt * a * rest).sum(0) / (wt * a * a).sum(0).clamp_min(1e-12)).clamp(-1, 2)
        tried = misfit(t)
        far = ((r - own).abs() >= _AWAY) & (tried < away)
        alt, away = torch.where(far[None], t, alt), torch.where(far, tried, away)
        better = tried < best
        th, best = torch.where(better[None], t, th), torch.where(better, tried, best)
    if polish:
        alt, cost = _polished(alt, misfit, geo, y, wt, polish)
        better = cost < best - POLISH_MARGIN
        th = torch.where(better[None], alt, th)
    return th


#: With ``POLISH``, the grid value tried as another valley lies at least this far from the
#: pixel's own roughness.
_AWAY = 0.1
#: Levenberg–Marquardt steps given to each pixel's best roughness in another valley when
#: the roughness is searched again (:func:`_reseeded`; 0: none). On a photographed brick
#: of bench/nearcal.py's draw 1, 7 of 16,384 pixels held the joint fit's end in another
#: valley of the roughness (0.27 for a true 0.57), 120 above the misfit the true maps'
#: valleys give, and the grid could not move them: there the misfit is 92 at 0.55 with
#: the normal kept, 63 with it fitted (docs/rti-record.md).
POLISH = 0
#: A pixel's other valley (``POLISH``) is kept only where it lowers the pixel's misfit by
#: more than this (in units of the noise's variance, as the misfit counts).
POLISH_MARGIN = 0.0


def _polished(th: Tensor, misfit, geo: lm.Geometry, y: Tensor, wt: Tensor, steps: int) -> tuple[Tensor, Tensor]:
    """``th`` (9, P) after ``steps`` Levenberg–Marquardt steps of each pixel's ρ, roughness
    and normal under the lights of ``geo`` (F0 kept), each pixel's step kept where it
    lowers its ``misfit``, and that misfit (P,)."""
    cost, mu = misfit(th), torch.full((th.shape[1],), 1e-3, dtype=F64)
    free = [0, 1, 2, 6, 7, 8]
    for _ in range(steps):
        a, s1, s0 = lm.bases(th[6:9], geo)
        m = th[None, 0:3] * a + th[None, 3:6] * s1 + s0
        n, p = m.shape[0], m.shape[2]
        jac = torch.zeros(n, 3, p, 6, dtype=F64)
        for c in range(3):
            jac[:, c, :, c] = a[:, c]
        for j in range(3):  # roughness and slopes: central differences
            hi, lo = th.clone(), th.clone()
            hi[6 + j] += 1e-6
            lo[6 + j] -= 1e-6
            jac[..., 3 + j] = (_model(hi, geo) - _model(lo, geo)) / 2e-6
        r = y - m
        w = wt / (1 + wt * r**2 / ROBUST**2)  # Cauchy's weights
        h = torch.einsum("kcpi,kcp,kcpj->pij", jac, w, jac)
        g = torch.einsum("kcpi,kcp,kcp->pi", jac, w, r)
        diag = h.diagonal(dim1=1, dim2=2)
        h = h + torch.diag_embed(mu[:, None] * diag + 1e-12)
        step = torch.linalg.solve(h, g[..., None])[..., 0]
        t = th.clone()
        t[free] += step.T
        t = torch.max(torch.min(t, _HIGH), _LOW)
        tried = misfit(t)
        better = tried < cost
        th, cost = torch.where(better[None], t, th), torch.where(better, tried, cost)
        mu = torch.where(better, (mu / 3).clamp_min(1e-7), mu * 4)
    return th, cost


def _shared_start(th: Tensor, shared: Tensor, lights: LightSet, pts: Tensor, y: Tensor, wt: Tensor):
    """``th`` (9, P) with the F0 of the pixels ``shared`` at the value of ``_F0_GRID`` that,
    each pixel's roughness searched again (:func:`_reseeded`), fits the photos best
    (Cauchy's loss, as the steps weigh them), and that value."""

    geo = lm.geometry(lights, pts)

    def misfit(t: Tensor) -> Tensor:
        return (ROBUST**2 * torch.log1p(wt * (y - _model(t, geo)) ** 2 / ROBUST**2)).sum((0, 1))

    best = None
    for f in _F0_GRID:
        t = th.clone()
        t[3:6, shared] = f
        t = _reseeded(t, misfit, geo, y, wt)
        cost = float(misfit(t).sum())
        if best is None or cost < best[0]:
            best = (cost, float(f), t)
    return best[2], best[1]


def _solve(
    photos: _Photos,
    th: Tensor,
    lg: Tensor,
    iterations: int,
    progress=None,
    held: bool = False,
    shared_f0: bool = False,
    searched: bool = False,
    scan: tuple[Tensor, float] | None = None,
    fixed: tuple[tuple[float, float], Tensor] | None = None,
    sharing: Tensor | None = None,
) -> _Solved:
    """Gauss–Newton over the lights' positions and log gains and every pixel's 9 numbers
    ``th`` (9, P), started at ``photos.lights``' positions and ``lg`` (module doc). With
    ``held``, each pixel's numbers are held near their start with the spread ``_SPREAD``
    (a Gaussian prior), as the second-order formula of the bias assumes. With
    ``shared_f0``, the pixels whose start's F0 is a dielectric's share one F0, fitted with
    the lights (``SHARED_F0``; one number for the three channels with ``GREY_F0``),
    started at the value of ``_F0_GRID`` that fits best; with
    ``searched`` every pixel starts at the roughness searched there, else at the start's;
    ``scan``: that scan, from an earlier call on the same photos and start. ``fixed``: the
    noise model and the pixels kept of an earlier call (:class:`_Solved`'s ``noise`` and
    ``used``), so that the two ends' misfits are of the same pixels in the same units;
    ``sharing``: with them and that call's ``scan``, which kept pixels share the F0 (its
    ``shared``), in place of those whose start's F0 is a dielectric's."""
    lights, aims, pts, y, valid = photos.lights, photos.aims, photos.pts, photos.y, photos.valid
    n = len(lights)
    pos = lights.position.clone()
    m0 = _render(th, _placed(lights, aims, pos, lg.exp()), pts)
    if fixed is None:
        wt, noise = _noise_weights(y, m0, valid)
        per_pixel = (wt * (y - m0) ** 2).sum((0, 1)) / valid.sum((0, 1)).clamp_min(1)
        used = per_pixel <= OUTLIER * per_pixel.median()
    else:
        noise, used = fixed
        wt = valid / (noise[0] * y.clamp_min(0) + noise[1])
    th, y, valid, wt, pts = th[:, used], y[..., used], valid[..., used], wt[..., used], pts[used]
    level = photos.level
    basis = _free_directions(lights, photos.near, gradient=level, common=photos.common)
    shared = (th[3:6] < SHARED_BELOW).all(0) if shared_f0 else torch.zeros(th.shape[1], dtype=torch.bool)
    if shared_f0 and sharing is not None:
        shared = sharing.clone()
    if shared.any():
        scan = scan or _shared_start(th, shared, _placed(lights, aims, pos, lg.exp()), pts, y, wt)
        scanned, f0 = scan
        if float(torch.as_tensor(f0).min()) >= SHARED_MIN:  # f0: a float, or the RGB (3, 1) of an end
            th = (scanned if searched else th).clone()
            th[3:6, shared] = f0
        else:  # the pixels kept show no dielectric's highlight: each keeps its own
            shared = torch.zeros_like(shared)
    extra = (1 if GREY_F0 else 3) if shared.any() else 0
    if extra:
        free = torch.zeros(extra, 0, dtype=F64) if HOLD_F0 else torch.eye(extra, dtype=F64)
        basis = torch.block_diag(basis, free)  # held: no column, the shared F0 takes no step
        half = iterations // 2
        reseeds = {half, half + 3, half + 6} if iterations >= 8 else set()
    if level:
        basis = torch.block_diag(basis, torch.eye(2, dtype=F64))

    def geometry(pos: Tensor, lg: Tensor) -> lm.Geometry:
        """The geometry of the lights at ``pos`` with log gains ``lg``."""
        return lm.geometry(_placed(lights, aims, pos, lg.exp()), pts)

    def residual2(th: Tensor, geo: lm.Geometry) -> Tensor:
        """Squared residuals in units of the noise (N, 3, P)."""
        return wt * (y - _model(th, geo)) ** 2

    start, hold = th.clone(), (_SPREAD**-2 if held else torch.zeros(9, dtype=F64))[:, None]

    def pixel_misfit(th: Tensor, geo: lm.Geometry) -> Tensor:
        prior = (hold * (th - start) ** 2).sum(0)
        return (ROBUST**2 * torch.log1p(residual2(th, geo) / ROBUST**2)).sum((0, 1)) + prior

    origin, place_weight = pos.clone(), (photos.spread**-2 if photos.spread > 0 else 0.0) * photos.near.to(F64)

    def place_prior(pos: Tensor) -> float:
        """−2 log of the places' prior (``photos.spread``), up to a constant."""
        return float((place_weight[:, None] * (pos - origin) ** 2).sum())

    cost = float(pixel_misfit(th, geometry(pos, lg)).sum()) + place_prior(pos)
    first, mu = cost, 1e-3
    for it in range(iterations):
        at = geometry(pos, lg)
        if extra and it in reseeds:
            th = _reseeded(th, lambda t, at=at: pixel_misfit(t, at), at, y, wt, POLISH)
            cost = float(pixel_misfit(th, at).sum()) + place_prior(pos)
        placed = replace(lights, position=pos)
        irls = wt / (1 + residual2(th, at) / ROBUST**2)  # Cauchy's weights, reweighted each step
        a, gp, b, c, gl = normal_equations(th, placed, aims, lg.exp(), pts, irls, y)
        a, gp = a + torch.diag(hold[:, 0]), gp - (hold * (th - start)).T
        if photos.spread > 0:  # the places' prior: its curvature, and the gradient of −½ it
            c[: 3 * n, : 3 * n] += torch.diag(place_weight.repeat_interleave(3))
            gl[: 3 * n] -= (place_weight[:, None] * (pos - origin)).reshape(-1)
        if extra:
            a, gp, b, c, gl = _with_shared_f0(a, gp, b, c, gl, shared, grey=extra == 1)
        if level:
            b, c, gl = _with_level(b, c, gl, (th[7:9] - start[7:9]).sum(1))
        for _ in range(8):
            ad, s, rhs = reduced_system(a, gp, b, c, gl, mu)
            dl = basis @ torch.linalg.solve(basis.T @ s @ basis, basis.T @ rhs)
            dp = torch.linalg.solve(ad, (gp - torch.einsum("pik,k->pi", b, dl))[..., None])[..., 0]
            pos_t = pos + dl[: 3 * n].reshape(n, 3)
            lg_t = lg + dl[3 * n : 6 * n].reshape(n, 3)
            base = th
            if extra:  # the shared F0's step, for every pixel that shares it
                base = th.clone()
                base[3:6, shared] += dl[6 * n : 6 * n + extra, None]  # a grey step: one number, all three
                base = torch.max(torch.min(base, _HIGH), _LOW)
            th_t = torch.max(torch.min(base + dp.T, _HIGH), _LOW)
            at_t = geometry(pos_t, lg_t)
            moved, kept = pixel_misfit(th_t, at_t), pixel_misfit(base, at_t)
            better = moved <= kept
            th_t = torch.where(better[None], th_t, base)
            cost_t = float(torch.where(better, moved, kept).sum()) + place_prior(pos_t)
            if cost_t < cost:
                th, pos, lg, cost = th_t, pos_t, lg_t, cost_t
                mu = max(mu / 3, 1e-7)
                break
            mu *= 4
        if progress is not None:
            progress(it + 1)
    values = float(valid.sum())
    kept = shared if shared_f0 else None
    spread = None
    if extra and not HOLD_F0:  # how well the photos hold the shared F0 where the steps left it
        at = geometry(pos, lg)
        irls = wt / (1 + residual2(th, at) / ROBUST**2)
        a, gp, b, c, gl = normal_equations(th, replace(lights, position=pos), aims, lg.exp(), pts, irls, y)
        a, gp, b, c, gl = _with_shared_f0(a + torch.diag(hold[:, 0]), gp, b, c, gl, shared, grey=extra == 1)
        if level:
            b, c, gl = _with_level(b, c, gl, torch.zeros(2, dtype=F64))
        spread = _f0_spread(reduced_system(a, gp, b, c, gl, 0.0)[1], basis, n, extra, level)
    return _Solved(pos, lg, used, th, noise, first / values, cost / values, kept, scan, spread)


def _f0_spread(s: Tensor, basis: Tensor, n: int, extra: int, level: bool) -> Tensor:
    """The shared F0's standard error (``extra`` numbers: RGB, or one grey) from the
    lights' system ``s`` with every pixel eliminated (:func:`reduced_system`, undamped;
    the Fisher information of photos whose noise the weights describe) in the steps'
    ``basis`` (``n`` lights; the shared F0's columns last, then with ``level`` the two
    multipliers, whose constraint the inverse of the bordered system keeps), with the
    gains' overall RGB factor held (the albedo and the shared F0 would take it): how far
    noise alone moves it with the lights, gains and every pixel's numbers free. Only the
    noise's part of its error: a bias does not show in it (docs/rti-record.md)."""
    overall = torch.zeros(basis.shape[0], 3, dtype=F64)
    for c in range(3):
        overall[3 * n + c : 6 * n : 3, c] = 1
    q = torch.linalg.qr(basis.T @ overall)[0]
    u = torch.linalg.svd(torch.eye(basis.shape[1], dtype=F64) - q @ q.T)[0][:, : basis.shape[1] - 3]
    cov = u @ torch.linalg.pinv(u.T @ basis.T @ s @ basis @ u, hermitian=True) @ u.T  # bordered: indefinite
    end = cov.shape[0] - (2 if level else 0)
    return cov.diagonal()[end - extra : end].clamp_min(0).sqrt()


def _pair_shift(
    photos: _Photos, fit: _Solved, pairs: int, iterations: int, progress=None
) -> tuple[Tensor, Tensor, list[tuple[_Photos, _Solved]]]:
    """The mean shift of the near lights' positions and of the log gains from ``fit`` to
    the fits of ``pairs`` antithetic pairs of replicas (:func:`_debiased`), and each
    replica with its fit's end."""
    a, b = fit.noise
    lights = replace(photos.lights, position=fit.pos)
    pts, valid = photos.pts[fit.used], photos.valid[..., fit.used]
    if REPLICA_FENCE > 0:  # the replicas' truth without the roughness outliers (module doc)
        fit = replace(fit, th=_fenced(fit.th, REPLICA_FENCE))
    clean = _render(fit.th, _placed(lights, photos.aims, fit.pos, fit.lg.exp()), pts)
    sd = (a * clean.clamp_min(0) + b).sqrt()
    shift_pos, shift_lg, ends = torch.zeros_like(fit.pos), torch.zeros_like(fit.lg), []
    for k in range(pairs):
        z = torch.randn(clean.shape, generator=torch.Generator().manual_seed(PAIR_SEED + k), dtype=F64)
        for sign in (1.0, -1.0):
            replica = replace(photos, lights=lights, pts=pts, y=clean + sign * sd * z, valid=valid)
            done = (2 * k + (sign < 0) + 1) * iterations
            step = None if progress is None else (lambda i, done=done: progress(done + i))
            if fit.shared is not None and bool(fit.shared.any()):  # as the photos were: one F0, searched
                f0 = fit.th[3:6, fit.shared][:, :1]
                again = _solve(
                    replica,
                    fit.th.clone(),
                    fit.lg.clone(),
                    iterations,
                    step,
                    shared_f0=True,
                    scan=(fit.th, f0),
                    fixed=(fit.noise, torch.ones(len(pts), dtype=torch.bool)),
                    sharing=fit.shared,
                )
                if REPLICA_SEARCHED:  # a second start, as the photos had: roughness searched at its own scan
                    other = _solve(
                        replica,
                        fit.th.clone(),
                        fit.lg.clone(),
                        iterations,
                        None,
                        shared_f0=True,
                        searched=True,
                        fixed=(fit.noise, torch.ones(len(pts), dtype=torch.bool)),
                        sharing=fit.shared,
                    )
                    again = other if other.cost < again.cost else again
            else:
                again = _solve(replica, fit.th.clone(), fit.lg.clone(), iterations, step)
            shift_pos += (again.pos - fit.pos) / (2 * pairs)
            shift_lg += (again.lg - fit.lg) / (2 * pairs)
            ends.append((replica, again))
    shift_pos = torch.where(photos.near[:, None], shift_pos, torch.zeros_like(shift_pos))
    return shift_pos, shift_lg, ends


def _fenced(th: Tensor, k: float) -> Tensor:
    """``th`` (9, P) with every pixel's roughness outside Tukey's fences, k interquartile
    ranges beyond the quartiles of the pixels' roughness, set to their median."""
    r = th[6]
    q1, mid, q3 = torch.quantile(r, torch.tensor([0.25, 0.5, 0.75], dtype=r.dtype))
    out = (r < q1 - k * (q3 - q1)) | (r > q3 + k * (q3 - q1))
    th = th.clone()
    th[6, out] = mid
    return th


def _radial(shift_pos: Tensor, out: Tensor, near: Tensor) -> float:
    """The mean over the near lights of ``shift_pos``'s part along each light's direction
    ``out`` from the sample's centre (0 with none)."""
    if not bool(near.any()):
        return 0.0
    return float((shift_pos * out / out.norm(dim=1, keepdim=True)).sum(1)[near].mean())


def _debiased(
    photos: _Photos, fit: _Solved, pairs: int, iterations: int, progress=None
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """The positions and log gains of ``fit`` with their bias removed (module doc): the
    kept pixels rendered from the fit's own lights, gains and per-pixel numbers, with
    noise of the fit's model added and subtracted (``pairs`` antithetic pairs), each
    replica fitted as the photos were, from that truth; their mean shift is the bias.
    With ``BIAS_ITERATED`` the bias is measured once more at each replica's end, from
    that replica as its truth, and 2·(the first) − (the mean of the second) removed."""
    shift_pos, shift_lg, ends = _pair_shift(photos, fit, pairs, iterations, progress)
    record: dict[str, Any] = {"pairs": pairs}
    if BIAS_ITERATED:  # Hall & Martin's iterated bootstrap: the first measure's own bias taken out
        again_pos, again_lg = torch.zeros_like(shift_pos), torch.zeros_like(shift_lg)
        for replica, end in ends:
            p, g, _ = _pair_shift(replica, end, pairs, iterations)
            again_pos += p / len(ends)
            again_lg += g / len(ends)
        record["first_radial_mm"] = round(_radial(shift_pos, fit.pos, photos.near), 4)
        record["second_radial_mm"] = round(_radial(again_pos, fit.pos, photos.near), 4)
        shift_pos, shift_lg = 2 * shift_pos - again_pos, 2 * shift_lg - again_lg
    record["removed_mm"] = _mean_max(shift_pos.norm(dim=1)[photos.near])
    if BIAS_RADIAL:  # the common radial part alone, the gains following the distances
        out = fit.pos  # from the sample's centre, the frame's origin
        dist = out.norm(dim=1, keepdim=True)
        radial = _radial(shift_pos, out, photos.near)
        record["radial_mm"] = round(radial, 4)
        step = torch.where(photos.near[:, None], radial * out / dist, torch.zeros_like(out))
        return fit.pos - step, fit.lg - 2 * (step * out / dist).sum(1, keepdim=True) / dist, record
    return fit.pos - shift_pos, fit.lg - shift_lg, record


def _second_order(photos: _Photos, fit: _Solved) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """The positions and log gains of ``fit`` with their bias removed by its second-order
    formula (Box 1971, "Bias in nonlinear estimation"; module doc): each pixel's numbers,
    fitted from its own few values, spread with covariance C = A⁻¹ (its 9 × 9 block, the
    spread capped by ``_SPREAD``; numbers at a bound held), and where the model bends that
    spread leaves a residual whose mean is −½ Σᵢⱼ Cᵢⱼ ∂²m/∂θᵢ∂θⱼ. The lights' Gauss–Newton
    step towards that mean residual, pixels eliminated as in the fit, is the bias."""
    a_noise, b_noise = fit.noise
    lights = replace(photos.lights, position=fit.pos)
    pts, valid = photos.pts[fit.used], photos.valid[..., fit.used]
    gains = fit.lg.exp()
    base = _placed(lights, photos.aims, fit.pos, gains)
    jac = _jacobians(fit.th, lights, photos.aims, gains, pts)
    m = jac[0]
    wt = valid / (a_noise * m.clamp_min(0) + b_noise)
    a = normal_equations(fit.th, lights, photos.aims, gains, pts, wt, m, jac)[0]
    held = ((fit.th <= _LOW + 1e-6) | (fit.th >= _HIGH - 1e-6)).T.to(F64)  # (P, 9)
    cov = torch.linalg.inv(a + torch.diag(_SPREAD**-2)[None] + torch.diag_embed(held * 1e12))
    ev, vec = torch.linalg.eigh(cov)
    curved = torch.zeros_like(m)  # Σᵢⱼ Cᵢⱼ ∂²m/∂θᵢ∂θⱼ, along C's principal axes
    h = 1e-3
    for k in range(9):
        u = h * (vec[:, :, k] * ev[:, k : k + 1].clamp_min(0).sqrt()).T  # (9, P)
        curved += (_render(fit.th + u, base, pts) + _render(fit.th - u, base, pts) - 2 * m) / h**2
    a, gp, b, c, gl = normal_equations(fit.th, lights, photos.aims, gains, pts, wt, m - 0.5 * curved, jac)
    if photos.level:  # the bias step keeps the pixels' mean slope
        b, c, gl = _with_level(b, c, gl, torch.zeros(2, dtype=F64))
    _, s, rhs = reduced_system(a, gp, b, c, gl, 0.0)
    n = len(lights)
    basis = _free_directions(photos.lights, photos.near, gradient=photos.level, common=photos.common)
    if photos.level:
        basis = torch.block_diag(basis, torch.eye(2, dtype=F64))
    bias = (basis @ torch.linalg.solve(basis.T @ s @ basis, basis.T @ rhs))[: 6 * n]
    shift_pos = torch.where(photos.near[:, None], bias[: 3 * n].reshape(n, 3), torch.zeros(n, 3, dtype=F64))
    norm = shift_pos.norm(dim=1)[photos.near]
    record = {
        "second_order": True,
        "removed_mm": _mean_max(norm),
    }
    return fit.pos - shift_pos, fit.lg - bias[3 * n :].reshape(n, 3), record


def fit_positions(
    capture: Capture,
    maps: MapSet,
    gains: Tensor,
    iterations: int | None = None,
    progress=None,
    bias_pairs: int | None = None,
    second_order: bool | None = None,
    shared_f0: bool | None = None,
    level: bool | None = None,
    alternate: tuple[MapSet, Tensor] | None = None,
    hold_places: bool = False,
    place_spread_mm: float | None = None,
    common: bool = False,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Positions (N, 3, mm) of every photo's light and RGB gains (N, 3) fitted jointly with
    the maps by ``iterations`` Gauss–Newton steps (when None, ``SHARED_ITERATIONS`` with a
    shared F0, else ``ITERATIONS``), their bias removed with ``bias_pairs`` antithetic pairs
    of replicas (``BIAS_PAIRS`` when None; 0: left in) or, without pairs and with
    ``second_order`` (``SECOND_ORDER`` when None), by its second-order formula after a fit
    that holds the pixels' numbers near their start (module doc). With ``shared_f0``
    (``SHARED_F0`` when None) the dielectric pixels share one F0 in the fit. With ``level``
    (``selfcal.LEVEL`` when None) the gains' gradient across the dome is fitted too and the
    kept pixels' slopes' sum held where the start put it (:func:`_with_level`).
    ``progress`` is called with the steps done so far, of ``iterations`` · (1 + 2 · pairs).

    ``capture`` is the capture as calibrated before self-calibration, already reduced to
    the pixels to use; ``maps`` are maps fitted to its photos divided by ``gains`` (the
    start), which are gains times any intensity scale of that fit. Directional lights keep
    their directions. Returns the positions, the gains (the start's overall factor, and
    without ``level`` its gradient across the dome, kept) and a record. ``alternate``: other
    start maps and their gains (``WEAK_START``), fitted from too, on the same pixels under
    the same noise model (with ``WEAK_SAME`` the same pixels sharing the F0, started at the
    first start's scan, else its own; no roughness searched). Of the starts' ends, the one
    ``ENDS_BY`` says is kept: by default the one that fits the photos best. With
    ``hold_places`` every light stays where the capture puts it: only the gains are fitted
    with the maps (:func:`estimate_held_gains`). ``place_spread_mm``: a Gaussian prior of
    that many mm per axis on the near lights' places about where the capture puts them
    (``PLACE_SPREAD_MM`` when None; 0: none). With ``common`` the near lights move only
    together, by one shift and one change of the dome's scale (``CALIBRATED_COMMON``)."""
    n = len(capture.files)
    lights = _double(capture.lights)
    near = lights.w > 0.5
    aims = torch.stack(
        [
            torch.tensor(capture.rig.lights[k].aim_mm, dtype=F64) if k is not None else torch.zeros(3, dtype=F64)
            for k in capture.light_indices
        ]
    )
    aims = torch.where(near[:, None], aims, lights.position - lights.axis)  # directional: unused
    h, w = capture.size
    photos = _Photos(
        lights=lights,
        aims=aims,
        near=torch.zeros_like(near) if hold_places else near,  # held: every light's place fixed
        pts=surface_points(capture.field_mm, (h, w), dtype=F64).reshape(-1, 3),
        y=capture.linear(list(range(n))).to(F64).reshape(n, 3, -1),
        valid=(~capture.saturation(list(range(n)))).to(F64).reshape(n, 1, -1).expand(n, 3, -1),
        level=selfcal.LEVEL if level is None else level,
        spread=PLACE_SPREAD_MM if place_spread_mm is None else place_spread_mm,
        common=common,
    )
    th = _numbers(maps)
    pairs = BIAS_PAIRS if bias_pairs is None else bias_pairs
    second = pairs == 0 and (SECOND_ORDER if second_order is None else second_order)
    shared = SHARED_F0 if shared_f0 is None else shared_f0
    if iterations is None:
        iterations = SHARED_ITERATIONS if shared else ITERATIONS
    if ENDS_BY not in _ENDS_BY:
        raise ValueError(f"lightpos.ENDS_BY: one of {', '.join(_ENDS_BY)}, not {ENDS_BY!r}")
    first = _solve(photos, th, gains.to(F64).log(), iterations, progress, held=second, shared_f0=shared)
    solved = {"start": first}  # each start's end
    if shared and first.shared is not None and bool(first.shared.any()):
        # once more with every pixel's roughness searched at the shared F0's start: the end that
        # fits the photos better is kept (``_F0_GRID``; the start's roughness suits rough
        # materials, the searched one glossy ones, docs/rti-record.md)
        later = None if progress is None else (lambda i: progress(iterations + i))
        lg0 = gains.to(F64).log()
        solved["searched"] = _solve(
            photos, th, lg0, iterations, later, held=second, shared_f0=True, searched=True, scan=first.scan
        )
    if alternate is not None:  # from other start maps, on the same pixels and in the same units
        later = None if progress is None else (lambda i: progress(len(solved) * iterations + i))
        solved["weak"] = _solve(
            photos,
            _numbers(alternate[0]),
            alternate[1].to(F64).log(),
            iterations,
            later,
            held=second,
            shared_f0=shared,
            fixed=(first.noise, first.used),
            scan=first.scan if WEAK_SAME else None,
            sharing=first.shared if WEAK_SAME else None,
        )
    nominal = lights.position[near]  # directional lights keep their directions: none moved
    distance = {
        k: float((v.pos[near] - nominal).square().sum(1).sum().div(max(len(nominal), 1)).sqrt())
        for k, v in solved.items()
    }
    if ENDS_BY == "nearest" and len(nominal):
        kept = min(solved, key=distance.__getitem__)
    else:
        kept = "searched" if "searched" in solved and solved["searched"].cost < first.cost else "start"
        if "weak" in solved and solved["weak"].cost < (1 - WEAK_MARGIN) * solved[kept].cost:
            kept = "weak"
    fit = solved[kept]
    # which start's end was kept where an F0 was shared, or the weak start's
    roughness = kept if kept == "weak" or "searched" in solved else None
    ends = {k: v.cost for k, v in solved.items()}  # each start's misfit per value at its end
    if pairs > 0:
        done = (len(ends) - 1) * iterations  # the other starts' steps
        step = None if progress is None else (lambda i: progress(done + i))
        pos, lg, bias = _debiased(photos, fit, pairs, iterations, step)
    elif second:
        pos, lg, bias = _second_order(photos, fit)
    else:
        pos, lg, bias = fit.pos, fit.lg, {"pairs": 0}
    shift = (pos - lights.position).norm(dim=1)[near]
    record = {
        "near_lights": int(near.sum()),
        "pixels_used": round(float(fit.used.double().mean()), 4),
        "iterations": iterations,
        "noise_model": {"a": _sig4(fit.noise[0]), "b": _sig4(fit.noise[1])},  # var = a·m + b
        "misfit_per_value": {  # robust, in units of the noise model read from the first start's residuals
            "start": round(fit.first, 4),
            "end": round(fit.cost, 4),
            **({"ends": {k: round(v, 4) for k, v in ends.items()}, "kept": kept} if len(ends) > 1 else {}),
        },
        # each start's end: its near lights' root mean square distance from the places they
        # started at, the rig file's (``ENDS_BY``)
        **({"ends_moved_mm": {k: round(v, 3) for k, v in distance.items()}} if len(ends) > 1 else {}),
        "moved_mm": _mean_max(shift),
        "bias": bias,
    }
    if fit.shared is not None:
        one = fit.th[3:6, fit.shared][:, 0] if bool(fit.shared.any()) else None
        # the one F0 of the dielectric pixels (None: none shared), and their share of those used
        record["shared_f0"] = {
            "share": round(float(fit.shared.double().mean()), 4),
            "value": None if one is None else [round(float(v), 4) for v in one],
            "roughness": roughness,  # the kept end's start: "start" (the maps'), "searched", "weak", None
            # the scan's best value: where the steps started it, or why none was shared
            "scanned": None if fit.scan is None else round(fit.scan[1], 4),
            # its standard error from the photos' noise (None: none shared, or held)
            "se": None if fit.f0_spread is None else [round(float(v), 4) for v in fit.f0_spread],
        }
    return pos.float(), lg.exp().float(), record


def _numbers(maps: MapSet) -> Tensor:
    """Every pixel's 9 numbers (9, P) of ``maps``: ρ and F0 per channel, roughness and the
    normal's two slopes."""
    spec = maps.specular.to(F64).reshape(maps.specular.shape[0], -1).expand(3, -1)
    slopes = lm._theta_of(maps.roughness.to(F64), maps.normal.to(F64)).reshape(3, -1)
    return torch.cat([maps.diffuse.to(F64).reshape(3, -1), spec.clone(), slopes])


def _lit_from(capture: Capture, pos: Tensor) -> Capture:
    """The capture with its near lights at ``pos`` (N, 3), each aimed at its rig-file aim
    point (the photo's own axis where it has no rig light)."""
    lights = capture.lights
    near = lights.w > 0.5
    position, axis = lights.position.clone(), lights.axis.clone()
    for i, k in enumerate(capture.light_indices):
        if not bool(near[i]):
            continue
        aim = torch.tensor(capture.rig.lights[k].aim_mm) if k is not None else position[i] + axis[i]
        position[i] = pos[i]
        axis[i] = (aim - pos[i]) / (aim - pos[i]).norm()
    return replace(capture, lights=replace(lights, position=position, axis=axis))


def _level_turn(slope: Tensor) -> Tensor:
    """The rotation (3, 3) that turns the normal of slope ``slope`` (2,: n_x / n_z, n_y /
    n_z) to the vertical, about the axis in the sample's plane perpendicular to it
    (Rodrigues): applied to the lights about the sample's centre, it turns the dome so
    that maps fitted under it lie level."""
    m = torch.cat([slope.to(F64), torch.ones(1, dtype=F64)])
    m = m / m.norm()
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    axis = torch.linalg.cross(m, z)
    sin, cos = axis.norm(), m @ z
    if float(sin) < 1e-12:
        return torch.eye(3, dtype=F64)
    k = axis / sin
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=F64)
    return torch.eye(3, dtype=F64) + sin * kx + (1 - cos) * (kx @ kx)


_LEVELS = {"median": selfcal.median_slope, "agreed": selfcal.agreed_slope, "base": selfcal.base_slope}


def _turned_level(
    small: Capture, pos: Tensor, gains: Tensor, fit_cfg: ReconstructConfig, turns: int
) -> tuple[Tensor, list[dict[str, Any]]]:
    """The near lights' positions ``pos`` (N, 3) turned about the sample's centre until the
    ``lm`` solver's maps fitted at them with ``gains`` lie level (``LEVEL_TURNS``; level as
    ``LEVEL_BY`` means it), at most ``turns`` times, and the record of each turn (which
    level, the maps' slope by it, the angle, and whether it was made: the last is not
    where it was under ``LEVEL_TURN_MIN``; after ``turns`` turns made, the maps at the last
    are not fitted again). The fit's other numbers (its misfit, the gains) stay those of
    the lights before the turns."""
    from matscan.reconstruct.job import reconstruct_capture
    from matscan.reconstruct.selfcal import with_gains

    near = small.lights.w > 0.5
    done = []
    for _ in range(turns):
        maps = reconstruct_capture(with_gains(_lit_from(small, pos), gains), fit_cfg, None).maps
        if LEVEL_BY not in _LEVELS:
            raise ValueError(f"lightpos.LEVEL_BY is {LEVEL_BY!r}: one of {', '.join(_LEVELS)}")
        slope = _LEVELS[LEVEL_BY](maps).to(F64)
        rot = _level_turn(slope)
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(rot)) - 1) / 2))))
        made = angle >= LEVEL_TURN_MIN
        done.append(
            {"by": LEVEL_BY, "slope": [round(float(v), 5) for v in slope], "degrees": round(angle, 4), "made": made}
        )
        if not made:
            break
        pos = torch.where(near[:, None], (pos.to(F64) @ rot.T).to(pos.dtype), pos)
    return pos, done


def _mean_max(mm: Tensor) -> dict[str, float]:
    """The record's mean and largest of distances ``mm`` (0 for none)."""
    return {
        "mean": round(float(mm.mean()), 3) if len(mm) else 0.0,
        "max": round(float(mm.max()), 3) if len(mm) else 0.0,
    }


def _sig4(v: float) -> float:
    return float(f"{v:.4g}")


def _fixed_steps(cfg: ReconstructConfig):
    """The solver settings of the joint fit's own maps: the full level's fixed steps only,
    as when its settings were chosen and measured (the final fit after it takes the steps
    on the pixels still converging; runs/lm-converge/README.md)."""
    return replace(cfg.lm, more_iterations=0)


def estimate_held_gains(
    capture: Capture, gains: Tensor, cfg: ReconstructConfig, progress: bool = False, level: bool | None = None
) -> tuple[Tensor, dict[str, Any]]:
    """RGB gains (N, 3) fitted by the joint fit with every light held at the capture's
    place, for a capture whose intensities the diffuse reflection could not give
    (``gains``: :func:`matscan.reconstruct.selfcal.estimate_gains`'s, unread), and a
    record. Placed from the photos too, the lights of such materials (a black knit, a worn
    print, a brushed metal) went 20-87 mm astray, and 2.4-52 mm started at the truth: the
    knit's misfit hardly tells those places apart, the metal's prefers them, and the worn
    print's steps leave its truth (docs/rti-record.md, "their misfit, profiled"); held, their
    gains came 3-7% off (RMS) against ±20% at the rig file's, and over six draws of the
    three they relit 1.31 → 0.63 dB below the ideal dome on average, 3 → 9 of 18 within
    0.5 dB, worse on 3 (docs/rti-record.md, "The unread intensities").
    Pixels as :func:`estimate_positions` takes them (``POSITION_SIDE``); ``level`` as
    there."""
    from matscan.reconstruct.job import SELF_CALIBRATION_OFF, reconstruct_capture
    from matscan.reconstruct.selfcal import gauged, reduced, with_gains

    h, w = capture.size
    factor = max(1, math.ceil(max(h, w) / POSITION_SIDE))
    small = reduced(capture, factor)
    fit_cfg = replace(cfg, refine="on", solver="lm", validate=0, lm=_fixed_steps(cfg), **SELF_CALIBRATION_OFF)
    start = reconstruct_capture(with_gains(small, gains), fit_cfg, None)
    shared = SHARED_F0 if cfg.shared_f0 is None else cfg.shared_f0
    level = selfcal.fits_gradient(capture, cfg) if level is None else level
    steps = SHARED_ITERATIONS if shared else ITERATIONS
    with tqdm(total=steps * (2 if shared else 1), desc="gains", unit="step", disable=not progress, leave=False) as bar:
        _, fitted, fit = fit_positions(
            small,
            start.maps,
            gains * start.intensity_scale,
            iterations=steps,
            progress=lambda i: bar.update(i - bar.n),
            shared_f0=shared,
            level=level,
            hold_places=True,
            bias_pairs=0,  # the places held: no bias of theirs to remove
        )
    held = gauged(fitted, capture.lights, level)
    record = {
        "light_gains": {f: [round(float(v), 5) for v in g] for f, g in zip(capture.files, held, strict=True)},
        "misfit_per_value": fit["misfit_per_value"],
        "pixels_used": fit["pixels_used"],
        "reduced_by": factor,
    }
    return held, record


def estimate_positions(
    capture: Capture,
    gains: Tensor,
    cfg: ReconstructConfig,
    progress: bool = False,
    level: bool | None = None,
    together: bool = False,
) -> tuple[LightSet | None, Tensor, dict[str, Any], list[str]]:
    """The photos' lights with the near lights where the photos place them, new gains
    (N, 3), a record and warnings, for a capture whose intensities were self-calibrated
    (``gains``, from :func:`matscan.reconstruct.selfcal.estimate_gains`). With
    ``cfg.shared_f0`` (``SHARED_F0`` when None) the dielectric pixels share one F0 in the
    fit, which then takes ``SHARED_ITERATIONS`` steps from each of its two starts;
    without, each pixel fits its own in ``ITERATIONS`` steps. The maps that
    start the joint fit are the ``lm`` solver's from flat maps, on every ``factor``-th
    pixel (``POSITION_SIDE``). Without near lights, or where the capture gives each
    photo's geometry (a flash rig: measured on domes only), the lights are returned as
    None and the gains unchanged. ``level``: the gains' convention (the intensities'
    record's ``convention`` is "level sample"); by default :func:`selfcal.fits_gradient`'s.
    ``together``: the near lights move only together from where the capture puts them
    (``CALIBRATED_COMMON``: a calibration's places whose intensities were confirmed)."""
    from matscan.reconstruct.job import SELF_CALIBRATION_OFF, reconstruct_capture
    from matscan.reconstruct.selfcal import gauged, reduced, with_gains

    near = capture.lights.w > 0.5
    if not bool(near.any()):
        note = (
            "--self-calibrate-positions: the capture's lights are all directional, with no position to fit; "
            "only their intensities were self-calibrated"
        )
        return None, gains, {"near_lights": 0}, [note]
    if capture.rig.per_image_geometry:
        note = (
            "--self-calibrate-positions: the capture gives each photo's light and camera (a flash rig); "
            "their positions are kept, only the intensities were self-calibrated (measured on domes only)"
        )
        return None, gains, {"near_lights": int(near.sum()), "kept": "per-photo geometry"}, [note]
    h, w = capture.size
    factor = max(1, math.ceil(max(h, w) / POSITION_SIDE))
    small = reduced(capture, factor)
    fit_cfg = replace(cfg, refine="on", solver="lm", validate=0, lm=_fixed_steps(cfg), **SELF_CALIBRATION_OFF)
    start_cfg = fit_cfg
    if START_PRIOR != 1.0 or START_ROUGHNESS_PRIOR != 1.0:  # the start's maps held less near the solver's start
        held = {k: getattr(cfg.lm, k) * START_PRIOR for k in _PRIORS}
        held["prior_roughness"] *= START_ROUGHNESS_PRIOR
        start_cfg = replace(fit_cfg, lm=replace(fit_cfg.lm, **held))
    start = reconstruct_capture(with_gains(small, gains), start_cfg, None)
    alternate = None
    if WEAK_START > 0:  # a third start, its maps held less near the solver's flat start
        weak_cfg = replace(fit_cfg, lm=replace(fit_cfg.lm, **{k: getattr(cfg.lm, k) * WEAK_START for k in _PRIORS}))
        weak = reconstruct_capture(with_gains(small, gains), weak_cfg, None)
        alternate = (weak.maps, gains * weak.intensity_scale)
    shared = SHARED_F0 if cfg.shared_f0 is None else cfg.shared_f0
    level = selfcal.fits_gradient(capture, cfg) if level is None else level
    steps = SHARED_ITERATIONS if shared else ITERATIONS
    total = steps * (1 + 2 * BIAS_PAIRS + (1 if shared else 0) + (alternate is not None))  # the other starts
    placed = "light_positions_mm" in (capture.calibration or {})
    spread = CALIBRATED_SPREAD_MM if placed and CALIBRATED_SPREAD_MM > 0 else None  # about the calibration's
    tilt = selfcal.median_slope(start.maps)  # the start's, which the fit holds under the level convention
    if level and LEVEL_START:
        start = replace(start, maps=selfcal.levelled(start.maps))
        if alternate is not None:
            alternate = (selfcal.levelled(alternate[0]), alternate[1])
    with tqdm(total=total, desc="positions", unit="step", disable=not progress, leave=False) as bar:
        pos, fitted, record = fit_positions(
            small,
            start.maps,
            gains * start.intensity_scale,
            iterations=steps,
            progress=lambda i: bar.update(i - bar.n),
            shared_f0=shared,
            level=level,
            alternate=alternate,
            place_spread_mm=spread,
            common=together,
        )
    record["reduced_by"] = factor
    if spread is not None:
        record["place_spread_mm"] = spread
    if together:
        record["moved_together"] = True
    if level:  # the start's median slope (x, y), and whether the fit started with it removed
        record["start_slope"] = {"median": [round(float(v), 5) for v in tilt], "removed": LEVEL_START}
    if level and LEVEL_TURNS:  # the fitted dome turned until the maps at it lie level
        levelled_gains = gauged(fitted, capture.lights, level)
        pos, record["level_turns"] = _turned_level(small, pos, levelled_gains, fit_cfg, LEVEL_TURNS)
        record["moved_mm"] = _mean_max((pos - capture.lights.position).norm(dim=1)[near])
    record["light_positions_mm"] = {
        capture.files[i]: [round(float(v), 3) for v in pos[i]] for i in range(len(pos)) if bool(near[i])
    }
    lights = _lit_from(capture, pos).lights
    notes = []
    if record["moved_mm"]["max"] > MOVED_WARN_MM:
        notes.append(
            f"--self-calibrate-positions: a light moved {record['moved_mm']['max']:.0f} mm from the rig file's "
            f"place (more than {MOVED_WARN_MM:.0f} mm): check the rig file, or measure the positions with "
            "`matscan calibrate --grey --positions` or `matscan rig from-spheres`"
        )
    return lights, gauged(fitted, capture.lights, level), record, notes
