"""Calibration (paper §3.2): a colour matrix from a ColorChecker, and per-light
intensity scales (and optional flat fields and near-light positions) from a grey card.

``calibration.json`` (``matscan-calibration/1``)::

    {"format": "matscan-calibration/1",
     "colour_matrix": [[…], […], […]],        # linear camera RGB → linear sRGB
     "light_scales": {"0": 1.02, "1": 0.97, …},  # per rig light: photo = scale × model
     "flat_fields": {"0": "flat_00.exr", …},   # optional: per light, mean 1
     "light_positions_mm": {"0": [x, y, z], …},  # optional: near lights' fitted places
     "exposure_s": 0.005, "led_level": 1.0,    # optional: the grey card's exposure and LED level
     "grey_albedo": 0.18}

A capture that names it is corrected on reading for reconstruction
(:func:`apply_calibration`): colour matrix first, then each photo divided by its
light's scale and flat field; lights with a fitted position
(:func:`fit_light_positions`, ``calibrate --positions``) are moved there, each LED
still aimed where the rig file aims it. The scales hold for photos taken at the grey card's
exposure and LED level, which ``calibrate`` copies from the card's ``capture.json``
(``acquisition``) where ``matscan capture`` recorded them; a capture that records another
exposure or level has the scales multiplied by the ratio of exposure × level
(:func:`exposure_ratio`). Every field is checked there (errors name the file
and the field); plausible-but-wrong calibrations become warnings in the capture's
``meta["warnings"]``. :func:`check_chart` and :func:`check_scales` give the
warnings about a chart photo and about computed scales; :func:`calibrate` is
``matscan calibrate``: photos in, ``calibration.json`` out.

The ColorChecker is found in the photo (:func:`detect_chart`: OpenCV's ``mcc``
detector, then the grid fitted to the patches' own pixels), or located by the user
(the four outer corners of its grid of cells, in pixels). Its reference values come
from colour-science's published data (``colorchecker24.json``, which names the
edition).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from matscan.capture import Capture
from matscan.capture.folder import EXPOSURE_LIMITS, Correction
from matscan.color import srgb_to_linear
from matscan.errors import MatscanError, input_error
from matscan.jsonfile import check_file_name, check_number, check_object, check_vector, short_repr
from matscan.render import render, surface_points
from matscan.rig import Rig

CALIBRATION_FORMAT = "matscan-calibration/1"
GREY_CARD = 0.18

#: The ColorChecker Classic's reference values (``colorchecker24.json``, written by
#: tools/colorchecker_reference.py from colour-science's published data; its
#: ``edition`` names the chart's formulation).
CHART_FILE = Path(__file__).with_name("colorchecker24.json")


def colorchecker_reference() -> dict[str, Any]:
    """The chart's reference file: edition, source, and per patch (row by row from dark
    skin to black) its name, CIE xyY and linear sRGB."""
    return json.loads(CHART_FILE.read_text(encoding="utf-8"))


def colorchecker_linear() -> Tensor:
    """(24, 3) linear sRGB (D65) reference values of the chart's patches, row by row."""
    patches = colorchecker_reference()["patches"]
    return torch.tensor([p["linear_srgb"] for p in patches], dtype=torch.float32)


CHART_PATCHES = 24


def _check_corners(corners: Sequence[Sequence[float]]) -> list[np.ndarray]:
    """The four corners as float arrays; each must be two finite numbers."""
    if len(corners) != 4:
        raise MatscanError(f"corners: expected 4 (x, y) points, got {len(corners)}")
    out = []
    for i, c in enumerate(corners):
        out.append(np.array(check_vector(list(c), 2, f"corners[{i}]"), dtype=np.float64))
    return out


def grid_homography(corners: Sequence[Sequence[float]], rows: int = 4, cols: int = 6) -> np.ndarray:
    """The 3 × 3 map from chart cell coordinates (u across ``cols`` cells, v down
    ``rows``; a cell is 1 × 1) to pixels (x = column, y = row), given the grid's four
    outer corners: top-left, top-right, bottom-right, bottom-left."""
    import cv2

    tl, tr, br, bl = _check_corners(corners)
    cells = np.float32([[0, 0], [cols, 0], [cols, rows], [0, rows]])
    pixels = np.float32([tl, tr, br, bl])
    if abs(cv2.contourArea(pixels)) < 1.0:
        raise MatscanError("corners: the four corners enclose no area; give the chart's outer corners")
    return cv2.getPerspectiveTransform(cells, pixels)


def _apply(h: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = np.c_[uv, np.ones(len(uv))] @ h.T
    return p[:, :2] / p[:, 2:]


def sample_patches(
    photo: Tensor,
    corners: Sequence[Sequence[float]] | None = None,
    rows: int = 4,
    cols: int = 6,
    fraction: float = 0.5,
) -> Tensor:
    """Mean colour (rows·cols, 3) of each patch of a chart in a linear photo (3, H, W).

    ``corners``: the outer corners of the chart's grid of cells (x = column, y = row of
    a pixel's centre) in the order top-left, top-right, bottom-right, bottom-left (as
    :func:`detect_chart` gives them); the whole photo by default. The chart may be seen
    in perspective: cells map to the photo by the homography of the corners. The
    central ``fraction`` of each cell is averaged (5 × 5 samples). A sample outside the
    photo is an error (the corners do not lie on the photo).
    """
    _, h, w = photo.shape
    if corners is None:
        corners = [(0, 0), (w, 0), (w, h), (0, h)]
    hom = grid_homography(corners, rows, cols)
    steps = np.linspace(-fraction / 2, fraction / 2, 5)
    out = []
    for r in range(rows):
        for c in range(cols):
            uv = np.array([(c + 0.5 + du, r + 0.5 + dv) for dv in steps for du in steps])
            samples = []
            for x, y in _apply(hom, uv):
                if not (0 <= x < w and 0 <= y < h):
                    raise MatscanError(
                        f"corners: patch {r * cols + c + 1} of the chart falls at (x {x:.0f}, y {y:.0f}), "
                        f"outside the {w}×{h} photo; give the chart's corners inside the photo"
                    )
                samples.append(photo[:, int(y), int(x)])
            out.append(torch.stack(samples).mean(0))
    return torch.stack(out)


def _patch_centre(img: np.ndarray, hom: np.ndarray, r: int, c: int) -> np.ndarray | None:
    """The centre (x, y) of the patch in cell (r, c): of the cell's pixels, those closer in
    colour to the cell's centre than to its rim (where the chart's dark gaps are)."""
    inv = np.linalg.inv(hom)
    poly = _apply(hom, np.array([[c, r], [c + 1, r], [c + 1, r + 1], [c, r + 1]], dtype=np.float64))
    x0, y0 = np.maximum(np.floor(poly.min(0)).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(poly.max(0)).astype(int) + 1, (img.shape[1], img.shape[0]))
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    ys, xs = np.mgrid[y0:y1, x0:x1]
    xs, ys = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    uv = _apply(inv, np.c_[xs, ys]) - (c, r)
    inside = (uv > 0).all(1) & (uv < 1).all(1)
    off = np.abs(uv - 0.5).max(1)
    colours = img[ys.astype(int), xs.astype(int)]
    core, rim = inside & (off < 0.25), inside & (off > 0.45)
    if core.sum() < 4 or rim.sum() < 4:
        return None
    near = np.linalg.norm(colours - np.median(colours[core], 0), axis=1)
    far = np.linalg.norm(colours - np.median(colours[rim], 0), axis=1)
    chosen = inside & (near < far)
    if chosen.sum() < 4:
        return None
    # the centroid in cell coordinates, each pixel weighted by the cell area it covers
    # (1/w³ of the inverse homography), mapped back: an image-space centroid would be
    # pulled toward the near side of a patch seen in perspective
    w = np.c_[xs[chosen], ys[chosen], np.ones(int(chosen.sum()))] @ inv[2]
    weight = 1 / np.abs(w) ** 3
    centre_uv = (uv[chosen] * weight[:, None]).sum(0) / weight.sum() + (c, r)
    return _apply(hom, centre_uv[None])[0]


def _fit_grid(centres: np.ndarray, rows: int, cols: int) -> np.ndarray:
    import cv2

    uv = np.float32([[c + 0.5, r + 0.5] for r in range(rows) for c in range(cols)])
    keep = np.isfinite(centres).all(1)
    hom, _ = cv2.findHomography(uv[keep], np.float32(centres[keep]), 0)
    if hom is None:
        raise MatscanError("chart: the detected patches do not form a grid")
    return hom


#: Rounds of patch-centre refinement after OpenCV's detection: its patch outlines are
#: off by a few pixels; fitting the grid to the patches' own centres brought the corners
#: of simulated charts (turned 15° to 270°, in perspective, 8-bit with noise) from 3–9 px
#: off to under 0.5 px.
REFINE_ROUNDS = 2


def detect_chart(photo: Tensor, where: str = "chart photo") -> list[tuple[float, float]]:
    """The outer corners of a ColorChecker Classic's grid of cells in a linear photo
    (3, H, W), top-left, top-right, bottom-right, bottom-left with the chart upright
    (dark skin top-left, black bottom-right) whatever its orientation in the photo.

    OpenCV's ``mcc`` detector (opencv-contrib) finds the chart and its patches; the
    grid is then fitted, by a homography, to the centroids of the patches' own pixels
    (``REFINE_ROUNDS`` rounds). Raises a MatscanError naming ``where`` when no chart is
    found.
    """
    import cv2

    if not hasattr(cv2, "mcc"):
        raise MatscanError(
            "calibrate: this OpenCV has no ColorChecker detector (cv2.mcc); install opencv-contrib-python-headless "
            "in place of opencv-python-headless, or give --corners"
        )
    from matscan.color import linear_to_srgb

    srgb = linear_to_srgb(photo.clamp(0, 1)).permute(1, 2, 0).numpy()
    bgr = np.ascontiguousarray((srgb[:, :, ::-1] * 255 + 0.5).astype(np.uint8))
    detector = cv2.mcc.CCheckerDetector_create()
    if not detector.process(bgr, cv2.mcc.MCC24, 1):
        raise MatscanError(f"{where}: no ColorChecker Classic found; give its corners with --corners")
    checker = detector.getBestColorChecker()
    centres = np.asarray(checker.getColorCharts(), dtype=np.float64).reshape(CHART_PATCHES, 4, 2).mean(1)
    hom = _fit_grid(centres, 4, 6)
    img = srgb.astype(np.float64)
    for _ in range(REFINE_ROUNDS):
        found = [_patch_centre(img, hom, r, c) for r in range(4) for c in range(6)]
        if sum(f is not None for f in found) < 12:
            break
        centres = np.array([f if f is not None else (np.nan, np.nan) for f in found])
        hom = _fit_grid(centres, 4, 6)
    corners = _apply(hom, np.array([[0, 0], [6, 0], [6, 4], [0, 4]], dtype=np.float64))
    return [(float(x), float(y)) for x, y in corners]


#: A chart's patches are a colour chart when their chromaticities (r, g, b over their
#: sum) spread by more than this; the ColorChecker's spread 0.6, a grey card's under 0.02.
MIN_CHART_SPREAD = 0.1


def check_chart(measured: Tensor) -> list[str]:
    """Warnings (one line each, saying what to do) about patches sampled from a chart photo.

    ``measured``: (24, 3) linear camera RGB of the ColorChecker's patches, row by row
    (:func:`sample_patches`). Warns when the patches are black, when they are almost
    without chroma (the photo shows no colour chart), and when the bottom row does not
    run from white to black (corners in the wrong order). Empty when all is well.
    """
    if measured.shape != (CHART_PATCHES, 3):
        raise MatscanError(f"measured: expected ({CHART_PATCHES}, 3) patch colours, got {tuple(measured.shape)}")
    m = measured.double()
    total = m.sum(dim=1)
    if not torch.isfinite(m).all() or float(total.max()) <= 1e-6:
        return ["the chart photo is black where the patches should be; check the exposure and --corners"]
    chroma = m / total.clamp_min(1e-9)[:, None]
    spread = float((chroma.max(dim=0).values - chroma.min(dim=0).values).max())
    if spread < MIN_CHART_SPREAD:
        return [
            f"the photo shows no colour chart (its patches are nearly grey: chromaticity spread {spread:.3f}); "
            "check --corners, or photograph a ColorChecker Classic"
        ]
    neutral = total[18:24]
    if not bool((neutral[:-1] > neutral[1:]).all()):
        return [
            "the chart's bottom row does not run from white to black; give --corners in the order "
            "top-left, top-right, bottom-right, bottom-left with the chart upright (white patch bottom-left)"
        ]
    return []


def colour_matrix(measured: Tensor, reference: Tensor) -> Tensor:
    """3 × 3 M minimising Σ ‖M·measured_i − reference_i‖² (linear least squares)."""
    sol = torch.linalg.lstsq(measured.double(), reference.double()).solution  # measured @ X ≈ reference
    return sol.T.float()


def weighted_median(values: Tensor, weights: Tensor) -> float:
    """The minimiser s of Σ w_i |v_i − s| (for v = p/r, w = r: of Σ |p_i − s r_i|).

    ``values`` and ``weights`` are 1-D and non-empty (an empty input is an error).
    """
    if values.numel() == 0:
        raise MatscanError("weighted_median: no values (every sample was masked out)")
    order = torch.argsort(values)
    v, w = values[order], weights[order]
    cum = torch.cumsum(w, 0)
    idx = int(torch.searchsorted(cum, cum[-1] / 2))
    return float(v[min(idx, len(v) - 1)])


#: A light's scale outside this range is implausible (a warning says so); outside
#: ``SCALE_LIMITS`` it is an error (the corrected photos would leave float32's range).
SCALE_PLAUSIBLE = (1e-3, 1e3)
SCALE_LIMITS = (1e-6, 1e6)


def check_scales(scales: Mapping[str, float], source: str = "calibration") -> list[str]:
    """Warnings (one line each) about implausible light scales (outside ``SCALE_PLAUSIBLE``).

    ``scales`` maps a light index (as text) to its scale (photo = scale × model);
    ``source`` names where they come from in the message.
    """
    low, high = SCALE_PLAUSIBLE
    odd = {k: s for k, s in scales.items() if not low <= s <= high}
    if not odd:
        return []
    shown = ", ".join(f"light {k}: {s:g}" for k, s in list(odd.items())[:4]) + (", …" if len(odd) > 4 else "")
    return [
        f"{source}: implausible light scale ({shown}; expected {low:g} to {high:g}); "
        "check the exposure of the grey-card photos and recalibrate"
    ]


def significant(value: float, digits: int = 7) -> float:
    """``value`` to ``digits`` significant digits (a scale of 2e-6 keeps its own digits,
    where 6 decimals made 1.93e-6 and 2.10e-6 the same 2e-6)."""
    return float(f"{float(value):.{digits}g}")


def _grey_scale(photo: Tensor, model: Tensor, saturated: Tensor, k: int, where: str = "calibrate") -> float:
    """The scale of light ``k`` from its grey-card photo (``where``: its file) and
    rendering (each (c, H, W))."""
    lit = model > 1e-4
    if not bool(lit.any()):
        raise MatscanError(f"{where}: light {k} does not light the grey card (check the rig file)")
    ok = (~saturated).expand_as(model) & lit
    if not bool(ok.any()):
        raise MatscanError(f"{where}: every pixel saturated under light {k}; lower the exposure")
    s = weighted_median(photo[ok] / model[ok], model[ok])
    if not s > 0:
        raise MatscanError(f"{where}: the grey card is black under light {k}; check that the light fired")
    return s


def _photo_name(capture: Capture, i: int) -> str:
    """How messages name a capture's photo ``i``: its file, where the capture has a folder."""
    return str(capture.folder / capture.files[i]) if capture.folder is not None else f"calibrate: photo {i}"


def light_scales(
    grey: Capture,
    albedo: float = GREY_CARD,
    flat_fields: bool = False,
    flat_sigma_px: float = 8.0,
    colour: bool = False,
) -> tuple[dict[str, Any], dict[str, Tensor]]:
    """Per-light intensity scale from photos of a grey card (a flat Lambertian of
    ``albedo``) under each light: the scale minimising the L1 distance between the
    photo and the rendering (the paper's 24 parameters); optionally the remaining
    smooth spatial ratio as a flat field of mean 1. With ``colour`` each scale is an
    RGB triple, one per channel: the card is neutral, so its colour under a light is
    the light's (and the camera's white balance, the same for every light).

    A light under which every pixel is saturated (or the card black) is an error
    naming it; :func:`check_scales` gives the warnings about implausible scales.
    """
    h, w = grey.size
    pts = surface_points(grey.field_mm, (h, w))
    n = torch.zeros(3, h, w)
    n[2] = 1
    scales, flats = {}, {}
    for i, k in enumerate(grey.light_indices):
        if k is None:
            raise MatscanError("calibrate: grey-card photos must come from a rig with fixed lights")
        with torch.no_grad():
            model = render(
                torch.full((3, h, w), albedo),
                torch.zeros(3, h, w),
                torch.ones(1, h, w),
                n,
                grey.lights.select([i]),
                pts,
            )[0]
        photo = grey.linear([i])[0]
        where = _photo_name(grey, i)
        if colour:
            rgb = tuple(_grey_scale(photo[c : c + 1], model[c : c + 1], grey.saturated[i], k, where) for c in range(3))
            scales[str(k)] = rgb
            s = torch.tensor(rgb).view(3, 1, 1)
        else:
            s = scales[str(k)] = _grey_scale(photo, model, grey.saturated[i], k, where)
        if flat_fields:
            ratio = smooth((photo / (s * model).clamp_min(1e-4)).mean(0), flat_sigma_px)
            mean = float(ratio.mean().clamp_min(1e-12))
            # the flat field has mean 1, so the scale takes the ratio's mean: their product
            # stays the smoothed ratio itself
            if colour:
                scales[str(k)] = tuple(v * mean for v in scales[str(k)])
            else:
                scales[str(k)] *= mean
            flats[str(k)] = (ratio / mean)[None]
    return scales, flats


#: The total degree of the polynomial surface a flat field is first fitted with.
FLAT_DEGREE = 4


def smooth(x: Tensor, sigma_px: float, degree: int = FLAT_DEGREE) -> Tensor:
    """A smooth version of an (H, W) image: the least-squares polynomial surface of total
    ``degree`` in x and y, plus the rest Gaussian-blurred (``sigma_px``, edges mirrored).

    A flat field's brightness runs on past the photo's edge; blurring it directly
    bends it toward the inside there (by about its slope × 0.8 σ: mirrored edges) or
    mixes opposite edges (a periodic blur). The polynomial carries the slope and the
    curvature, so what is blurred is nearly flat and the edges keep their level.
    """
    h, w = x.shape[-2:]
    v, u = torch.meshgrid(
        torch.linspace(-1, 1, h, dtype=torch.float64), torch.linspace(-1, 1, w, dtype=torch.float64), indexing="ij"
    )
    terms = torch.stack([u**i * v**j for i in range(degree + 1) for j in range(degree + 1 - i)], -1)  # (H, W, T)
    step = max(1, int(math.sqrt(h * w / 65536)))  # at most about 256² samples for the fit
    a = terms[::step, ::step].reshape(-1, terms.shape[-1])
    coef = torch.linalg.lstsq(a, x[::step, ::step].reshape(-1, 1).double()).solution
    surface = (terms @ coef)[..., 0].to(x.dtype)
    rest = x - surface
    radius = min(int(math.ceil(3 * sigma_px)), h - 1, w - 1)
    if sigma_px <= 0 or radius < 1:
        return x
    t = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (t / sigma_px) ** 2)
    kernel = (kernel / kernel.sum()).to(x.dtype)
    y = F.pad(rest[None, None], (radius, radius, radius, radius), mode="reflect")
    y = F.conv2d(y, kernel.view(1, 1, 1, -1))
    return surface + F.conv2d(y, kernel.view(1, 1, -1, 1))[0, 0]


#: The grey-card photos are averaged over blocks to at most this many on each side for
#: the position fit: the irradiance of a light is smooth, and averaging lowers the noise.
POSITION_GRID = 64
#: A block enters the position fit when its mean is at least this share of the photo's
#: brightest block (dimmer ones are mostly quantisation noise in the logarithm).
POSITION_DARK = 0.02
#: The pull toward the rig file's places: this weight × Σ (offset / 5 mm)² beside the sum of
#: squared log residuals. Residuals of 8-bit photos averaged over blocks are about 0.002,
#: so it matters only where the photos leave a direction undetermined (on a simulated
#: dome24 at 256², LEDs ±5 mm off: 0.134 mm mean error with none, 0.139 with 1e-5).
POSITION_PRIOR = 1e-6
#: Fits: one plain, then two with Cauchy weights at 2.5 × the residuals' robust spread.
ROUNDS = 3


@dataclass(frozen=True)
class LightFit:
    """Near lights' positions fitted to grey-card photos (:func:`fit_light_positions`).

    Attributes:
        positions: per near light (its index as text) the fitted position, mm, in the rig's frame.
        moved_mm: per light, the distance from the rig file's position, mm.
        vignetting: (a, b): the shared falloff toward the corners the fit found,
            log V = a ρ² + b ρ⁴ with ρ the distance from the field's centre over half
            its width (the flat fields hold it, when written).
        residual: root mean square of the fit's log residual (0.01 ≈ 1%).
    """

    positions: dict[str, tuple[float, float, float]]
    moved_mm: dict[str, float]
    vignetting: tuple[float, float]
    residual: float


def _log_irradiance(pos: Tensor, aim: Tensor, exponent: Tensor, pts: Tensor) -> Tensor:
    """log of (1/d²) · lobe · cos θ for lights at pos (L, 3) aimed at aim (L, 3) at the
    points pts (P, 3) of the plane z = 0: (L, P); the constant R² and intensity left out."""
    lv = pos[:, None, :] - pts[None]
    d2 = (lv * lv).sum(-1)
    l_dir = lv / d2.sqrt()[..., None]
    axis = aim - pos
    axis = axis / axis.norm(dim=-1, keepdim=True)
    lobe = (-(l_dir * axis[:, None, :]).sum(-1)).clamp_min(1e-9).log() * exponent[:, None]
    return -d2.log() + lobe + l_dir[..., 2].clamp_min(1e-9).log()


def fit_light_positions(grey: Capture, grid: int = POSITION_GRID, iterations: int = 40) -> LightFit:
    """Each near light's position from its photo of a flat grey card (a Lambertian plane
    at z = 0), with the camera's vignetting shared by all photos.

    Under a point light at q the card images to ρ I (R/d)² lobe cos θ V(x) (design.md,
    image formation), whose shape across the field depends on q alone: where the
    brightest point falls and how fast the brightness falls away from it. The logarithm
    of the photos, averaged over blocks (``grid``), is fitted by Levenberg–Marquardt over
    every light's position and log-intensity and the two vignetting terms
    (log V = a ρ² + b ρ⁴); the card's albedo and the lights' intensities drop out. Each
    LED keeps the aim point the rig file gives it. Two reweighting rounds (Cauchy
    weights at 2.5 × the residuals' robust spread) discount a stain or a speck on the
    card. Directional lights are left out (they have no position).

    The card must be matte: a sheen brightens it toward each light's mirror point,
    which the fit takes for a light elsewhere. Simulated (dome24 at 128², LEDs ±5 mm off,
    8-bit): a card with a GGX sheen of F0 0.04 at roughness 1.0 is placed within 1.5 mm
    on average, at roughness 0.7 it moves the lights about 28 mm (:func:`check_light_fit`
    warns beyond ``MOVED_WARNING_MM``); a matte card, 0.4 mm.

    Raises:
        MatscanError: photos with per-image geometry, a light that lights too little of
            the card to place it.
    """
    h, w = grey.size
    pts = surface_points(grey.field_mm, (h, w), dtype=torch.float64).permute(2, 0, 1)[None]
    gh, gw = min(h, grid), min(w, grid)
    pts = F.adaptive_avg_pool2d(pts, (gh, gw))[0].permute(1, 2, 0).reshape(-1, 3)  # (P, 3)
    half = float(grey.field_mm[0]) / 2
    rho2 = (pts[:, 0] ** 2 + pts[:, 1] ** 2) / half**2  # (P,)
    chosen, photos, masks = [], [], []
    for i, k in enumerate(grey.light_indices):
        if k is None:
            raise MatscanError("calibrate: grey-card photos must come from a rig with fixed lights")
        if grey.rig.lights[k].directional:
            continue
        grey_photo = grey.linear([i])[0].double().mean(0)[None, None]  # (1, 1, H, W)
        block = F.adaptive_avg_pool2d(grey_photo, (gh, gw)).reshape(-1)
        sat = F.adaptive_max_pool2d(grey.saturated[i][None].float(), (gh, gw)).reshape(-1) > 0
        ok = ~sat & (block > POSITION_DARK * float(block.max()))
        if int(ok.sum()) < 16:
            raise MatscanError(f"{_photo_name(grey, i)}: light {k} lights too little of the grey card to place it")
        chosen.append((i, k))
        photos.append(block.clamp_min(1e-12).log())
        masks.append(ok)
    if not chosen:
        return LightFit({}, {}, (0.0, 0.0), 0.0)
    index = [i for i, _ in chosen]
    start = grey.lights.select(index).position.double()  # (L, 3)
    aim = torch.tensor([grey.rig.lights[k].aim_mm for _, k in chosen], dtype=torch.float64)
    exponent = grey.lights.select(index).exponent.double()
    logp = torch.stack(photos)  # (L, P)
    ok = torch.stack(masks)

    def residual(own: Tensor, vig: Tensor, logp_k: Tensor, start_k: Tensor, aim_k: Tensor, m_k: Tensor) -> Tensor:
        """One light's log residuals (P,) at its offset and log-intensity ``own`` (4,)
        and the vignetting ``vig`` (2,)."""
        model = _log_irradiance((start_k + own[:3])[None], aim_k[None], m_k[None], pts)[0]
        return logp_k - model - own[3] - vig[0] * rho2 - vig[1] * rho2**2

    data = (logp, start, aim, exponent)
    own = torch.zeros(len(chosen), 4, dtype=torch.float64)
    own[:, 3] = ((logp - _log_irradiance(start, aim, exponent, pts)) * ok).sum(1) / ok.sum(1)
    vig = torch.zeros(2, dtype=torch.float64)
    weights = ok.double()
    for _ in range(ROUNDS):
        own, vig = _levenberg_marquardt(residual, data, own, vig, weights, iterations)
        r = torch.vmap(residual, in_dims=(0, None, 0, 0, 0, 0))(own, vig, *data)
        spread = 1.4826 * float(r[ok].abs().median()) + 1e-6
        weights = ok / (1 + (r / (2.5 * spread)) ** 2)
    rms = float(((r**2 * ok).sum() / ok.sum()).sqrt())
    keys = [str(k) for _, k in chosen]
    pos = (start + own[:, :3]).tolist()
    moved = own[:, :3].norm(dim=-1).tolist()
    return LightFit(
        {k: (round(p[0], 3), round(p[1], 3), round(p[2], 3)) for k, p in zip(keys, pos, strict=True)},
        {k: round(d, 3) for k, d in zip(keys, moved, strict=True)},
        (round(float(vig[0]), 5), round(float(vig[1]), 5)),
        rms,
    )


def _levenberg_marquardt(residual, data, own: Tensor, shared: Tensor, weights: Tensor, iterations: int):
    """Minimise Σ weights · r² + POSITION_PRIOR · Σ (offset / 5 mm)² over every light's
    ``own`` (L, 4: offset mm, log-intensity) and the parameters all lights share (S,).

    Light k's residuals depend on its own four numbers and the shared ones, so the
    normal equations are assembled from per-light Jacobians into one (4L + S)² system."""
    n, m = own.shape[0], shared.shape[0]
    dims = (0, None) + (0,) * len(data)
    residuals = torch.vmap(residual, in_dims=dims)
    jacobians = torch.vmap(torch.func.jacfwd(residual, argnums=(0, 1)), in_dims=dims)
    prior = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=own.dtype) * POSITION_PRIOR / 25

    def cost(o: Tensor, v: Tensor) -> float:
        r = residuals(o, v, *data)
        return float((weights * r * r).sum() + (prior * o * o).sum())

    damping, current = 1e-3, cost(own, shared)
    for _ in range(iterations):
        r = residuals(own, shared, *data)  # (L, P)
        j_own, j_shared = jacobians(own, shared, *data)  # (L, P, 4), (L, P, S)
        wj_own, wj_shared = weights[..., None] * j_own, weights[..., None] * j_shared
        a = torch.zeros(4 * n + m, 4 * n + m, dtype=own.dtype)
        blocks = torch.einsum("lpi,lpj->lij", wj_own, j_own) + torch.diag(prior)  # (L, 4, 4)
        a[: 4 * n, : 4 * n] = torch.block_diag(*blocks)
        cross = torch.einsum("lpi,lpj->lij", wj_own, j_shared).reshape(4 * n, m)
        a[: 4 * n, 4 * n :] = cross
        a[4 * n :, : 4 * n] = cross.T
        a[4 * n :, 4 * n :] = torch.einsum("lpi,lpj->ij", wj_shared, j_shared)
        b_own = torch.einsum("lpi,lp->li", wj_own, r) + prior * own
        b = torch.cat([b_own.reshape(-1), torch.einsum("lpi,lp->i", wj_shared, r)])
        diag = a.diagonal().clamp_min(1e-12)
        while True:
            step = torch.linalg.solve(a + damping * torch.diag(diag), b)
            new_own, new_shared = own - step[: 4 * n].view(n, 4), shared - step[4 * n :]
            new = cost(new_own, new_shared)
            if new < current:
                done = current - new < 1e-10 * current
                own, shared, current, damping = new_own, new_shared, new, damping / 3
                break
            damping *= 4
            if damping > 1e8:
                return own, shared
        if done:
            break
    return own, shared


#: A fitted light this far from the rig file's place (mm), or a fit whose log residual
#: is above FIT_RESIDUAL, is worth a warning: a wrong rig file, or a card that is not a
#: flat matte grey filling the field.
MOVED_WARNING_MM = 20.0
FIT_RESIDUAL = 0.03


def check_light_fit(fit: LightFit, source: str = "calibration") -> list[str]:
    """One-line warnings about fitted light positions (:func:`fit_light_positions`)."""
    warnings = []
    far = sorted((int(k) for k, d in fit.moved_mm.items() if d > MOVED_WARNING_MM))
    if far:
        worst = max(fit.moved_mm.values())
        warnings.append(
            f"{source}: {_light_list(far)} moved more than {MOVED_WARNING_MM:g} mm from the rig file "
            f"(up to {worst:.1f} mm); check the rig file, and that the grey card is matte and lies flat "
            "at the sample plane"
        )
    if fit.residual > FIT_RESIDUAL:
        warnings.append(
            f"{source}: the grey card departs from the lights' model by {100 * fit.residual:.1f}% (rms); "
            "check that it is matte, clean and fills the field"
        )
    return warnings


def with_light_positions(capture: Capture, positions: Mapping[int, Sequence[float]]) -> Capture:
    """The capture with the named rig lights at other positions (mm, the rig's frame),
    each LED still aimed at the point the rig file aims it at; other photos unchanged."""
    lights = capture.lights
    pos, axis = lights.position.clone(), lights.axis.clone()
    for i, k in enumerate(capture.light_indices):
        if k is None or k not in positions:
            continue
        p = torch.tensor([float(v) for v in positions[k]], dtype=pos.dtype)
        aim = torch.tensor(capture.rig.lights[k].aim_mm, dtype=pos.dtype)
        pos[i] = p
        axis[i] = (aim - p) / (aim - p).norm()
    return replace(capture, lights=replace(lights, position=pos, axis=axis))


def write_calibration(
    path: Path,
    matrix: Tensor | None,
    scales: Mapping[str, float | Sequence[float]] | None,
    flats: dict[str, Tensor] | None = None,
    positions: Mapping[str, Sequence[float]] | None = None,
    exposure: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """Write ``calibration.json`` (and flat-field EXRs beside it); ``exposure`` holds
    ``exposure_s`` and ``led_level``, the grey card's, where they are known."""
    from matscan.imagefile import write_image

    doc: dict[str, Any] = {"format": CALIBRATION_FORMAT, "grey_albedo": GREY_CARD}
    if matrix is not None:
        doc["colour_matrix"] = [[round(float(v), 6) for v in row] for row in matrix]
    if scales:
        doc["light_scales"] = {
            k: significant(v) if isinstance(v, (int, float)) else [significant(c) for c in v] for k, v in scales.items()
        }
    if positions:
        doc["light_positions_mm"] = {k: [round(float(v), 3) for v in p] for k, p in positions.items()}
    if scales and exposure and "exposure_s" in exposure:
        doc["exposure_s"] = float(exposure["exposure_s"])
        doc["led_level"] = float(exposure.get("led_level", 1.0))
    elif scales and exposure and "led_level" in exposure:  # a camera that set its own exposure
        doc["led_level"] = float(exposure["led_level"])
    if flats:
        doc["flat_fields"] = {}
        for k, t in flats.items():
            file = f"flat_{int(k):02d}.exr"
            write_image(path.parent / file, t.permute(1, 2, 0).numpy(), bits=32)
            doc["flat_fields"][k] = file
    from matscan.atomic import write_text
    from matscan.jsonfile import dumps

    write_text(path, dumps(doc, str(path)))
    return doc


@dataclass(frozen=True)
class Calibration:
    """What :func:`calibrate` wrote and measured.

    Attributes:
        path: the ``calibration.json`` written (flat fields, if any, lie beside it).
        colour_matrix: (3, 3) linear camera RGB → linear sRGB, from the chart photo; else None.
        chart_error: mean absolute error of the chart's 24 patches after the matrix
            (linear sRGB, [0, 1] scale); else None.
        light_scales: per rig light (its index as text) the RGB scale: photo = scale × model,
            per channel; empty without a grey card.
        flat_fields: per rig light, (1, H, W) of mean 1; empty unless asked for.
        warnings: one line each, saying what to check (:func:`check_chart`, :func:`check_scales`).
        light_fit: the near lights' fitted positions (:func:`fit_light_positions`), when asked for.
        exposure_s: the grey card's exposure (s), where its capture recorded one; the scales
            hold at that exposure and ``led_level``.
        led_level: the LEDs' level (0-1) of the grey card's photos, where recorded.
    """

    path: Path
    colour_matrix: Tensor | None
    chart_error: float | None
    light_scales: dict[str, tuple[float, float, float]]
    flat_fields: dict[str, Tensor]
    warnings: tuple[str, ...]
    light_fit: LightFit | None = None
    exposure_s: float | None = None
    led_level: float | None = None


CHART_ENCODINGS = ("srgb", "linear")


def calibrate(
    out: str | Path,
    grey: str | Path | None = None,
    chart: str | Path | None = None,
    corners: Sequence[Sequence[float]] | None = None,
    chart_encoding: str = "srgb",
    flat_fields: bool = False,
    overwrite: bool = False,
    positions: bool = False,
) -> Calibration:
    """Write ``calibration.json`` from a ColorChecker photo and/or a grey-card capture
    (``matscan calibrate``).

    Args:
        out: the calibration file to write (put it in the capture folder and name it
            in ``capture.json``); checked and locked before any work
            (:func:`matscan.outputs.claim_output`), never one of the inputs.
        grey: capture folder of an 18 % grey card under each light (``"@sample"``
            names the built-in sample capture): per-light RGB scales (:func:`light_scales`;
            with a chart, measured on the colour-corrected photos).
        chart: photo of a ColorChecker Classic: the colour matrix (:func:`colour_matrix`).
        corners: the outer corners of the chart's grid of cells in pixels (x, y),
            top-left, top-right, bottom-right, bottom-left (:func:`sample_patches`);
            found in the photo by default (:func:`detect_chart`).
        chart_encoding: ``"srgb"`` or ``"linear"``, the transfer function of an integer
            chart photo (a float photo is linear).
        flat_fields: also write per-light flat fields (``flat_NN.exr`` beside ``out``).
        overwrite: replace an existing calibration file (and its flat fields).
        positions: also fit every near light's position to its grey-card photo
            (:func:`fit_light_positions`) and write them as ``light_positions_mm``; the
            scales and flat fields are then measured against the lights at those places.

    Returns:
        :class:`Calibration`: what was written and measured, with warnings.

    Raises:
        MatscanError: neither ``grey`` nor ``chart`` given, an existing ``out`` without
            ``overwrite``, unreadable inputs, corners off the photo, a light that does
            not light the card or saturates it everywhere.
    """
    from matscan.outputs import capture_inputs, check_destination, claim_output
    from matscan.samples import capture_folder

    if grey is None and chart is None:
        raise MatscanError("calibrate: give grey (a capture of a grey card under each light) and/or chart (a photo)")
    if positions and grey is None:
        raise MatscanError("calibrate: positions are fitted to grey-card photos; give grey")
    if chart_encoding not in CHART_ENCODINGS:
        raise MatscanError(f"chart_encoding: {chart_encoding!r} is not one of {', '.join(CHART_ENCODINGS)}")
    grey = capture_folder(grey) if grey is not None else None
    inputs = ([Path(chart)] if chart is not None else []) + (capture_inputs(grey) if grey is not None else [])
    with claim_output(out, "calibrate", inputs, kind="file", overwrite=overwrite, suffixes=(".json",)) as claim:
        if flat_fields and grey is not None:  # the flat-field files beside it are outputs too
            for flat in sorted(claim.path.parent.glob("flat_*.exr")):
                check_destination(flat, inputs, "file", overwrite)
        return _calibrate(claim.path, grey, chart, corners, chart_encoding, flat_fields, positions)


def _calibrate(
    out: Path,
    grey: Path | None,
    chart: str | Path | None,
    corners: Sequence[Sequence[float]] | None,
    chart_encoding: str,
    flat_fields: bool,
    positions: bool = False,
) -> Calibration:
    """:func:`calibrate` once its output is claimed: measure, then write ``out``."""
    from matscan.capture import load_capture
    from matscan.imagefile import read_image

    matrix = residual = None
    scales: dict[str, tuple[float, float, float]] = {}
    flats: dict[str, Tensor] = {}
    warnings: list[str] = []
    if chart is not None:
        img = read_image(chart)
        photo = torch.from_numpy(img.pixels[:, :, :3]).permute(2, 0, 1).float()
        if img.kind == "int" and chart_encoding == "srgb":
            photo = srgb_to_linear(photo)
        if corners is None:
            corners = detect_chart(photo, str(chart))
        measured = sample_patches(photo, corners)
        warnings += check_chart(measured)
        matrix = colour_matrix(measured, colorchecker_linear())
        residual = float((measured @ matrix.T - colorchecker_linear()).abs().mean())
    fit = None
    exposure: dict[str, float] = {}
    if grey is not None:
        card = load_capture(grey)
        exposure = {k: card.meta[k] for k in ("exposure_s", "led_level") if k in card.meta}
        if matrix is not None:  # the scales divide photos already colour-corrected (apply_calibration)
            n = len(card.files)
            card = replace(card, correction=Correction(matrix, torch.ones(n, 3), (None,) * n))
        if positions:
            fit = fit_light_positions(card)
            card = with_light_positions(card, {int(k): p for k, p in fit.positions.items()})
            warnings += check_light_fit(fit, str(out))
        scales, flats = light_scales(card, flat_fields=flat_fields, colour=True)
        for k, rgb in scales.items():  # what apply_calibration refuses to read, refused here
            wrong = [c for c in rgb if not SCALE_LIMITS[0] <= c <= SCALE_LIMITS[1]]
            if wrong:
                raise input_error(
                    card.folder or grey,
                    f"light {k}'s scale {wrong[0]:.4g} is outside {SCALE_LIMITS[0]:g} to {SCALE_LIMITS[1]:g}: "
                    "the grey card's photos are not in the rig's units (their encoding, or an exposure far off?)",
                )
        warnings += check_scales({k: sum(v) / 3 for k, v in scales.items()}, str(out))
    write_calibration(out, matrix, scales, flats, fit.positions if fit is not None else None, exposure)
    return Calibration(
        out,
        matrix,
        residual,
        scales,
        flats,
        tuple(warnings),
        fit,
        exposure.get("exposure_s"),
        exposure.get("led_level"),
    )


@dataclass(frozen=True)
class Merged:
    """What :func:`merge_calibrations` made of several calibrations of one dome.

    Attributes:
        document: the merged calibration object (write it, or name it in a capture).
        files: how many calibrations went in.
        positions: how many of them gave each light's position, by light key.
        position_spread_mm: the RMS distance of the calibrations' positions from their
            mean (over every light two or more placed; None where none was): how far
            apart the captures put the lights. The mean's own error is about this over
            the square root of the count, where their errors are independent.
        scale_spread: the same for the scales' logarithms (RMS, a share).
        left_out: the files left out as astray (``ASTRAY_FACTOR``), by name, with their
            places' RMS distance (mm) from the files' per-light median places.
    """

    document: dict[str, Any]
    files: int
    positions: dict[str, int]
    position_spread_mm: float | None
    scale_spread: float | None
    left_out: dict[str, float]


def merge_calibrations(documents: Sequence[Mapping[str, Any]], names: Sequence[str]) -> Merged:
    """One calibration from several calibrations of the same dome (``calibrate --merge``):
    each light's position the mean of the positions the calibrations give it, each
    light's RGB scale their geometric mean; the colour matrix, grey albedo and flat fields
    must be the same in all (the same base calibration, as self-calibrations of captures
    sharing one calibration file write them; flat-field names compared as given). Files
    that record the exposure and LED level their scales hold at (every one or none) have
    their scales brought to the first file's by the ratio of exposure × level, and the
    result records the first's.

    Self-calibrations of captures of different samples under one dome (each capture's
    ``self_calibration.json``) place its lights with errors of their own; their mean
    places them closer than most do alone (docs/rti.md, "A dome calibrated once"). A file
    whose places lie far from the others' (``ASTRAY_FACTOR``: a capture whose fit went
    astray) is left out, places and scales, and named in ``left_out``.
    ``names`` name the documents in errors (the files they were read from)."""
    if len(documents) != len(names) or not documents:
        raise MatscanError("calibrate --merge: give one or more calibration files")
    per_file: list[tuple[dict[str, tuple[float, ...]], dict[str, tuple[float, ...]]]] = []  # scales, places
    base: dict[str, Any] | None = None
    reference: tuple[float, float] | None = None
    first_level = None
    for doc, name in zip(documents, names, strict=True):
        file_scales: dict[str, tuple[float, ...]] = {}
        file_places: dict[str, tuple[float, ...]] = {}
        per_file.append((file_scales, file_places))
        check_object(doc, name, _CALIBRATION_KEYS)
        if doc["format"] != CALIBRATION_FORMAT:
            raise MatscanError(f"{name}: format: must be {CALIBRATION_FORMAT!r}, got {short_repr(doc['format'])}")
        exposure = _exposure(doc, f"{name}: ")
        level = doc.get("led_level") if exposure is None else None  # a level alone (the camera set the exposure)
        own = ("light_scales", "light_positions_mm", "exposure_s", "led_level")
        rest = {k: v for k, v in doc.items() if k not in own}
        if base is None:
            base, first, reference, first_level = rest, name, exposure, level
        elif (exposure is None) != (reference is None):
            which, other = (name, first) if exposure is None else (first, name)
            raise MatscanError(
                f"{which}: records no exposure where {other} does, so their scales cannot be brought "
                "to one exposure; merge calibrations that all record it"
            )
        elif exposure is None and level != first_level:

            def said(value: Any) -> str:
                return "no LED level" if value is None else f"LED level {value:g}"

            raise MatscanError(
                f"{name}: records {said(level)} where {first} records {said(first_level)}, and neither an "
                "exposure, so their scales cannot be brought to one level; merge calibrations made at one level"
            )
        elif rest != base:
            key = next(k for k in sorted(set(rest) | set(base)) if rest.get(k) != base.get(k))
            raise MatscanError(
                f"{name}: {key} differs from {first}'s; merge only calibrations made on one base calibration"
            )
        for k, v in check_object(doc.get("light_scales", {}), f"{name}: light_scales").items():
            field = f"{name}: light_scales[{short_repr(k)}]"
            if not _LIGHT_KEY.fullmatch(k):
                raise MatscanError(f"{field}: {short_repr(k)} is not a light index")
            rgb = check_vector(v, 3, field) if isinstance(v, (list, tuple)) else (check_number(v, field),) * 3
            for c in rgb:
                check_number(c, field, *SCALE_LIMITS, positive=True)
            if exposure is not None and reference is not None:  # as if taken at the first file's
                rgb = tuple(c * reference[0] * reference[1] / (exposure[0] * exposure[1]) for c in rgb)
            file_scales[k] = rgb
        for k, v in check_object(doc.get("light_positions_mm", {}), f"{name}: light_positions_mm").items():
            field = f"{name}: light_positions_mm[{short_repr(k)}]"
            if not _LIGHT_KEY.fullmatch(k):
                raise MatscanError(f"{field}: {short_repr(k)} is not a light index")
            xyz = check_vector(v, 3, field)
            if xyz[2] <= 0:
                raise MatscanError(f"{field}: light {k} is at z = {xyz[2]:g} mm, not above the sample plane")
            file_places[k] = xyz
    left = _astray(per_file, names)
    positions: dict[str, list[tuple[float, ...]]] = {}
    scales: dict[str, list[tuple[float, ...]]] = {}
    for (file_scales, file_places), name in zip(per_file, names, strict=True):
        if name in left:
            continue
        for k, v in file_scales.items():
            scales.setdefault(k, []).append(v)
        for k, v in file_places.items():
            positions.setdefault(k, []).append(v)
    merged = dict(base or {})
    if reference is not None:
        merged["exposure_s"], merged["led_level"] = reference
    elif first_level is not None:
        merged["led_level"] = first_level

    def order(d: dict[str, Any]) -> dict[str, Any]:
        return dict(sorted(d.items(), key=lambda kv: int(kv[0])))

    logs = {k: torch.tensor(v, dtype=torch.float64).log() for k, v in scales.items()}
    pts = {k: torch.tensor(v, dtype=torch.float64) for k, v in positions.items()}
    if logs:
        merged["light_scales"] = order({k: [significant(c) for c in t.mean(0).exp()] for k, t in logs.items()})
    if pts:
        kept = [places for (_, places), name in zip(per_file, names, strict=True) if name not in left and places]
        means = {k: t.mean(0) for k, t in pts.items()}
        if MERGE_WEIGHTED:
            means.update(_weighted_places(kept) or {})
        merged["light_positions_mm"] = order({k: [round(float(c), 3) for c in t] for k, t in means.items()})

    def spread(groups: dict[str, Tensor]) -> float | None:
        """RMS over the lights given twice or more of each value's distance from its light's mean."""
        devs = [(t - t.mean(0)).square().sum(1) for t in groups.values() if len(t) > 1]
        return float(torch.cat(devs).mean().sqrt()) if devs else None

    log_spread = spread(logs)
    return Merged(
        merged,
        len(documents) - len(left),
        {k: len(v) for k, v in order(positions).items()},
        spread(pts),
        log_spread / math.sqrt(3) if log_spread is not None else None,  # per channel
        left,
    )


#: ``merge_calibrations`` leaves out a file whose places lie more than this many times the
#: files' median distance from the per-light median places, and more than ``ASTRAY_MM``
#: (RMS over the lights, mm), among three files or more: on a simulated dome one capture's
#: fit (a leather's) put the lights 8.5 mm off where three others put them 0.5-1.3 mm off,
#: and the mean of the four came out 2.2 mm off (docs/rti.md, "A dome calibrated once").
ASTRAY_FACTOR = 3.0
ASTRAY_MM = 1.0


#: Merge the places weighted (:func:`_weighted_places`) instead of by their plain mean.
#: Off: on 24 simulated domes it placed the lights 0.45 mm off on average where the mean
#: is 0.46, and in its pilot a brick's intensities no longer confirmed the weighted places,
#: whose fit then went 1.26 mm astray (docs/rti.md, "Half the merge's error is the dome's
#: scale and shift").
MERGE_WEIGHTED = False


def _common_moves(places: Tensor) -> Tensor:
    """An orthonormal basis (3L, 4) of the moves of L lights together: one shift (3
    numbers) and the dome's scale (each light along its own direction from the origin)."""
    d = places / places.norm(dim=1, keepdim=True)
    moves = [torch.eye(3, dtype=places.dtype)[j].expand_as(places).reshape(-1) for j in range(3)]
    return torch.linalg.qr(torch.stack([*moves, d.reshape(-1)], 1))[0]


def _weighted_places(groups: list[dict[str, tuple[float, ...]]], rounds: int = 10) -> dict[str, Tensor] | None:
    """The places of the lights every file gives (three files or more), each file weighted
    by how closely its places follow the others' once its own shift and scale
    (:func:`_common_moves`) are taken out: 1 / the mean square of its aligned places'
    distance from the weighted mean of the others', iterated ``rounds`` times. Captures
    of different samples place the lights with errors of their own, and a glossy one's
    (a simulated plastic's, a leather's) are both a scale (0.5-1.2 mm too far out) and
    light by light (0.7 mm against a paper's 0.4). The result is then shifted and scaled
    to the plain mean's, which is what the files agree on for the dome as a whole."""
    keys = sorted(set.intersection(*(set(g) for g in groups)), key=int) if groups else []
    if len(groups) < 3 or len(keys) < 5:
        return None
    p = torch.stack([torch.tensor([g[k] for k in keys], dtype=torch.float64) for g in groups])
    mean = p.mean(0)
    centre, w = mean, torch.ones(len(p), dtype=torch.float64)
    for _ in range(rounds):
        b = _common_moves(centre)
        off = (p - centre).reshape(len(p), -1)
        aligned = centre + (off - off @ b @ b.T).reshape(p.shape)  # each file's shift and scale taken out
        spread = []
        for k in range(len(p)):
            o = torch.arange(len(p)) != k
            ref = (w[o, None, None] * aligned[o]).sum(0) / w[o].sum()
            spread.append((aligned[k] - ref).square().mean())
        w = 1 / torch.stack(spread).clamp_min(1e-12)
        centre = (w[:, None, None] * aligned).sum(0) / w.sum()
    b = _common_moves(centre)
    centre = centre + (b @ (b.T @ (mean - centre).reshape(-1))).reshape(-1, 3)
    return dict(zip(keys, centre, strict=True))


def _astray(per_file, names: Sequence[str]) -> dict[str, float]:
    """The files whose places lie astray (``ASTRAY_FACTOR``, ``ASTRAY_MM``): name → their
    RMS distance (mm) from the per-light median of all the files' places."""
    placed = [places for _, places in per_file]
    keys = [k for k in set().union(*placed) if sum(k in p for p in placed) >= 3]
    if len([p for p in placed if p]) < 3 or not keys:
        return {}
    median = {k: torch.tensor([p[k] for p in placed if k in p], dtype=torch.float64).quantile(0.5, 0) for k in keys}
    dist = {}
    for places, name in zip(placed, names, strict=True):
        mine = [k for k in keys if k in places]
        if mine:
            d = torch.stack([torch.tensor(places[k], dtype=torch.float64) - median[k] for k in mine])
            dist[name] = float(d.square().sum(1).mean().sqrt())
    typical = float(torch.tensor(list(dist.values()), dtype=torch.float64).quantile(0.5))  # two middles: their mean
    return {n: round(d, 3) for n, d in dist.items() if d > ASTRAY_FACTOR * typical and d > ASTRAY_MM}


def merge(out: str | Path, files: Sequence[str | Path], overwrite: bool = False) -> Merged:
    """``matscan calibrate --merge FILES --out FILE``: read each calibration file, merge
    them (:func:`merge_calibrations`) and write the result to ``out``, checked and locked
    first and written atomically, never over one of the files. Flat fields named by
    relative paths (beside the first file, as the files must name the same ones) are
    named again relative to ``out``'s folder, so the merge finds them wherever it is
    written; self-calibrations name them by absolute path."""
    from matscan.atomic import write_text
    from matscan.jsonfile import dumps, read_json
    from matscan.outputs import calibration_inputs, claim_output

    paths = [Path(f) for f in files]
    inputs = [p for path in paths for p in calibration_inputs(path)]
    with claim_output(out, "calibrate", inputs, kind="file", overwrite=overwrite, suffixes=(".json",)) as claim:
        documents = [read_json(p) for p in paths]
        result = merge_calibrations(documents, [str(p) for p in paths])
        flats = result.document.get("flat_fields")
        if isinstance(flats, dict):
            base = paths[0].resolve().parent
            for key, name in flats.items():
                if isinstance(name, str) and not Path(name).is_absolute():
                    flats[key] = os.path.relpath(base / name, claim.path.parent)
        write_text(claim.path, dumps(result.document, str(claim.path)))
    return result


_CALIBRATION_KEYS = {
    "format": True,
    "colour_matrix": False,
    "light_scales": False,
    "flat_fields": False,
    "grey_albedo": False,
    "light_positions_mm": False,
    "exposure_s": False,
    "led_level": False,
}


def _exposure(doc: Mapping[str, Any], prefix: str) -> tuple[float, float] | None:
    """A calibration's ``exposure_s`` and ``led_level`` (1 where absent), checked; None
    where it records no exposure."""
    if "exposure_s" not in doc:  # a level alone: a card whose camera set its own exposure
        if "led_level" in doc:
            check_number(doc["led_level"], f"{prefix}led_level", 0.0, 1.0, positive=True)
        return None
    seconds = check_number(doc["exposure_s"], f"{prefix}exposure_s", *EXPOSURE_LIMITS, positive=True)
    level = check_number(doc.get("led_level", 1.0), f"{prefix}led_level", 0.0, 1.0, positive=True)
    return seconds, level


def exposure_ratio(capture: Capture) -> tuple[float, list[str]]:
    """How much brighter the capture's photos are than the grey card's that its
    calibration's scales were measured on: the ratio of exposure × LED level, the
    capture's (``capture.meta``, from ``acquisition``) over the calibration's; 1 where
    either does not record an exposure, with a one-line warning saying so where the
    calibration has scales. Exposure and LED level (the PWM duty at 20 kHz, averaged
    over the exposure) scale a photo linearly."""
    cal = capture.calibration or {}
    _, prefix, name = _where(capture)
    recorded = _exposure(cal, prefix)
    if "light_scales" not in cal:
        return 1.0, []
    seconds = capture.meta.get("exposure_s")
    if recorded is None and seconds is None:
        card, here = cal.get("led_level"), capture.meta.get("led_level")
        if card is not None and here is not None and abs(card - here) > 1e-9:
            return 1.0, [
                f"{name}'s grey card was lit at LED level {card:g} and the capture at {here:g}, and neither "
                "records its exposure (the camera set it): the photos are taken as made at the card's; "
                "calibrate at the capture's level"
            ]
        return 1.0, []
    if recorded is None and "led_level" in cal:  # the card's camera set its own exposure
        return 1.0, [
            f"{name}'s grey card was taken at an exposure its camera set (LED level {cal['led_level']:g}), so the "
            f"photos (at {seconds:.4g} s, LED level {capture.meta.get('led_level', 1.0):g}) are taken as made at "
            "it; calibrate with a card taken by the capture's camera to have the ratio applied"
        ]
    if recorded is None:
        return 1.0, [
            f"{name} does not record its grey card's exposure, so the photos (at {seconds:.4g} s) are "
            "taken as made at it; calibrate again from the grey card's capture to have the ratio applied"
        ]
    if seconds is None:
        return 1.0, [
            f"{name}'s scales were measured at {recorded[0]:.4g} s (LED level {recorded[1]:g}); the capture "
            "records no exposure, so its photos are taken as made at that exposure and level"
        ]
    return seconds * capture.meta.get("led_level", 1.0) / (recorded[0] * recorded[1]), []


#: The range a flat field's median must lie in: it is a gain of mean 1 (vignetting and
#: LED falloff across the field stay well within it).
FLAT_MEDIAN = (0.25, 4.0)
#: The largest magnitude of a colour matrix entry (real ones are within ±3).
MAX_MATRIX_ENTRY = 1e3
_LIGHT_KEY = re.compile(r"0|[1-9][0-9]{0,8}")


def _where(capture: Capture) -> tuple[str, str, str]:
    """How messages name the calibration (``place``), the start of a field's name
    (``prefix``: ``place`` then the field follows), and how warnings name it."""
    if capture.calibration_file is not None:
        place = str(capture.calibration_file)
        return place, f"{place}: ", capture.calibration_file.name
    if capture.folder is not None:
        place = f"{capture.folder / 'capture.json'}: calibration"
        return place, f"{place}.", "capture.json's calibration"
    return "calibration", "calibration.", "the calibration"


def _light_keyed(value: Any, where: str, rig: Rig | None) -> dict[int, Any]:
    """An object keyed by light indices of ``rig`` (``"0"``, ``"17"``), as {index: value};
    with no rig, keyed by light indices of any rig."""
    out = {}
    for key, item in check_object(value, where).items():
        if not _LIGHT_KEY.fullmatch(key):
            raise MatscanError(f"{where}: key {short_repr(key)} is not a light index (0, 1, 2, …)")
        if rig is not None and int(key) >= len(rig.lights):
            raise MatscanError(
                f"{where}: key {short_repr(key)} is not a light of rig {rig.name!r} (0 to {len(rig.lights) - 1})"
            )
        out[int(key)] = item
    return out


def _colour_matrix(value: Any, where: str) -> Tensor:
    """The 3 × 3 colour matrix, every entry finite and within ±``MAX_MATRIX_ENTRY``."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise MatscanError(f"{where}: must be 3 × 3 (three rows of three numbers), got {short_repr(value)}")
    rows = []
    for i, row in enumerate(value):
        if not isinstance(row, (list, tuple)) or len(row) != 3:
            raise MatscanError(f"{where}: must be 3 × 3 (row {i} is {short_repr(row)})")
        rows.append(check_vector(row, 3, f"{where}[{i}]", -MAX_MATRIX_ENTRY, MAX_MATRIX_ENTRY))
    return torch.tensor(rows, dtype=torch.float32)


def _scales(value: Any, where: str, rig: Rig | None) -> dict[int, tuple[float, float, float]]:
    """Per-light scales, each one number or an RGB triple (self-calibration writes
    those): finite, positive, within ``SCALE_LIMITS``; returned as RGB triples."""
    scales = {}
    for k, s in _light_keyed(value, where, rig).items():
        field = f"{where}['{k}']"
        values = check_vector(s, 3, field) if isinstance(s, (list, tuple)) else (check_number(s, field),) * 3
        for v in values:
            if v <= 0:
                raise MatscanError(
                    f"{field}: light {k} has scale {v:g}; a scale must be positive (photo = scale × model): recalibrate"
                )
            check_number(v, field, *SCALE_LIMITS)
        scales[k] = (values[0], values[1], values[2])
    return scales


def _positions(value: Any, where: str, rig: Rig | None) -> dict[int, tuple[float, float, float]]:
    """Per-light positions (mm): three finite numbers each, above the sample plane, for
    near lights only (of ``rig``, where given)."""
    out = {}
    for k, p in _light_keyed(value, where, rig).items():
        field = f"{where}['{k}']"
        if rig is not None and rig.lights[k].directional:
            raise MatscanError(f"{field}: light {k} is directional in rig {rig.name!r}; it has no position")
        x, y, z = check_vector(p, 3, field)
        if not z > 0:
            raise MatscanError(f"{field}: light {k} would be at z = {z:g} mm, not above the sample plane (z > 0)")
        out[k] = (x, y, z)
    return out


def _flat_field(path: Path, size: tuple[int, int] | None) -> Tensor:
    """A flat field (1 or 3, H, W) read from ``path``: finite, of median near 1, and
    the photos' ``size`` (where given)."""
    from matscan.imagefile import read_image

    px = read_image(path).pixels
    if px.shape[2] not in (1, 3):
        raise input_error(path, f"a flat field has 1 or 3 channels, this one {px.shape[2]}")
    flat = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).float()
    if size is not None and tuple(flat.shape[-2:]) != size:
        raise input_error(
            path, f"flat field is {flat.shape[-1]}×{flat.shape[-2]} pixels but the photos are {size[1]}×{size[0]}"
        )
    if not torch.isfinite(flat).all():
        raise input_error(path, "flat field holds NaN or infinite values")
    if float(flat.min()) < 0:
        raise input_error(path, f"flat field holds negative values (down to {float(flat.min()):.4g})")
    # A flat field is a relative gain of mean 1 (light_scales writes it so); the photos
    # are divided by it, so one far from 1 (all zero, a raw white-card photo) would
    # scale the light it belongs to many times over, silently.
    median = float(flat.median())
    if not FLAT_MEDIAN[0] <= median <= FLAT_MEDIAN[1]:
        raise input_error(
            path,
            f"flat field's median is {median:.4g}; a flat field is a relative gain of mean 1 "
            f"(within {FLAT_MEDIAN[0]:g} to {FLAT_MEDIAN[1]:g}): divide it by its mean, or write it with "
            "calibrate --flat-fields",
        )
    return flat.clamp_min(1e-3)


def _flat_files(value: Any, where: str, capture: Capture) -> dict[int, Path]:
    """Per-light flat-field files (beside the calibration file, or in the capture folder)."""
    base = capture.calibration_file.parent if capture.calibration_file is not None else capture.folder
    files = {}
    for k, name in _light_keyed(value, where, capture.rig).items():
        name = check_file_name(name, f"{where}['{k}']")
        if base is None:
            raise MatscanError(f"{where}['{k}']: a flat-field file needs a capture folder to be found in")
        if not (base / name).is_file():
            raise MatscanError(f"{where}['{k}']: no such file {short_repr(str(base / name))}")
        files[k] = base / name
    return files


def _coverage_warning(scales: dict[int, Any], capture: Capture, name: str) -> list[str]:
    """A warning naming the capture's lights that have no scale."""
    missing = sorted({k for k in capture.light_indices if k is not None and k not in scales})
    if not missing:
        return []
    return [
        f"{_light_list(missing)} no scale in {name}; they are used uncalibrated — "
        "recalibrate with a grey card under every light"
    ]


def _light_list(indices: list[int]) -> str:
    """``lights 0, 6..23 have`` / ``light 4 has`` for sorted indices."""
    runs: list[list[int]] = []
    for k in indices:
        if runs and k == runs[-1][-1] + 1:
            runs[-1].append(k)
        else:
            runs.append([k])
    text = ", ".join(f"{r[0]}..{r[-1]}" if len(r) > 2 else ", ".join(map(str, r)) for r in runs)
    return f"light {text} has" if len(indices) == 1 else f"lights {text} have"


def _checked_fields(
    cal: Any, place: str, prefix: str, rig: Rig | None
) -> tuple[Tensor | None, dict[int, tuple[float, float, float]], dict[int, tuple[float, float, float]]]:
    """A calibration's fields checked (keys, format, grey albedo, exposure), and its colour
    matrix, scales and light positions read; light keys against ``rig`` where given."""
    check_object(cal, place, _CALIBRATION_KEYS)
    if cal["format"] != CALIBRATION_FORMAT:
        raise MatscanError(f"{prefix}format: must be {CALIBRATION_FORMAT!r}, got {short_repr(cal['format'])}")
    if "grey_albedo" in cal:
        check_number(cal["grey_albedo"], f"{prefix}grey_albedo", 0.0, 1.0, positive=True)
    _exposure(cal, prefix)
    matrix = _colour_matrix(cal["colour_matrix"], f"{prefix}colour_matrix") if "colour_matrix" in cal else None
    scales = _scales(cal["light_scales"], f"{prefix}light_scales", rig) if "light_scales" in cal else {}
    moved = (
        _positions(cal["light_positions_mm"], f"{prefix}light_positions_mm", rig) if "light_positions_mm" in cal else {}
    )
    return matrix, scales, moved


def check_calibration_file(path: str | Path) -> None:
    """Check a calibration file as far as it can be without a capture: its fields as
    :func:`apply_calibration` checks them (light indices of any rig), and its flat
    fields (beside it) readable and of median near 1. What needs the capture (its rig's
    light count, the photos' size) is checked when it is applied. Errors name the file
    in one line: ``matscan batch --calibration`` checks its file so before any capture."""
    from matscan.jsonfile import read_json

    path = Path(path)
    cal = read_json(path)
    _checked_fields(cal, str(path), f"{path}: ", None)
    for k, file in _light_keyed(cal.get("flat_fields", {}), f"{path}: flat_fields", None).items():
        file = check_file_name(file, f"{path}: flat_fields['{k}']")
        if not (path.parent / file).is_file():
            raise MatscanError(f"{path}: flat_fields['{k}']: no such file {short_repr(str(path.parent / file))}")
        _flat_field(path.parent / file, None)


def apply_calibration(capture: Capture) -> Capture:
    """The capture with its calibration applied (colour matrix, then per-light scale
    and flat field, and the lights at their calibrated positions); unchanged when it
    has none.

    Every field is checked first (errors name the calibration file or
    ``capture.json: calibration`` and the field): ``colour_matrix`` 3 × 3 finite;
    ``light_scales`` keyed by lights of the rig, each finite and positive;
    ``flat_fields`` keyed by lights, naming readable files of the photos' size;
    ``light_positions_mm`` keyed by near lights, each three finite numbers with z > 0.
    Plausible-but-wrong calibrations (scales for only some of the capture's lights,
    implausible scales) are appended as one-line warnings to the result's
    ``meta["warnings"]``.
    """
    cal = capture.calibration
    if cal is None:
        return capture
    place, prefix, name = _where(capture)
    matrix, scales, moved = _checked_fields(cal, place, prefix, capture.rig)
    flats = _flat_files(cal["flat_fields"], f"{prefix}flat_fields", capture) if "flat_fields" in cal else {}
    if moved:
        capture = with_light_positions(capture, moved)
    ratio, warnings = exposure_ratio(capture)
    warnings += check_scales({str(k): sum(s) / 3 for k, s in scales.items()}, name)
    if "light_scales" in cal:
        warnings += _coverage_warning(scales, capture, name)

    gain = ratio * torch.tensor(
        [scales.get(k, (1.0,) * 3) if k is not None else (1.0,) * 3 for k in capture.light_indices],
        dtype=torch.float32,
    ).reshape(-1, 3)
    flat_of = {k: _flat_field(path, capture.size).half() for k, path in flats.items()}
    correction = Correction(
        matrix, gain, tuple(flat_of.get(k) if k is not None else None for k in capture.light_indices)
    )
    # the largest corrected value, in float64: the photos are corrected as they are read, so
    # an overflow must be found now
    top = float((capture.lut if capture.lut is not None else capture.images).abs().max())
    row_sum = float(matrix.abs().sum(1).max()) if matrix is not None else 1.0
    smallest_flat = min((float(f.min()) for f in flat_of.values()), default=1.0)
    bound = top * row_sum / float(gain.min()) / smallest_flat
    if not math.isfinite(bound) or bound > torch.finfo(torch.float32).max:
        raise MatscanError(f"{place}: the calibration makes the photos overflow; check its values")
    meta = {**capture.meta, "warnings": [*capture.meta.get("warnings", []), *warnings]}
    if ratio != 1.0:
        meta["exposure_ratio"] = ratio
    return replace(capture, correction=correction, meta=meta)


def with_light_gains(capture: Capture, gains: Tensor) -> dict[str, Any]:
    """The calibration a capture was read with (:func:`apply_calibration`), its per-light
    scales multiplied by per-photo RGB ``gains`` (N, 3), as a calibration object that
    can be written anywhere: the colour matrix, grey albedo and light positions are kept
    as they are, flat-field files are named by absolute path, and lights the capture did
    not photograph keep their scales. The scales then hold at the capture's exposure and
    LED level, which the result records where the capture does (the lights it did not
    photograph scaled by the ratio :func:`apply_calibration` applied). Self-calibration
    writes its gains this way, so a later capture naming the result is corrected exactly
    as this one was."""
    cal = dict(capture.calibration or {})
    cal["format"] = CALIBRATION_FORMAT
    n = len(capture.files)
    if gains.shape != (n, 3):
        raise ValueError(f"gains: expected shape ({n}, 3), got {tuple(gains.shape)}")
    before = capture.correction.gain if capture.correction is not None else torch.ones(n, 3)
    ratio = capture.meta.get("exposure_ratio", 1.0)
    scales = {
        str(k): [significant(float(c) * ratio) for c in (s if isinstance(s, (list, tuple)) else (s,) * 3)]
        if ratio != 1.0
        else s
        for k, s in cal.get("light_scales", {}).items()
    }
    if "exposure_s" in capture.meta:
        cal["exposure_s"] = capture.meta["exposure_s"]
        cal["led_level"] = capture.meta.get("led_level", 1.0)
    elif "led_level" in capture.meta:  # a camera that set its own exposure: the capture's level alone
        cal.pop("exposure_s", None)
        cal["led_level"] = capture.meta["led_level"]
    for k, b, g in zip(capture.light_indices, before, gains, strict=True):
        if k is not None:
            scales[str(k)] = [significant(float(v)) for v in b * g]
    cal["light_scales"] = dict(sorted(scales.items(), key=lambda kv: int(kv[0])))
    if "flat_fields" in cal:
        _, prefix, _ = _where(capture)
        flats = _flat_files(cal["flat_fields"], f"{prefix}flat_fields", capture)
        cal["flat_fields"] = {str(k): str(path.resolve()) for k, path in flats.items()}
    return cal
