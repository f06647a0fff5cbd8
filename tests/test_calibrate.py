"""Calibration recovers a known colour matrix and known per-light scales from simulated photos."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

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
from matscan.imagefile import write_image
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


def _grey_capture(tmp_path, scales, indices):
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


def test_calibrate_function_writes_and_returns_the_calibration(tmp_path):
    # the library function behind `matscan calibrate`: a chart and a grey card in one call
    from matscan.calibrate import Calibration, calibrate

    a = torch.tensor([[1.1, 0.05, -0.02], [0.03, 0.92, 0.04], [-0.01, 0.08, 1.2]])
    write_image(tmp_path / "chart.exr", _chart(a).permute(1, 2, 0).numpy(), bits=32)
    indices, truth = [0, 12, 23], [1.05, 1.2, 0.8]
    _grey_capture(tmp_path, truth, indices)
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
    assert [abs(cal.light_scales[str(k)] / s - 1) < 0.005 for k, s in zip(indices, truth, strict=True)] == [True] * 3
    assert sorted(cal.flat_fields) == ["0", "12", "23"]
    doc = json.loads(out.read_text())
    assert doc["light_scales"] == {k: round(v, 6) for k, v in cal.light_scales.items()}
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
