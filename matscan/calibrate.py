"""Calibration (paper §3.2): a colour matrix from a ColorChecker, and per-light
intensity scales (and optional flat fields) from a grey card.

``calibration.json`` (``matscan-calibration/1``)::

    {"format": "matscan-calibration/1",
     "colour_matrix": [[…], […], […]],        # linear camera RGB → linear sRGB
     "light_scales": {"0": 1.02, "1": 0.97, …},  # per rig light: photo = scale × model
     "flat_fields": {"0": "flat_00.exr", …},   # optional: per light, mean 1
     "grey_albedo": 0.18}

A capture that names it is corrected on reading for reconstruction
(:func:`apply_calibration`): colour matrix first, then each photo divided by its
light's scale and flat field. Every field is checked there (errors name the file
and the field); plausible-but-wrong calibrations become warnings in the capture's
``meta["warnings"]``. :func:`check_chart` and :func:`check_scales` give the
warnings about a chart photo and about computed scales; :func:`calibrate` is
``matscan calibrate``: photos in, ``calibration.json`` out.

The ColorChecker is located by the user (the chart's four outer corners in pixel
coordinates, or the whole photo when the chart fills it): an automatic detector
would need a second OpenCV build beside ours.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from matscan.capture import Capture
from matscan.capture.folder import Correction
from matscan.color import srgb_to_linear
from matscan.errors import MatscanError, input_error
from matscan.jsonfile import check_file_name, check_number, check_object, check_vector, short_repr
from matscan.materials.noise import blur
from matscan.render import render, surface_points
from matscan.rig import Rig

CALIBRATION_FORMAT = "matscan-calibration/1"
GREY_CARD = 0.18

#: ColorChecker Classic patches, row by row from dark skin to black, as the 8-bit
#: sRGB values X-Rite publishes for the chart (post-November-2014 formulation).
COLORCHECKER_SRGB8 = [
    (115, 82, 68),
    (194, 150, 130),
    (98, 122, 157),
    (87, 108, 67),
    (133, 128, 177),
    (103, 189, 170),
    (214, 126, 44),
    (80, 91, 166),
    (193, 90, 99),
    (94, 60, 108),
    (157, 188, 64),
    (224, 163, 46),
    (56, 61, 150),
    (70, 148, 73),
    (175, 54, 60),
    (231, 199, 31),
    (187, 86, 149),
    (8, 133, 161),
    (243, 243, 242),
    (200, 200, 200),
    (160, 160, 160),
    (122, 122, 121),
    (85, 85, 85),
    (52, 52, 52),
]


def colorchecker_linear() -> Tensor:
    """(24, 3) linear sRGB reference values of the chart's patches."""
    return srgb_to_linear(torch.tensor(COLORCHECKER_SRGB8, dtype=torch.float64) / 255).float()


def _check_corners(corners: Sequence[Sequence[float]]) -> list[np.ndarray]:
    """The four corners as float arrays; each must be two finite numbers."""
    if len(corners) != 4:
        raise MatscanError(f"corners: expected 4 (x, y) points, got {len(corners)}")
    out = []
    for i, c in enumerate(corners):
        out.append(np.array(check_vector(list(c), 2, f"corners[{i}]"), dtype=np.float64))
    return out


def sample_patches(
    photo: Tensor,
    corners: Sequence[Sequence[float]] | None = None,
    rows: int = 4,
    cols: int = 6,
    fraction: float = 0.5,
) -> Tensor:
    """Mean colour (rows·cols, 3) of each patch of a chart in a linear photo (3, H, W).

    ``corners``: the chart's outer corners (x = column, y = row) in the order
    top-left, top-right, bottom-right, bottom-left; the whole photo by default.
    The central ``fraction`` of each patch is averaged (5 × 5 samples). A sample
    outside the photo is an error (the corners do not lie on the photo).
    """
    _, h, w = photo.shape
    if corners is None:
        corners = [(0, 0), (w, 0), (w, h), (0, h)]
    tl, tr, br, bl = _check_corners(corners)
    steps = np.linspace(-fraction / 2, fraction / 2, 5)
    out = []
    for r in range(rows):
        for c in range(cols):
            samples = []
            for dv in steps:
                for du in steps:
                    u, v = (c + 0.5 + du) / cols, (r + 0.5 + dv) / rows
                    top = tl + (tr - tl) * u
                    bottom = bl + (br - bl) * u
                    x, y = top + (bottom - top) * v
                    if not (0 <= x < w and 0 <= y < h):
                        raise MatscanError(
                            f"corners: patch {r * cols + c + 1} of the chart falls at (x {x:.0f}, y {y:.0f}), "
                            f"outside the {w}×{h} photo; give the chart's corners inside the photo"
                        )
                    samples.append(photo[:, int(y), int(x)])
            out.append(torch.stack(samples).mean(0))
    return torch.stack(out)


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
    if measured.shape != (len(COLORCHECKER_SRGB8), 3):
        raise MatscanError(
            f"measured: expected ({len(COLORCHECKER_SRGB8)}, 3) patch colours, got {tuple(measured.shape)}"
        )
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


def _grey_scale(photo: Tensor, model: Tensor, saturated: Tensor, k: int) -> float:
    """The scale of light ``k`` from its grey-card photo and rendering (each (3, H, W))."""
    lit = model > 1e-4
    if not bool(lit.any()):
        raise MatscanError(f"calibrate: light {k} does not light the grey card (check the rig file)")
    ok = (~saturated).expand_as(model) & lit
    if not bool(ok.any()):
        raise MatscanError(f"calibrate: every pixel saturated under light {k}; lower the exposure")
    s = weighted_median(photo[ok] / model[ok], model[ok])
    if not s > 0:
        raise MatscanError(f"calibrate: the grey card is black under light {k}; check that the light fired")
    return s


def light_scales(
    grey: Capture, albedo: float = GREY_CARD, flat_fields: bool = False, flat_sigma_px: float = 8.0
) -> tuple[dict[str, float], dict[str, Tensor]]:
    """Per-light intensity scale from photos of a grey card (a flat Lambertian of
    ``albedo``) under each light: the scale minimising the L1 distance between the
    photo and the rendering (the paper's 24 parameters); optionally the remaining
    smooth spatial ratio as a flat field of mean 1.

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
        s = _grey_scale(photo, model, grey.saturated[i], k)
        scales[str(k)] = s
        if flat_fields:
            ratio = (photo / (s * model).clamp_min(1e-4)).mean(0)
            ratio = blur(ratio, flat_sigma_px)
            flats[str(k)] = (ratio / ratio.mean().clamp_min(1e-12))[None]
    return scales, flats


def write_calibration(
    path: Path, matrix: Tensor | None, scales: dict[str, float] | None, flats: dict[str, Tensor] | None = None
) -> dict[str, Any]:
    """Write ``calibration.json`` (and flat-field EXRs beside it)."""
    from matscan.imagefile import write_image

    doc: dict[str, Any] = {"format": CALIBRATION_FORMAT, "grey_albedo": GREY_CARD}
    if matrix is not None:
        doc["colour_matrix"] = [[round(float(v), 6) for v in row] for row in matrix]
    if scales:
        doc["light_scales"] = {k: round(v, 6) for k, v in scales.items()}
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
        light_scales: per rig light (its index as text): photo = scale × model; empty without a grey card.
        flat_fields: per rig light, (1, H, W) of mean 1; empty unless asked for.
        warnings: one line each, saying what to check (:func:`check_chart`, :func:`check_scales`).
    """

    path: Path
    colour_matrix: Tensor | None
    chart_error: float | None
    light_scales: dict[str, float]
    flat_fields: dict[str, Tensor]
    warnings: tuple[str, ...]


CHART_ENCODINGS = ("srgb", "linear")


def calibrate(
    out: str | Path,
    grey: str | Path | None = None,
    chart: str | Path | None = None,
    corners: Sequence[Sequence[float]] | None = None,
    chart_encoding: str = "srgb",
    flat_fields: bool = False,
    overwrite: bool = False,
) -> Calibration:
    """Write ``calibration.json`` from a ColorChecker photo and/or a grey-card capture
    (``matscan calibrate``).

    Args:
        out: the calibration file to write (put it in the capture folder and name it
            in ``capture.json``); checked and locked before any work
            (:func:`matscan.outputs.claim_output`), never one of the inputs.
        grey: capture folder of an 18 % grey card under each light (``"@sample"``
            names the built-in sample capture): per-light scales (:func:`light_scales`).
        chart: photo of a ColorChecker Classic: the colour matrix (:func:`colour_matrix`).
        corners: the chart's outer corners in pixels (x, y), top-left, top-right,
            bottom-right, bottom-left; the whole photo by default (:func:`sample_patches`).
        chart_encoding: ``"srgb"`` or ``"linear"``, the transfer function of an integer
            chart photo (a float photo is linear).
        flat_fields: also write per-light flat fields (``flat_NN.exr`` beside ``out``).
        overwrite: replace an existing calibration file (and its flat fields).

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
    if chart_encoding not in CHART_ENCODINGS:
        raise MatscanError(f"chart_encoding: {chart_encoding!r} is not one of {', '.join(CHART_ENCODINGS)}")
    grey = capture_folder(grey) if grey is not None else None
    inputs = ([Path(chart)] if chart is not None else []) + (capture_inputs(grey) if grey is not None else [])
    with claim_output(out, "calibrate", inputs, kind="file", overwrite=overwrite) as claim:
        if flat_fields and grey is not None:  # the flat-field files beside it are outputs too
            for flat in sorted(claim.path.parent.glob("flat_*.exr")):
                check_destination(flat, inputs, "file", overwrite)
        return _calibrate(claim.path, grey, chart, corners, chart_encoding, flat_fields)


def _calibrate(
    out: Path,
    grey: Path | None,
    chart: str | Path | None,
    corners: Sequence[Sequence[float]] | None,
    chart_encoding: str,
    flat_fields: bool,
) -> Calibration:
    """:func:`calibrate` once its output is claimed: measure, then write ``out``."""
    from matscan.capture import load_capture
    from matscan.imagefile import read_image

    matrix = residual = None
    scales: dict[str, float] = {}
    flats: dict[str, Tensor] = {}
    warnings: list[str] = []
    if chart is not None:
        img = read_image(chart)
        photo = torch.from_numpy(img.pixels[:, :, :3]).permute(2, 0, 1).float()
        if img.kind == "int" and chart_encoding == "srgb":
            photo = srgb_to_linear(photo)
        measured = sample_patches(photo, corners)
        warnings += check_chart(measured)
        matrix = colour_matrix(measured, colorchecker_linear())
        residual = float((measured @ matrix.T - colorchecker_linear()).abs().mean())
    if grey is not None:
        scales, flats = light_scales(load_capture(grey), flat_fields=flat_fields)
        warnings += check_scales(scales, str(out))
    write_calibration(out, matrix, scales, flats)
    return Calibration(out, matrix, residual, scales, flats, tuple(warnings))


_CALIBRATION_KEYS = {
    "format": True,
    "colour_matrix": False,
    "light_scales": False,
    "flat_fields": False,
    "grey_albedo": False,
}
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


def _light_keyed(value: Any, where: str, rig: Rig) -> dict[int, Any]:
    """An object keyed by light indices of ``rig`` (``"0"``, ``"17"``), as {index: value}."""
    out = {}
    for key, item in check_object(value, where).items():
        if not _LIGHT_KEY.fullmatch(key) or int(key) >= len(rig.lights):
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


def _scales(value: Any, where: str, rig: Rig) -> dict[int, tuple[float, float, float]]:
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


def _flat_field(path: Path, size: tuple[int, int]) -> Tensor:
    """A flat field (1 or 3, H, W) read from ``path``: finite, the photos' size."""
    from matscan.imagefile import read_image

    px = read_image(path).pixels
    if px.shape[2] not in (1, 3):
        raise input_error(path, f"a flat field has 1 or 3 channels, this one {px.shape[2]}")
    flat = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).float()
    if tuple(flat.shape[-2:]) != size:
        raise input_error(
            path, f"flat field is {flat.shape[-1]}×{flat.shape[-2]} pixels but the photos are {size[1]}×{size[0]}"
        )
    if not torch.isfinite(flat).all():
        raise input_error(path, "flat field holds NaN or infinite values")
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


def apply_calibration(capture: Capture) -> Capture:
    """The capture with its calibration applied (colour matrix, then per-light scale
    and flat field); unchanged when it has none.

    Every field is checked first (errors name the calibration file or
    ``capture.json: calibration`` and the field): ``colour_matrix`` 3 × 3 finite;
    ``light_scales`` keyed by lights of the rig, each finite and positive;
    ``flat_fields`` keyed by lights, naming readable files of the photos' size.
    Plausible-but-wrong calibrations (scales for only some of the capture's lights,
    implausible scales) are appended as one-line warnings to the result's
    ``meta["warnings"]``.
    """
    cal = capture.calibration
    if cal is None:
        return capture
    place, prefix, name = _where(capture)
    check_object(cal, place, _CALIBRATION_KEYS)
    if cal["format"] != CALIBRATION_FORMAT:
        raise MatscanError(f"{prefix}format: must be {CALIBRATION_FORMAT!r}, got {short_repr(cal['format'])}")
    if "grey_albedo" in cal:
        check_number(cal["grey_albedo"], f"{prefix}grey_albedo", 0.0, 1.0, positive=True)
    matrix = _colour_matrix(cal["colour_matrix"], f"{prefix}colour_matrix") if "colour_matrix" in cal else None
    scales = _scales(cal["light_scales"], f"{prefix}light_scales", capture.rig) if "light_scales" in cal else {}
    flats = _flat_files(cal["flat_fields"], f"{prefix}flat_fields", capture) if "flat_fields" in cal else {}
    warnings = check_scales({str(k): sum(s) / 3 for k, s in scales.items()}, name)
    if "light_scales" in cal:
        warnings += _coverage_warning(scales, capture, name)

    gain = torch.tensor(
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
    return replace(capture, correction=correction, meta=meta)
