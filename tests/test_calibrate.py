"""Calibration recovers a known colour matrix and known per-light scales from simulated photos."""

from __future__ import annotations

import importlib
import json
import math
import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from matscan.calibrate import (
    apply_calibration,
    colorchecker_linear,
    colour_matrix,
    light_scales,
    sample_patches,
    write_calibration,
)
from matscan.capture import load_capture, write_capture
from matscan.capture.virtual import CameraModel, simulate_images
from matscan.cli import main
from matscan.errors import MatscanError
from matscan.imagefile import read_image, write_image
from matscan.mapset import MapSet
from matscan.rig import LightSet, builtin_rig


def _chart(camera: torch.Tensor, size=(120, 180), margin=(10, 20)) -> torch.Tensor:
    """A photo with the chart (4 × 6 patches) inside a margin; patches as the camera sees them."""
    ref = colorchecker_linear() @ torch.linalg.inv(camera).T  # camera RGB = A⁻¹ · reference
    h, w = size
    photo = torch.full((3, h + 2 * margin[0], w + 2 * margin[1]), 0.05)
    for i in range(24):
        r, c = divmod(i, 6)
        y0, x0 = margin[0] + r * h // 4, margin[1] + c * w // 6
        photo[:, y0 + 2 : y0 + h // 4 - 2, x0 + 2 : x0 + w // 6 - 2] = ref[i].view(3, 1, 1)
    return photo


def test_colour_matrix_is_recovered(tmp_path):
    a = torch.tensor([[1.1, 0.05, -0.02], [0.03, 0.92, 0.04], [-0.01, 0.08, 1.2]])
    photo = _chart(a)
    corners = [(20, 10), (200, 10), (200, 130), (20, 130)]
    m = colour_matrix(sample_patches(photo, corners), colorchecker_linear())
    torch.testing.assert_close(m, a, atol=1e-4, rtol=0)
    write_image(tmp_path / "chart.exr", photo.permute(1, 2, 0).numpy(), bits=32)
    assert (
        main(
            [
                "calibrate",
                "--chart",
                str(tmp_path / "chart.exr"),
                "--chart-encoding",
                "linear",
                "--corners",
                "20,10,200,10,200,130,20,130",
                "--out",
                str(tmp_path / "calibration.json"),
            ]
        )
        == 0
    )
    doc = json.loads((tmp_path / "calibration.json").read_text())
    torch.testing.assert_close(torch.tensor(doc["colour_matrix"]), a, atol=1e-3, rtol=0)


def _grey_capture(tmp_path, scales, indices, camera=None):
    """A grey card under dome24's lights ``indices`` of intensity ``scales``; photos in
    the camera's RGB when its matrix (camera RGB → linear sRGB) is given."""
    size = 32
    n = torch.zeros(3, size, size)
    n[2] = 1
    card = MapSet(torch.full((3, size, size), 0.18), torch.zeros(3, size, size), torch.ones(1, size, size), n)
    rig = builtin_rig("dome24")
    ls = rig.light_set(indices)
    ls = LightSet(
        ls.position,
        ls.intensity * torch.tensor(scales).view(-1, 1),
        ls.axis,
        ls.exponent,
        ls.camera,
        ls.reference_distance_mm,
    )
    photos = simulate_images(card, ls, rig.field_mm, CameraModel(read_noise=0.001, encoding="linear", bits=16))
    if camera is not None:
        photos = torch.einsum("ij,njhw->nihw", torch.linalg.inv(camera), photos)
    write_capture(tmp_path / "grey", photos, rig, light_indices=indices, encoding="linear", bits=16)
    return load_capture(tmp_path / "grey")


def test_light_scales_are_recovered_and_applied(tmp_path):
    indices = [0, 5, 12, 19, 23]
    truth = [1.05, 0.9, 1.2, 0.97, 0.8]
    grey = _grey_capture(tmp_path, truth, indices)
    scales, flats = light_scales(grey, flat_fields=True)
    for k, s in zip(indices, truth, strict=True):
        assert abs(scales[str(k)] / s - 1) < 0.005
    assert all(abs(float(f.mean()) - 1) < 1e-5 for f in flats.values())
    write_calibration(tmp_path / "grey" / "calibration.json", None, scales, flats)
    doc = json.loads((tmp_path / "grey" / "capture.json").read_text())
    doc["calibration"] = "calibration.json"
    (tmp_path / "grey" / "capture.json").write_text(json.dumps(doc))
    corrected = apply_calibration(load_capture(tmp_path / "grey"))
    # after correction every light images the card as an intensity-1 light would
    reference = _grey_capture(tmp_path / "ref", [1.0] * 5, indices)
    assert (corrected.linear() - reference.linear()).abs().mean() < 0.002
    # corrected as read: a region of one photo is the same region of all of them, corrected
    torch.testing.assert_close(corrected.linear([1], rows=(2, 5)), corrected.linear()[[1], :, 2:5], rtol=0, atol=0)
    assert corrected.images.dtype == load_capture(tmp_path / "grey").images.dtype  # codes stay codes


@pytest.mark.parametrize(
    ("calibration", "acquisition", "ratio", "warned"),
    [
        ({"exposure_s": 0.02, "led_level": 0.5}, {"exposure_s": 0.005, "led_level": 1.0}, 0.5, None),
        ({"exposure_s": 0.02}, {"exposure_s": 0.04}, 2.0, None),
        ({"exposure_s": 0.02}, {"exposure_s": None, "led_level": 1.0}, 1.0, "measured at 0.02 s (LED level 1)"),
        ({}, {"exposure_s": 0.005}, 1.0, "does not record its grey card's exposure"),
        ({}, None, 1.0, None),
        # neither records an exposure (a camera that set its own): another level is said, not applied
        ({"led_level": 1.0}, {"exposure_s": None, "led_level": 0.5}, 1.0, "lit at LED level 1 and the capture at 0.5"),
        ({"led_level": 0.5}, {"exposure_s": None, "led_level": 0.5}, 1.0, None),
        ({"led_level": 1.0}, {"exposure_s": 0.01, "led_level": 0.5}, 1.0, "taken at an exposure its camera set"),
    ],
)
def test_scales_follow_the_exposure_and_level_the_capture_records(tmp_path, calibration, acquisition, ratio, warned):
    """Each photo is divided by its light's scale times the ratio of the capture's
    exposure × LED level to the calibration's (worked out by hand); where one side does
    not record an exposure, the scales are applied as they are and a warning says so."""
    capture = _grey_capture(tmp_path, [1.0, 1.0], [0, 5])
    doc = json.loads((tmp_path / "grey" / "capture.json").read_text())
    doc["calibration"] = {"format": "matscan-calibration/1", "light_scales": {"0": 2.0, "5": 4.0}, **calibration}
    if acquisition is not None:
        doc["acquisition"] = acquisition
    (tmp_path / "grey" / "capture.json").write_text(json.dumps(doc))
    corrected = apply_calibration(load_capture(tmp_path / "grey"))
    assert corrected.correction.gain[:, 0].tolist() == pytest.approx([2.0 * ratio, 4.0 * ratio])
    torch.testing.assert_close(corrected.linear()[1], capture.linear()[1] / (4.0 * ratio))
    found = [w for w in corrected.meta["warnings"] if "exposure" in w]
    assert found == ([] if warned is None else [next(w for w in found if warned in w)])
    assert corrected.meta.get("exposure_ratio", 1.0) == ratio


def test_calibrate_function_writes_and_returns_the_calibration(tmp_path):
    # the library function behind `matscan calibrate`: a chart and a grey card in one call
    from matscan.calibrate import Calibration, calibrate

    a = torch.tensor([[1.1, 0.05, -0.02], [0.03, 0.92, 0.04], [-0.01, 0.08, 1.2]])
    write_image(tmp_path / "chart.exr", _chart(a).permute(1, 2, 0).numpy(), bits=32)
    indices, truth = [0, 12, 23], [1.05, 1.2, 0.8]
    _grey_capture(tmp_path, truth, indices, camera=a)  # the card seen by the camera that saw the chart
    out = tmp_path / "object" / "calibration.json"  # beside the capture it corrects, never in the grey one
    cal = calibrate(
        out,
        grey=tmp_path / "grey",
        chart=tmp_path / "chart.exr",
        corners=[(20, 10), (200, 10), (200, 130), (20, 130)],
        chart_encoding="linear",
        flat_fields=True,
    )
    assert isinstance(cal, Calibration) and cal.path == out.resolve() and cal.warnings == ()
    torch.testing.assert_close(cal.colour_matrix, a, atol=1e-4, rtol=0)
    assert 0 <= cal.chart_error < 1e-4
    # RGB scales, measured on the colour-corrected card: each channel the light's scale
    for k, s in zip(indices, truth, strict=True):
        assert [abs(c / s - 1) < 0.005 for c in cal.light_scales[str(k)]] == [True] * 3
    assert sorted(cal.flat_fields) == ["0", "12", "23"]
    doc = json.loads(out.read_text())
    for k, v in cal.light_scales.items():  # written to 7 significant digits
        assert doc["light_scales"][k] == pytest.approx(list(v), rel=1e-6)
    assert sorted(p.name for p in out.parent.glob("flat_*.exr")) == ["flat_00.exr", "flat_12.exr", "flat_23.exr"]
    with pytest.raises(MatscanError, match="exists"):  # an existing calibration needs overwrite=True
        calibrate(out, chart=tmp_path / "chart.exr", chart_encoding="linear")
    with pytest.raises(MatscanError, match="give grey"):
        calibrate(tmp_path / "c.json")
    with pytest.raises(MatscanError, match="chart_encoding: 'gamma' is not one of srgb, linear"):
        calibrate(tmp_path / "c.json", chart=tmp_path / "chart.exr", chart_encoding="gamma")


# --- the chart found in the photo ------------------------------------------------------

PATCH, GAP, BORDER = 60, 12, 20  # a ColorChecker Classic's proportions, in chart pixels


def _chart_scene(camera: torch.Tensor, angle: float, tilt: float, seed: int, noise: float = 3.0):
    """An 8-bit sRGB photo (H, W, 3) of a ColorChecker (dark body, 4 × 6 patches of the
    reference colours as ``camera`` sees them) on a grey table, turned by ``angle``
    degrees and seen in perspective (``tilt``), with noise; and the true outer corners of
    its grid of cells in the photo (top-left, top-right, bottom-right, bottom-left)."""
    import cv2

    from matscan.color import linear_to_srgb

    ref = (colorchecker_linear() @ torch.linalg.inv(camera).T).clamp(0, 1)
    w, h = 6 * PATCH + 5 * GAP + 2 * BORDER, 4 * PATCH + 3 * GAP + 2 * BORDER
    chart = np.full((h, w, 3), 0.02, np.float32)
    for i in range(24):
        r, c = divmod(i, 6)
        y0, x0 = BORDER + r * (PATCH + GAP), BORDER + c * (PATCH + GAP)
        chart[y0 : y0 + PATCH, x0 : x0 + PATCH] = ref[i].numpy()
    chart8 = (linear_to_srgb(torch.from_numpy(chart)).numpy() * 255 + 0.5).astype(np.uint8)
    a = math.radians(angle)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = (src - [w / 2, h / 2]) * 1.1
    dst[1] += [0, tilt * h]
    dst[2] += [0, -tilt * h]
    dst = np.float32(dst @ rot.T + [450, 380])
    m = cv2.getPerspectiveTransform(src, dst)
    table = np.full((760, 900, 3), 150, np.uint8)
    photo = cv2.warpPerspective(chart8, m, (900, 760), dst=table, borderMode=cv2.BORDER_TRANSPARENT)
    rng = np.random.default_rng(seed)
    photo = np.clip(photo + rng.normal(0, noise, photo.shape), 0, 255).astype(np.uint8)
    x0 = BORDER - GAP / 2 - 0.5  # pixel centres: a patch over pixels x..x+59 is centred at x + 29.5
    cells = np.float32(
        [
            [x0, x0],
            [x0 + 6 * (PATCH + GAP), x0],
            [x0 + 6 * (PATCH + GAP), x0 + 4 * (PATCH + GAP)],
            [x0, x0 + 4 * (PATCH + GAP)],
        ]
    )
    p = np.c_[cells, np.ones(4)] @ m.T
    return photo, p[:, :2] / p[:, 2:]


@pytest.mark.parametrize(("angle", "tilt", "seed"), [(15, 0.1, 0), (100, 0.05, 1), (190, 0.15, 2), (45, 0.2, 4)])
def test_chart_is_found_in_any_orientation_and_perspective(tmp_path, angle, tilt, seed):
    from matscan.calibrate import calibrate, detect_chart
    from matscan.color import srgb_to_linear

    a = torch.tensor([[1.1, 0.05, -0.02], [0.03, 0.92, 0.04], [-0.01, 0.08, 1.2]])
    photo8, truth = _chart_scene(a, angle, tilt, seed)
    linear = srgb_to_linear(torch.from_numpy(photo8).permute(2, 0, 1).float() / 255)
    corners = np.array(detect_chart(linear))
    assert np.linalg.norm(corners - truth, axis=1).max() < 2.0
    # end to end: the photo file in, the colour matrix out, no corners given
    write_image(tmp_path / "chart.png", photo8.astype(np.float32) / 255, bits=8)
    cal = calibrate(tmp_path / "calibration.json", chart=tmp_path / "chart.png")
    assert cal.warnings == ()
    # detection costs the matrix next to nothing: the same as with the true corners, but
    # for the noise of the few pixels sampled differently
    by_hand = colour_matrix(sample_patches(linear, truth.tolist()), colorchecker_linear())
    assert float((cal.colour_matrix - by_hand).abs().max()) < 5e-3
    # 8-bit quantisation, noise, and the patches the camera cannot show (clipped at 0)
    # leave it within 0.04 of the true matrix in every entry
    assert float((cal.colour_matrix - a).abs().max()) < 0.04


def test_no_chart_in_the_photo_is_named(tmp_path):
    from matscan.calibrate import calibrate

    write_image(tmp_path / "table.png", np.full((200, 300, 3), 0.5, np.float32), bits=8)
    with pytest.raises(MatscanError, match=r"table.png: no ColorChecker Classic found; give its corners"):
        calibrate(tmp_path / "calibration.json", chart=tmp_path / "table.png")
    assert not (tmp_path / "calibration.json").exists()


def test_reference_values_are_colour_sciences():
    colour = pytest.importorskip("colour")
    from matscan.calibrate import colorchecker_reference

    doc = colorchecker_reference()
    assert doc["edition"] == "ColorChecker24 - After November 2014"
    chart = colour.CCS_COLOURCHECKERS[doc["edition"]]
    assert [p["name"] for p in doc["patches"]] == list(chart.data)
    xyy = np.array([chart.data[n] for n in chart.data])
    np.testing.assert_allclose(np.array([p["xyY"] for p in doc["patches"]]), xyy, atol=1e-6)
    rgb = colour.XYZ_to_RGB(
        colour.xyY_to_XYZ(xyy),
        colour.RGB_COLOURSPACES["sRGB"],
        illuminant=chart.illuminant,
        chromatic_adaptation_transform="Bradford",
    )
    np.testing.assert_allclose(colorchecker_linear().numpy(), rgb, atol=1e-6)
    # and an independent known value: the white patch is near sRGB 243 (linear 0.896)
    assert 0.85 < float(colorchecker_linear()[18].mean()) < 0.93


# Near-light positions from a grey card: a dome24 whose LEDs are not where the rig file
# says, photographed through a vignetting lens. The photos are made here from the image
# formation model's closed form (design.md), not by the renderer.
CARD_SIZE = 128
CARD_VIGNETTING = 0.2


def _card_irradiance(positions, gains, size=CARD_SIZE, field=120.0, radius=225.0):
    """0.18 · I (R/d)² (a·(−l)) l_z for LEDs at ``positions`` (L, 3) aimed at the
    origin (exponent 1), per channel: (L, 3, size, size), float64."""
    c = (torch.arange(size, dtype=torch.float64) + 0.5) / size * field - field / 2
    x, y = c.view(1, -1).expand(size, size), -c.view(-1, 1).expand(size, size)
    p = torch.stack([x, y, torch.zeros_like(x)], -1)  # (H, W, 3)
    q = positions.double()[:, None, None, :]
    lv = q - p
    d = lv.norm(dim=-1)
    light = lv / d[..., None]
    axis = -q / q.norm(dim=-1, keepdim=True)
    e = (radius / d) ** 2 * (-(light * axis).sum(-1)) * light[..., 2]
    return 0.18 * gains.double()[:, :, None, None] * e[:, None]


@pytest.fixture(scope="module")
def moved_dome(tmp_path_factory):
    """A grey-card capture (16-bit linear) from dome24 with every LED ±5 mm off and
    ±20% / ±3% (colour) off in brightness; returns (folder, true positions, gains)."""
    g = torch.Generator().manual_seed(11)
    rig = builtin_rig("dome24")
    true = rig.light_set().position.double() + (torch.rand(24, 3, generator=g, dtype=torch.float64) * 2 - 1) * 5
    gains = (0.8 + 0.4 * torch.rand(24, 1, generator=g)) * (0.97 + 0.06 * torch.rand(24, 3, generator=g))
    c = (torch.arange(CARD_SIZE, dtype=torch.float64) + 0.5) / CARD_SIZE * 2 - 1
    vignetting = 1 - CARD_VIGNETTING * (c.view(1, -1) ** 2 + c.view(-1, 1) ** 2)
    photos = _card_irradiance(true, gains) * vignetting
    photos = (photos + 0.0005 * torch.randn(photos.shape, generator=g, dtype=torch.float64)).clamp(0, 1).float()
    folder = tmp_path_factory.mktemp("dome") / "grey"
    write_capture(folder, photos, rig, light_indices=list(range(24)), encoding="linear", bits=16)
    return folder, true, gains


def test_light_positions_are_fitted_to_a_grey_card(moved_dome):
    from matscan.calibrate import fit_light_positions

    folder, true, _ = moved_dome
    fit = fit_light_positions(load_capture(folder))
    fitted = torch.tensor([fit.positions[str(k)] for k in range(24)], dtype=torch.float64)
    error = (fitted - true).norm(dim=-1)
    moved = (true - builtin_rig("dome24").light_set().position.double()).norm(dim=-1)
    assert float(moved.mean()) > 4  # the rig file is off by about 5 mm
    assert float(error.mean()) < 0.3 and float(error.max()) < 1.0
    # log V = log(1 − 0.2 ρ²) ≈ −0.2 ρ² − 0.02 ρ⁴
    assert abs(fit.vignetting[0] + 0.2) < 0.02
    assert fit.residual < 0.01
    rig_file = {
        str(k): float(d) for k, d in enumerate((fitted - builtin_rig("dome24").light_set().position).norm(dim=-1))
    }
    assert all(abs(fit.moved_mm[k] - d) < 0.01 for k, d in rig_file.items())


def test_calibrate_positions_moves_the_lights_and_corrects_the_card(moved_dome, tmp_path):
    import shutil

    folder, true, gains = moved_dome
    grey = tmp_path / "grey"
    shutil.copytree(folder, grey)
    out = tmp_path / "cal" / "calibration.json"
    assert main(["calibrate", "--grey", str(grey), "--flat-fields", "--positions", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    placed = torch.tensor([doc["light_positions_mm"][str(k)] for k in range(24)], dtype=torch.float64)
    assert float((placed - true).norm(dim=-1).max()) < 1.0
    assert all(len(doc["light_scales"][str(k)]) == 3 for k in range(24))  # RGB
    for name in [out.name, *doc["flat_fields"].values()]:
        shutil.copy(out.parent / name, grey / name)
    meta = json.loads((grey / "capture.json").read_text())
    meta["calibration"] = "calibration.json"
    (grey / "capture.json").write_text(json.dumps(meta))
    corrected = apply_calibration(load_capture(grey))
    torch.testing.assert_close(corrected.lights.position.double(), placed, atol=1e-4, rtol=0)
    axis = -placed / placed.norm(dim=-1, keepdim=True)  # still aimed at the rig file's aim point, the origin
    torch.testing.assert_close(corrected.lights.axis.double(), axis, atol=1e-5, rtol=0)
    # corrected, the card images as under intensity-1 lights at the fitted places, in every channel
    expected = _card_irradiance(placed, torch.ones(24, 3))
    ratio = F.avg_pool2d(corrected.linear().double(), 8) / F.avg_pool2d(expected, 8)  # over the photos' noise
    assert float((ratio - 1).abs().mean()) < 0.003
    assert float((ratio.mean((-1, -2)) - 1).abs().max()) < 0.005


def test_positions_need_a_grey_card(tmp_path, capsys):
    assert (
        main(["calibrate", "--chart", str(tmp_path / "c.png"), "--positions", "--out", str(tmp_path / "c.json")]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert err == "matscan: error: calibrate: --positions fits the lights to grey-card photos; give --grey CAPTURE"
    with pytest.raises(MatscanError, match="positions are fitted to grey-card photos; give grey"):
        from matscan.calibrate import calibrate

        calibrate(tmp_path / "c.json", chart=tmp_path / "c.png", positions=True)


@pytest.mark.parametrize("shape", [(40, 60), (64, 64), (90, 30)])
def test_flat_field_smoothing_keeps_a_smooth_field_to_the_edges(shape):
    from matscan.calibrate import smooth

    h, w = shape
    v, u = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    field = 1 - 0.2 * (u**2 + v**2) + 0.1 * u  # vignetting and a light's slope: a smooth field
    torch.testing.assert_close(smooth(field, 8.0), field, atol=1e-5, rtol=0)  # edges kept, any aspect
    noisy = field + 0.01 * torch.randn(h, w, generator=torch.Generator().manual_seed(0))
    assert float((smooth(noisy, 8.0) - field).abs().mean()) < 0.003  # the noise averaged away


def test_light_fit_warnings_name_the_lights_and_what_to_check():
    from matscan.calibrate import LightFit, check_light_fit

    good = LightFit({"0": (1.0, 2.0, 200.0)}, {"0": 4.0, "1": 19.9}, (-0.2, 0.0), 0.004)
    assert check_light_fit(good, "cal.json") == []
    far = LightFit({}, {"0": 4.0, "3": 25.0, "4": 31.5}, (0.0, 0.0), 0.05)
    moved, residual = check_light_fit(far, "cal.json")
    assert moved.startswith("cal.json: lights 3, 4 have moved more than 20 mm from the rig file (up to 31.5 mm)")
    assert "matte" in moved
    assert residual.startswith("cal.json: the grey card departs from the lights' model by 5.0% (rms)")


def test_merged_calibrations_are_the_mean_places_and_geometric_mean_scales():
    """Three calibrations of one dome (hand-made numbers): light 0's merged position is
    the mean of three, light 2's (placed by one) is its own; scales (one number or RGB)
    merge to their geometric mean; the spreads are the RMS distances from the means,
    worked out by hand."""
    from matscan.calibrate import merge_calibrations

    base, p, s = {"format": "matscan-calibration/1", "grey_albedo": 0.18}, "light_positions_mm", "light_scales"
    docs = [
        {**base, p: {"0": [10, 0, 200], "1": [0, 20, 190]}, s: {"0": 2.0, "1": [1, 1, 4]}},
        {**base, p: {"0": [13, 0, 200], "1": [0, 24, 190]}, s: {"0": 8.0, "1": [1, 4, 1]}},
        {**base, p: {"0": [10, 3, 203], "2": [5, 5, 100]}, s: {"0": [4, 4, 4]}},
    ]
    m = merge_calibrations(docs, ["a.json", "b.json", "c.json"])
    assert m.files == 3 and m.positions == {"0": 3, "1": 2, "2": 1}
    assert m.document["grey_albedo"] == 0.18 and m.document["format"] == "matscan-calibration/1"
    assert m.document["light_positions_mm"] == {"0": [11.0, 1.0, 201.0], "1": [0.0, 22.0, 190.0], "2": [5, 5, 100]}
    assert m.document["light_scales"] == {"0": [4.0, 4.0, 4.0], "1": [1.0, 2.0, 2.0]}  # (2·8·4)^(1/3) = 4
    # light 0: squared distances 2²+1²+1² = 6, 1+1+1 = 3, 1+2²+2² = 9; light 1: 2² twice
    assert m.position_spread_mm == pytest.approx(math.sqrt((6 + 3 + 9 + 4 + 4) / 5))
    # log scales, each channel: light 0's log 2, 8, 4 lie -log 2, +log 2, 0 from log 4; light 1's two
    # files lie ∓log 2 from log 2 in green and in blue, 0 in red
    ln2 = math.log(2)
    per_light0 = [3 * ln2**2, 3 * ln2**2, 0.0]  # squared distances summed over the 3 channels
    per_light1 = [2 * ln2**2, 2 * ln2**2]
    assert m.scale_spread == pytest.approx(math.sqrt(sum(per_light0 + per_light1) / 5 / 3))


def test_a_calibration_whose_places_went_astray_is_left_out_of_the_merge():
    """Four calibrations of two lights: three within 1 mm of each other, one 8 mm off
    along x (a capture whose fit went astray): that one is left out, places and scales,
    and named with its distance from the per-light median places (8 mm, worked out by
    hand); the merge is the mean of the other three. Three that scatter alike keep all."""
    from matscan.calibrate import merge_calibrations

    def doc(dx: float, scale: float) -> dict:
        places = {"0": [100.0 + dx, 0.0, 150.0], "1": [0.0, 100.0, 150.0 + dx]}
        return {"format": "matscan-calibration/1", "light_positions_mm": places, "light_scales": {"0": scale}}

    m = merge_calibrations([doc(0.0, 1.0), doc(0.5, 1.0), doc(1.0, 1.0), doc(8.5, 9.0)], list("abcd"))
    # the median places are dx = 0.75 for both lights; d lies 7.75 mm off on each: RMS 7.75
    assert m.left_out == {"d": 7.75} and m.files == 3
    assert m.document["light_positions_mm"] == {"0": [100.5, 0.0, 150.0], "1": [0.0, 100.0, 150.5]}
    assert m.document["light_scales"] == {"0": [1.0, 1.0, 1.0]}
    kept = merge_calibrations([doc(0.0, 1.0), doc(1.0, 1.0), doc(2.0, 1.0)], list("abc"))
    assert kept.left_out == {} and kept.files == 3


def _dome_moved(places: torch.Tensor, shift: tuple[float, float, float], scale_mm: float) -> torch.Tensor:
    """``places`` moved together: by ``shift`` and ``scale_mm`` along each one's direction."""
    return places + torch.tensor(shift, dtype=places.dtype) + scale_mm * places / places.norm(dim=1, keepdim=True)


def _common_part_removed(error: torch.Tensor, places: torch.Tensor) -> torch.Tensor:
    """``error`` (L, 3) less its least-squares fit by one shift and one scale about ``places``."""
    d = places / places.norm(dim=1, keepdim=True)
    moves = torch.stack(
        [torch.eye(3, dtype=places.dtype)[j].expand_as(places).reshape(-1) for j in range(3)] + [d.reshape(-1)], 1
    )
    fit = torch.linalg.lstsq(moves, error.reshape(-1, 1)).solution
    return (error.reshape(-1, 1) - moves @ fit).reshape(-1, 3)


def test_a_weighted_merge_follows_the_files_that_agree_light_by_light(monkeypatch):
    """Four calibrations of dome24's 24 lights, each moved by a shift and scale of its own
    (a capture's bias for the dome as a whole), three scattered 0.1 mm per axis light by
    light and one 2 mm. With ``MERGE_WEIGHTED`` the merge's light-by-light error (its shift
    and scale fitted out) is under 0.15 mm RMS, where the plain mean's is over 0.4 (the
    noisy file's 2 mm over 4); its shift and scale are the plain mean's, to the rounding;
    with three files whose places differ only by shifts and scales, it is their mean."""
    calibrate = importlib.import_module("matscan.calibrate")  # the package's calibrate is the function

    true = builtin_rig("dome24").light_set().position.double()
    g = torch.Generator().manual_seed(4)
    moves = [((0.3, 0.0, -0.2), 0.5), ((-0.1, 0.2, 0.0), -0.3), ((0.0, 0.0, 0.4), 1.0), ((0.2, -0.2, 0.1), 0.8)]
    files = [
        _dome_moved(true, shift, scale) + sd * torch.randn(24, 3, generator=g, dtype=torch.float64)
        for (shift, scale), sd in zip(moves, (0.1, 0.1, 0.1, 2.0), strict=True)
    ]

    def doc(places: torch.Tensor) -> dict:
        return {
            "format": "matscan-calibration/1",
            "light_positions_mm": {str(k): places[k].tolist() for k in range(24)},
        }

    def merged(places: list[torch.Tensor]) -> torch.Tensor:
        m = calibrate.merge_calibrations([doc(p) for p in places], [f"{k}.json" for k in range(len(places))])
        assert m.left_out == {}
        return torch.tensor([m.document["light_positions_mm"][str(k)] for k in range(24)], dtype=torch.float64)

    plain = merged(files)
    monkeypatch.setattr(calibrate, "MERGE_WEIGHTED", True)
    weighted = merged(files)
    rms = [float(_common_part_removed(m - true, true).square().mean().sqrt()) for m in (plain, weighted)]
    assert rms[0] > 0.4 and rms[1] < 0.15
    between = weighted - plain  # their difference: light by light only (to the places' rounding to 0.001 mm
    # and the scale's directions, which the merge takes about its own places, 0.5 mm from these at 200 mm)
    assert float((between - _common_part_removed(between, plain)).abs().max()) < 5e-3
    exact = [_dome_moved(true, shift, scale) for shift, scale in moves[:3]]
    assert torch.allclose(merged(exact), torch.stack(exact).mean(0), atol=1e-3)


def test_merged_scales_are_brought_to_the_first_files_exposure():
    """Scales measured at other exposures and LED levels merge as if taken at the first
    file's: a file at half the exposure (its photos half as bright, so its scales half)
    and one at a quarter of the level agree with the first once scaled (hand-made
    numbers); the merge records the first's exposure."""
    from matscan.calibrate import merge_calibrations

    s = "light_scales"
    docs = [
        {"format": "matscan-calibration/1", s: {"0": 2.0}, "exposure_s": 0.01, "led_level": 1.0},
        {"format": "matscan-calibration/1", s: {"0": 1.0}, "exposure_s": 0.005, "led_level": 1.0},
        {"format": "matscan-calibration/1", s: {"0": [0.5, 0.5, 0.25]}, "exposure_s": 0.01, "led_level": 0.25},
    ]
    m = merge_calibrations(docs, ["a.json", "b.json", "c.json"])
    assert m.document["exposure_s"] == 0.01 and m.document["led_level"] == 1.0
    # light 0: 2, 2 and (2, 2, 1) at the first's exposure; the blue channel's geometric mean 4^(1/3)
    assert m.document[s]["0"] == pytest.approx([2.0, 2.0, 4 ** (1 / 3)], abs=1e-6)
    assert m.scale_spread > 0  # the blue channel's 1 against 2 and 2


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"exposure_s": 0.01}, "a.json: records no exposure where b.json does"),
        ({"exposure_s": 0.0}, "b.json: exposure_s: must be positive"),
        ({"exposure_s": 0.01, "led_level": 1.5}, "b.json: led_level: 1.5 is out of range"),
        ({"led_level": 1.5}, "b.json: led_level: 1.5 is out of range"),  # a level alone may be recorded
        ({"colour_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "b.json: colour_matrix differs from a.json's"),
        ({"format": "matscan-calibration/2"}, "b.json: format: must be 'matscan-calibration/1'"),
        ({"light_scales": {"0": -1.0}}, "b.json: light_scales['0']"),
        ({"light_positions_mm": {"0": [0, 0, -3]}}, "not above the sample plane"),
        ({"light_positions_mm": {"x": [0, 0, 3]}}, "'x' is not a light index"),
        ({"flat_fields": {"0": "flat_00.exr"}}, "b.json: flat_fields differs from a.json's"),
    ],
)
def test_merging_calibrations_refuses_what_differs_or_is_wrong(change, said):
    from matscan.calibrate import merge_calibrations

    a = {"format": "matscan-calibration/1", "light_scales": {"0": 1.0}}
    with pytest.raises(MatscanError, match=re.escape(said)):
        merge_calibrations([a, {**a, **change}], ["a.json", "b.json"])


def test_calibrate_merge_writes_the_merge_and_never_over_its_files(tmp_path, capsys):
    """``matscan calibrate --merge``: the merged file and a summary with the count and the
    spread; an --out that is one of the files is refused, and --merge with --grey."""
    files = []
    for k, x in enumerate((10.0, 14.0)):
        doc = {"format": "matscan-calibration/1", "light_positions_mm": {"3": [x, 0.0, 150.0]}}
        files.append(tmp_path / f"s{k}.json")
        files[-1].write_text(json.dumps(doc))
    out = tmp_path / "dome.json"
    assert main(["calibrate", "--merge", *map(str, files), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "2 calibrations merged" in said and "spread about the mean 2.00 mm RMS" in said
    assert json.loads(out.read_text())["light_positions_mm"] == {"3": [12.0, 0.0, 150.0]}
    before = files[0].read_bytes()
    assert main(["calibrate", "--merge", *map(str, files), "--out", str(files[0]), "--overwrite"]) == 2
    assert "never writes over its inputs" in capsys.readouterr().err and files[0].read_bytes() == before
    assert main(["calibrate", "--merge", str(files[0]), "--grey", "@sample", "--out", str(out)]) == 2
    assert "--merge merges calibration files" in capsys.readouterr().err


def test_a_merge_written_elsewhere_names_the_flat_fields_where_they_are(tmp_path, capsys):
    """Flat fields named relative to the calibrations are named relative to the merge's
    folder, so a merge written into another folder still finds them (an audit found it
    naming flat_00.exr beside itself, where none was)."""
    lab = tmp_path / "lab"
    lab.mkdir()
    files = []
    for k, x in enumerate((10.0, 14.0)):
        doc = {
            "format": "matscan-calibration/1",
            "light_positions_mm": {"3": [x, 0.0, 150.0]},
            "flat_fields": {"3": "flat_03.exr"},
        }
        files.append(lab / f"s{k}.json")
        files[-1].write_text(json.dumps(doc))
    out = tmp_path / "domes" / "dome.json"
    assert main(["calibrate", "--merge", *map(str, files), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["flat_fields"] == {"3": "../lab/flat_03.exr"}
    beside = lab / "dome.json"
    assert main(["calibrate", "--merge", *map(str, files), "--out", str(beside)]) == 0
    assert json.loads(beside.read_text())["flat_fields"] == {"3": "flat_03.exr"}  # as given, beside them


def test_scales_keep_their_significant_digits(tmp_path):
    """Scales were written to 6 decimals: 1.93e-6 and 2.10e-6 both became 2e-6, and one
    under 5e-7 became 0, which the reader refuses."""
    from matscan.calibrate import write_calibration

    out = tmp_path / "calibration.json"
    write_calibration(out, None, {"0": [1.93e-6, 2.1e-6, 4e-7], "5": 123456.789})
    scales = json.loads(out.read_text())["light_scales"]
    assert scales["0"] == pytest.approx([1.93e-6, 2.1e-6, 4e-7], rel=1e-6)
    assert scales["5"] == pytest.approx(123456.789, rel=1e-6)


def test_a_grey_card_in_other_units_is_refused_when_calibrating(tmp_path, capsys):
    """Photos 2e6 times the rig's units gave scales of 2e6: written, then refused by every
    reconstruction that read them. The card's errors name its photo too."""
    _grey_capture(tmp_path, [1.0, 1.0], [0, 5])
    doc = json.loads((tmp_path / "grey" / "capture.json").read_text())
    for entry in doc["images"]:
        path = tmp_path / "grey" / entry["file"]
        write_image(path.with_suffix(".exr"), read_image(path).pixels * 2e6, bits=32)
        entry["file"] = path.with_suffix(".exr").name
    (tmp_path / "grey" / "capture.json").write_text(json.dumps(doc))
    assert main(["calibrate", "--grey", str(tmp_path / "grey"), "--out", str(tmp_path / "cal.json")]) == 2
    err = capsys.readouterr().err
    assert re.search(r"light 0's scale [12](\.\d+)?e\+06 is outside 1e-06 to 1e\+06", err)
    assert str(tmp_path / "grey") in err
    assert not (tmp_path / "cal.json").exists()
    black = doc["images"][1]["file"]
    write_image(tmp_path / "grey" / black, np.zeros((32, 32, 3), np.float32), bits=32)
    assert main(["calibrate", "--grey", str(tmp_path / "grey"), "--out", str(tmp_path / "cal.json")]) == 2
    assert f"{tmp_path / 'grey' / black}: the grey card is black under light 5" in capsys.readouterr().err


def test_calibrations_that_record_a_level_alone_merge_at_one_level(tmp_path):
    """Files whose card's camera set the exposure record the LED level alone: merged only
    at one level, which the merge keeps (it merged 1.0 with 0.5 silently, and dropped it)."""
    from matscan.calibrate import merge_calibrations

    a = {"format": "matscan-calibration/1", "light_scales": {"0": [1.0, 1.0, 1.0]}, "led_level": 1.0}
    with pytest.raises(MatscanError, match=r"b\.json: records LED level 0\.5 where a\.json records LED level 1"):
        merge_calibrations([a, {**a, "led_level": 0.5}], ["a.json", "b.json"])
    with pytest.raises(MatscanError, match=r"b\.json: records no LED level where a\.json records LED level 1"):
        merge_calibrations([a, {k: v for k, v in a.items() if k != "led_level"}], ["a.json", "b.json"])
    merged = merge_calibrations([a, {**a, "light_scales": {"0": [4.0, 4.0, 4.0]}}], ["a.json", "b.json"]).document
    assert merged["led_level"] == 1.0 and merged["light_scales"]["0"] == pytest.approx([2.0, 2.0, 2.0])


def test_a_self_calibration_records_the_captures_level_and_significant_scales(tmp_path):
    """with_light_gains (self_calibration.json): for a capture whose camera set its exposure
    it kept the card's level, not the capture's, at which its scales now hold; and it
    rounded scales to 6 decimals (1.93e-6 became 2e-6, a small one 0)."""
    from matscan.calibrate import with_light_gains

    _grey_capture(tmp_path, [1.0, 1.0], [0, 5])
    doc = json.loads((tmp_path / "grey" / "capture.json").read_text())
    doc["acquisition"] = {"exposure_s": None, "led_level": 0.5}
    doc["calibration"] = {
        "format": "matscan-calibration/1",
        "light_scales": {"0": [1.93e-6, 2.1e-6, 1.4e-6], "5": 1.0},
        "led_level": 1.0,
    }
    (tmp_path / "grey" / "capture.json").write_text(json.dumps(doc))
    capture = apply_calibration(load_capture(tmp_path / "grey"))
    made = with_light_gains(capture, torch.tensor([[1.0, 1.0, 0.3], [1.0, 1.0, 1.0]]))
    assert made["led_level"] == 0.5 and "exposure_s" not in made
    assert made["light_scales"]["0"] == pytest.approx([1.93e-6, 2.1e-6, 0.42e-6], rel=1e-5)
