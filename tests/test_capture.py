"""Capture folders: round trips in every encoding, per-image geometry, and each bad input's message."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from matscan.capture import load_capture, write_capture
from matscan.color import linear_to_srgb
from matscan.errors import MatscanError
from matscan.imagefile import write_image
from matscan.rig import builtin_rig, save_rig


def photos(n=3, size=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, size, size, generator=g) * 0.9


def test_srgb_8_bit_round_trip(tmp_path):
    rig = builtin_rig("dome24")
    imgs = photos()
    write_capture(tmp_path / "c", imgs, rig, light_indices=[4, 0, 17], encoding="srgb", bits=8)
    cap = load_capture(tmp_path / "c")
    assert cap.light_indices == (4, 0, 17)
    assert cap.rig == rig
    assert cap.images.shape == (3, 3, 10, 10)
    err = (linear_to_srgb(cap.linear()) - linear_to_srgb(imgs)).abs().max()
    assert err <= 0.5 / 255 + 1e-6
    torch.testing.assert_close(cap.lights.position, rig.light_set([4, 0, 17]).position)
    assert cap.mm_per_pixel == (12.0, 12.0)


def test_linear_16_bit_and_exr_round_trips(tmp_path):
    rig = builtin_rig("dome24")
    imgs = photos()
    write_capture(tmp_path / "c16", imgs, rig, light_indices=[1, 2, 3], encoding="linear", bits=16)
    assert (load_capture(tmp_path / "c16").linear() - imgs).abs().max() <= 0.5 / 65535 + 1e-7
    hdr = imgs * 3  # unclipped in float files
    write_capture(tmp_path / "c32", hdr, rig, light_indices=[1, 2, 3], encoding="linear", bits=32)
    torch.testing.assert_close(load_capture(tmp_path / "c32").linear(), hdr, rtol=0, atol=0)


def test_photos_are_held_as_stored_and_read_a_region_at_a_time(tmp_path):
    rig = builtin_rig("dome24")
    imgs = photos()
    write_capture(tmp_path / "c8", imgs, rig, light_indices=[4, 0, 17], encoding="srgb", bits=8)
    write_capture(tmp_path / "c16", imgs, rig, light_indices=[4, 0, 17], encoding="linear", bits=16)
    cap8, cap16 = load_capture(tmp_path / "c8"), load_capture(tmp_path / "c16")
    assert cap8.images.dtype == torch.uint8 and cap16.images.dtype == torch.uint16  # 1 and 2 bytes a value
    # the decoding table is IEC 61966-2-1's: code 128 is ((128/255 + 0.055)/1.055)^2.4 = 0.2158605
    assert abs(float(cap8.lut[128]) - 0.2158605) < 1e-6 and float(cap16.lut[65535]) == 1.0
    for cap in (cap8, cap16):
        full = cap.linear()
        assert full.dtype == torch.float32
        part = cap.linear([2, 0], rows=(3, 7), cols=(1, 9))
        torch.testing.assert_close(part, full[[2, 0], :, 3:7, 1:9], rtol=0, atol=0)
        picked = cap.select([2, 0])
        assert picked.light_indices == (17, 4) and picked.files == (cap.files[2], cap.files[0])
        torch.testing.assert_close(picked.linear(), full[[2, 0]], rtol=0, atol=0)
        strips = cap.strips(budget=25)  # 10 pixels wide, 3 photos: 25 values hold no row, so one row each
        assert strips == [(r, r + 1) for r in range(10)]
        assert cap.strips(budget=60) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]


def test_saturation_mask(tmp_path):
    imgs = photos(1)
    imgs[0, :, 0, 0] = 5.0
    write_capture(tmp_path / "c", imgs, builtin_rig("dome24"), light_indices=[0])
    cap = load_capture(tmp_path / "c")
    assert cap.saturated[0, 0, 0, 0] and cap.saturated.sum() == 1


def test_subset_of_lights_and_rig_file(tmp_path):
    rig = builtin_rig("dome24")
    write_capture(tmp_path / "c", photos(3), rig, light_indices=[0, 8, 16])
    cap = load_capture(tmp_path / "c", lights=[8, 16])
    assert cap.light_indices == (8, 16)
    # a capture naming its rig by file
    doc = json.loads((tmp_path / "c" / "capture.json").read_text())
    save_rig(rig, tmp_path / "c2.json")
    (tmp_path / "c" / "capture.json").write_text(json.dumps({**doc, "rig": "../c2.json"}))
    assert load_capture(tmp_path / "c").rig == rig


def test_flash_capture_per_image_geometry(tmp_path):
    rig = builtin_rig("flash")
    geometry = [((-27.0, 34.0, 273.0), (-27.0, 34.0, 273.0)), ((10.0, 0.0, 250.0), (12.0, 0.0, 250.0))]
    write_capture(tmp_path / "f", photos(2), rig, geometry=geometry, field_mm=(68.5, 60.0))
    cap = load_capture(tmp_path / "f")
    assert cap.light_indices == (None, None)
    assert cap.field_mm == (68.5, 60.0)
    torch.testing.assert_close(cap.lights.position, torch.tensor([g[0] for g in geometry]))
    torch.testing.assert_close(cap.lights.camera, torch.tensor([g[1] for g in geometry]))


def _capture(tmp_path, n=3):
    write_capture(tmp_path / "c", photos(n), builtin_rig("dome24"), light_indices=list(range(n)))
    return tmp_path / "c"


def _edit(folder, mutate):
    path = folder / "capture.json"
    doc = json.loads(path.read_text())
    mutate(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize(
    "mutate, words",
    [
        (
            lambda d: d["images"][1].update(light=30),
            r"images\[1\]: light 30 is not a light of rig 'dome24' \(0 to 23\)",
        ),
        (lambda d: d["images"][2].update(light=0), r"images\[2\]: light 0 appears twice \(also images\[0\]\)"),
        (lambda d: d["images"][1].update(file="led_09.png"), r"led_09\.png: no such file"),
        (lambda d: d["images"][0].pop("light"), r"images\[0\]: missing field 'light'"),
        (lambda d: d.update(encoding="gamma22"), r"encoding: 'gamma22' is not one of srgb, linear"),
        (lambda d: d.update(format="other/2"), r"format: expected 'matscan-capture/1'"),
        (lambda d: d.update(rig="dome99"), r"capture\.json: rig: 'dome99' is not a built-in rig"),
        (lambda d: d.update(extra=1), r"unknown key 'extra'"),
        (lambda d: d.update(images=[]), r"images: lists no photos \(matscan capture lists none until"),
        (lambda d: d.update(acquisition=[]), r"capture\.json: acquisition: expected an object"),
        (
            lambda d: d.update(acquisition={"exposure_s": "fast"}),
            r"capture\.json: acquisition: exposure_s: expected a finite number, got 'fast'",
        ),
        (lambda d: d.update(acquisition={"exposure_s": 0}), r"acquisition: exposure_s: must be positive, got 0"),
        (
            lambda d: d.update(acquisition={"exposure_s": 7200}),
            r"acquisition: exposure_s: 7200 is out of range",
        ),
        (
            lambda d: d.update(acquisition={"exposure_s": 0.01, "led_level": 2}),
            r"acquisition: led_level: 2 is out of range",
        ),
    ],
)
def test_capture_json_errors(tmp_path, mutate, words):
    folder = _capture(tmp_path)
    _edit(folder, mutate)
    with pytest.raises(MatscanError, match=words) as info:
        load_capture(folder)
    assert "\n" not in str(info.value)


def test_the_shortest_exposure_capture_can_meter_is_read(tmp_path):
    """``matscan capture`` meters from 0.01 s, halving up to 15 times; every exposure it
    can record loads (and one of an hour, the longest allowed)."""
    from matscan.capture.acquire import AcquireConfig

    folder = _capture(tmp_path)
    for seconds in (0.01 / 2**15, 3600):
        _edit(folder, lambda d, s=seconds: d.update(acquisition={"exposure_s": s}))
        assert load_capture(folder).meta["exposure_s"] == seconds
        AcquireConfig(exposure_s=seconds)
    for seconds in (0.0, 7200.0):
        with pytest.raises(MatscanError, match=r"--exposure: .* must be a number of seconds from 1e-09 to 3600"):
            AcquireConfig(exposure_s=seconds)


def test_unreadable_and_mismatched_images(tmp_path):
    folder = _capture(tmp_path)
    before = sorted((p.name, p.stat().st_mtime_ns) for p in folder.iterdir())
    (folder / "led_01.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(MatscanError, match=r"led_01\.png: cannot read as PNG"):
        load_capture(folder)
    write_image(folder / "led_01.png", np.zeros((5, 5, 3)))
    with pytest.raises(MatscanError, match=r"led_01\.png: is 5×5 pixels but led_00\.png is 10×10"):
        load_capture(folder)
    # reading never changes the folder (only our own edits above did)
    after = sorted(p.name for p in folder.iterdir())
    assert after == [name for name, _ in before]


def test_not_a_capture(tmp_path):
    with pytest.raises(MatscanError, match="no such capture folder"):
        load_capture(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MatscanError, match="no capture.json here"):
        load_capture(tmp_path / "empty")
    # a file where a folder belongs is named as one (it read "no such capture folder")
    (tmp_path / "empty" / "capture.json").write_text("{}")
    with pytest.raises(MatscanError, match=r"capture\.json: is a file, not a capture folder \(give the folder that"):
        load_capture(tmp_path / "empty" / "capture.json")
    from matscan.mapset import read_mapset

    with pytest.raises(MatscanError, match=r"capture\.json: is a file, not a map set folder"):
        read_mapset(tmp_path / "empty" / "capture.json")
    (tmp_path / "empty" / "capture.json").write_text("{")
    with pytest.raises(MatscanError, match=r"capture\.json: not valid JSON"):
        load_capture(tmp_path / "empty")


def test_a_float_photo_far_past_white_is_refused_naming_it(tmp_path):
    """A float photo may hold highlights above 1, not 3e38 (which would overflow every
    sum of squares downstream and fail the reconstruction at its end)."""
    images = photos(3)
    images[1, 0, 2, 2] = 3e38
    write_capture(tmp_path / "c", images, builtin_rig("dome24"), light_indices=[0, 1, 2], encoding="linear", bits=32)
    name = json.loads((tmp_path / "c" / "capture.json").read_text())["images"][1]["file"]
    with pytest.raises(MatscanError, match=rf"{name}: holds values up to 3e\+38; a float photo's lie within ±1e\+06"):
        load_capture(tmp_path / "c")
