"""The rig as data: dome24 geometry (design.md), Table 4 subsets, JSON and its errors."""

from __future__ import annotations

import json
import math

import pytest
import torch

from matscan.errors import MatscanError
from matscan.rig import builtin_rig, load_rig, resolve_rig, rig_to_dict, save_rig


def test_dome24_geometry():
    rig = builtin_rig("dome24")
    assert rig.reference_distance_mm == 225.0
    assert rig.camera.position_mm == (0.0, 0.0, 225.0)
    assert rig.camera.up == (0.0, 1.0, 0.0)
    assert rig.field_mm == (120.0, 120.0)
    assert rig.backlight
    assert len(rig.lights) == 24
    for k, light in enumerate(rig.lights):
        x, y, z = light.position_mm
        assert math.sqrt(x * x + y * y + z * z) == pytest.approx(225.0, abs=1e-9)
        elevation = math.degrees(math.asin(z / 225.0))
        azimuth = math.degrees(math.atan2(y, x)) % 360
        assert elevation == pytest.approx(22.5 * (k // 8 + 1), abs=1e-9)
        assert azimuth == pytest.approx(45.0 * (k % 8), abs=1e-9) or azimuth == pytest.approx(360.0, abs=1e-9)
        assert light.exponent == 1.0
        assert light.intensity == (1.0, 1.0, 1.0)
        # aimed at the origin: the axis is −position / |position|
        for a, p in zip(light.axis, light.position_mm, strict=True):
            assert a == pytest.approx(-p / 225.0, abs=1e-12)
    # hand-computed positions: 225·(cos 22.5°, 0, sin 22.5°) and 225·(0, cos 67.5°, sin 67.5°)
    assert rig.lights[0].position_mm == pytest.approx((207.87289, 0.0, 86.10377), abs=1e-4)
    assert rig.lights[18].position_mm == pytest.approx((0.0, 86.10377, 207.87289), abs=1e-4)
    assert rig.lights[12].position_mm == pytest.approx((-159.09903, 0.0, 159.09903), abs=1e-4)


def test_table4_subsets():
    rig = builtin_rig("dome24")
    assert rig.subset("1") == (0,)
    assert rig.subset("2") == (0, 16)
    assert rig.subset("3") == (0, 16, 23)
    assert rig.subset("6") == (0, 4, 8, 12, 16, 20)
    assert rig.subset("10") == (4, 6, 8, 10, 12, 14, 16, 18, 20, 22)
    assert rig.subset("16") == (0, 2, 4, 5, 6, 8, 10, 11, 12, 14, 16, 17, 18, 20, 22, 23)
    assert rig.subset("24") == tuple(range(24))
    for name, members in rig.subsets.items():
        assert len(members) == int(name)
    assert rig.subset("0,4,8") == (0, 4, 8)
    assert rig.subset("5,") == (5,)
    assert rig.subset(None) == tuple(range(24))


@pytest.mark.parametrize(
    "spec, words",
    [
        ("7", "not a subset"),
        ("0,99", "index 99"),
        ("0,0", "twice"),
        ("a,b", "not a list"),
        ("0,,4", "not a list"),  # was read as 0,4: a typo for a light left out
        (",4", "not a list"),
    ],
)
def test_bad_subsets(spec, words):
    with pytest.raises(MatscanError, match=words):
        builtin_rig("dome24").subset(spec)


def test_light_indices_may_be_numpy_or_torch_integers_not_floats_or_bools():
    import numpy as np

    rig = builtin_rig("dome24")
    assert rig.subset(np.array([3, 5])) == (3, 5) and rig.subset(torch.tensor([1, 2])) == (1, 2)
    torch.testing.assert_close(rig.light_set(np.array([0, 4])).position, rig.light_set([0, 4]).position)
    for bad in ([2.7], [True], [np.bool_(True)]):
        with pytest.raises(MatscanError, match="is not a light index"):
            rig.light_set(bad)


@pytest.mark.parametrize("indices, words", [([99], "index 99"), ([-1], "index -1"), ([3, 3], "twice")])
def test_light_set_and_simulate_check_their_lights(tmp_path, indices, words):
    # -1 would pick the last light, 99 fall off the list, a repeat render one LED twice
    from conftest import random_maps

    from matscan.capture.virtual import simulate

    rig = builtin_rig("dome24")
    with pytest.raises(MatscanError, match=words):
        rig.light_set(indices)
    with pytest.raises(MatscanError, match=words):
        simulate(random_maps(8), rig, tmp_path / "cap", lights=indices)
    assert not (tmp_path / "cap").exists()


def test_json_round_trip(tmp_path):
    for name in ("dome24", "flash"):
        rig = builtin_rig(name)
        save_rig(rig, tmp_path / f"{name}.json")
        assert load_rig(tmp_path / f"{name}.json") == rig
    assert resolve_rig("dome24.json", base=tmp_path) == builtin_rig("dome24")


def test_flash_rig():
    rig = builtin_rig("flash")
    assert rig.per_image_geometry
    assert rig.lights[0].exponent == 0.0


def _write(tmp_path, mutate):
    data = rig_to_dict(builtin_rig("dome24"))
    mutate(data)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    "mutate, words",
    [
        (lambda d: d["lights"][2].update(postion_mm=[1, 2, 3]), r"lights\[2\]: unknown key 'postion_mm'"),
        (lambda d: d["camera"].pop("position_mm"), r"camera: missing field 'position_mm'"),
        (lambda d: d.pop("field_mm"), r"missing field 'field_mm'"),
        (lambda d: d["lights"][3].update(position_mm=[10, 0, -10]), r"lights\[3\]\.position_mm: z = -10 is below"),
        (lambda d: d.update(field_mm=[0, 120]), r"field_mm: \[0.0, 120.0\] must be two positive sizes"),
        (lambda d: d.update(reference_distance_mm=-1), r"reference_distance_mm: must be positive"),
        (lambda d: d["lights"][0].update(intensity=[1, 1]), r"lights\[0\]\.intensity: expected 3"),
        (lambda d: d["subsets"].update(bad=[0, 30]), r"subsets\['bad'\]: 30 is not a light"),
        (lambda d: d["subsets"].update({"6": []}), r"subsets\['6'\]: names no light"),
    ],
)
def test_rig_file_errors(tmp_path, mutate, words):
    path = _write(tmp_path, mutate)
    with pytest.raises(MatscanError, match=words) as info:
        load_rig(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_rig_file_not_json(tmp_path):
    path = tmp_path / "rig.json"
    path.write_text("{ not json")
    with pytest.raises(MatscanError, match="not valid JSON"):
        load_rig(path)
    with pytest.raises(MatscanError, match="no such rig file"):
        load_rig(tmp_path / "missing.json")
    with pytest.raises(MatscanError, match="not a built-in rig"):
        resolve_rig("dome99")
