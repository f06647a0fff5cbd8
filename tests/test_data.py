"""The training-data pipeline: equivariance of the normal transform, determinism, subsets, composition."""

from __future__ import annotations

import pytest
import torch
from conftest import random_maps
from torch.utils.data import DataLoader

from matscan.data import DataConfig, SvbrdfDataset, composite_over_stage, mix_materials
from matscan.errors import MatscanError
from matscan.mapset import MapSet
from matscan.render import render, surface_points
from matscan.rig import DOME24_SUBSETS, LightSet, builtin_rig, transform_points

QUIET = dict(read_noise=(0.0, 0.0), exposure_jitter=0.0, white_balance_jitter=0.0, led_jitter=0.0, compile=False)


@pytest.mark.parametrize("rotations", [0, 1, 2, 3])
@pytest.mark.parametrize("flip", [False, True])
def test_transform_equivariance(rotations, flip):
    # render(T(maps), T(lights)) == T(render(maps, lights)): proves normals turn with the pixels
    maps = random_maps(12, seed=11, tilt=0.5)
    rig = builtin_rig("dome24")
    lights = rig.light_set([0, 5, 10, 13, 22])
    pts = surface_points(rig.field_mm, (12, 12))
    base = render(maps.diffuse, maps.specular, maps.roughness, maps.normal, lights, pts)
    moved = maps.transformed(rotations, flip)
    moved_lights = LightSet(
        transform_points(lights.position, rotations, flip),
        lights.intensity,
        transform_points(lights.axis, rotations, flip),
        lights.exponent,
        lights.camera,
        lights.reference_distance_mm,
    )
    out = render(moved.diffuse, moved.specular, moved.roughness, moved.normal, moved_lights, pts)
    expected = torch.rot90(base.flip(-1) if flip else base, rotations, dims=(-2, -1))
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-6)


def test_turn_is_counter_clockwise_seen_from_the_camera():
    # a normal tilted toward +x, turned 90° counter-clockwise, tilts toward +y
    n = torch.tensor([0.6, 0.0, 0.8]).view(3, 1, 1).expand(3, 2, 2)
    maps = MapSet(torch.zeros(3, 2, 2), torch.zeros(3, 2, 2), torch.zeros(1, 2, 2), n.clone())
    torch.testing.assert_close(maps.transformed(1).normal[:, 0, 0], torch.tensor([0.0, 0.6, 0.8]))
    torch.testing.assert_close(maps.transformed(0, True).normal[:, 0, 0], torch.tensor([-0.6, 0.0, 0.8]))
    p = transform_points(torch.tensor([[1.0, 0.0, 5.0]]), 1)
    torch.testing.assert_close(p, torch.tensor([[0.0, 1.0, 5.0]]))


def test_sample_shapes_presence_and_determinism():
    ds = SvbrdfDataset(DataConfig(crop=32, compile=False))
    a, b = ds[7], ds[7]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    assert a["inputs"].shape == (24, 3, 32, 32) and a["present"].shape == (24,)
    for name, c in (("diffuse", 3), ("specular", 3), ("roughness", 1), ("normal", 3)):
        assert a[name].shape == (c, 32, 32)
    torch.testing.assert_close(a["normal"].norm(dim=0), torch.ones(32, 32), atol=1e-5, rtol=0)
    absent = a["present"] == 0
    assert float(a["inputs"][absent].abs().sum()) == 0
    assert (a["inputs"][a["present"] == 1].flatten(1).amax(1) > 0).all()
    assert 0 <= a["inputs"].min() and a["inputs"].max() <= 1  # saturated, quantised
    full, off = a["full_size"], a["offset"]
    assert (off >= 0).all() and (off + 32 <= full).all()
    assert not torch.equal(ds[8]["diffuse"], a["diffuse"])


def test_worker_processes_give_the_same_samples():
    ds = SvbrdfDataset(DataConfig(crop=16, compile=False), length=6)
    batches = list(DataLoader(ds, batch_size=3, num_workers=2))
    direct = torch.stack([ds[i]["inputs"] for i in range(6)])
    torch.testing.assert_close(torch.cat([b["inputs"] for b in batches]), direct, rtol=0, atol=0)


def test_light_subsets_include_table4():
    ds = SvbrdfDataset(DataConfig(crop=16, compile=False))
    seen = set()
    for i in range(300):
        seen.add(tuple(ds.light_subset(torch.Generator().manual_seed(i))))
    assert set(DOME24_SUBSETS.values()) <= seen
    assert len(seen) > 50  # and many random ones
    fixed = SvbrdfDataset(DataConfig(crop=16, subsets="6", compile=False))[0]
    assert fixed["present"].nonzero().flatten().tolist() == [0, 4, 8, 12, 16, 20]


@pytest.mark.parametrize("prob", [0.0, 0.2, 1.0])
def test_named_subset_share_follows_the_training_setting(prob):
    # a random draw of k of 24 lights is one of Table 4's subsets with probability 1/24 · Σ_k 1/C(24, k)
    # over the named counts (about 0.045: mostly "24", then "1"); the named draws add prob of the rest
    from math import comb

    from matscan.train import TrainConfig, data_config

    named = set(DOME24_SUBSETS.values())
    chance = sum(1 / comb(24, len(v)) for v in named) / 24
    ds = SvbrdfDataset(data_config(TrainConfig(named_subset_prob=prob, crop=16)))
    n = 2000
    hits = sum(tuple(ds.light_subset(torch.Generator().manual_seed(i))) in named for i in range(n))
    expected = prob + (1 - prob) * chance
    sd = (expected * (1 - expected) / n) ** 0.5
    assert abs(hits / n - expected) <= 4 * sd + 1e-9
    with pytest.raises(MatscanError, match="named_subset_prob"):
        data_config(TrainConfig(named_subset_prob=1.5))


def test_noise_free_sample_is_the_rendering_of_its_maps(tmp_path):
    # without jitter and noise, 16-bit linear photos are the rendering at the crop's world position
    from matscan.mapset import write_mapset

    write_mapset(tmp_path / "m", random_maps(24, seed=3))  # a library material: no emission
    ds = SvbrdfDataset(
        DataConfig(crop=16, srgb_prob=0.0, subsets="24", library=(str(tmp_path / "m"),), library_prob=1.0, **QUIET)
    )
    for i in range(3):
        s = ds[i]
        pts = surface_points(ds.rig.field_mm, (16, 16), tuple(s["offset"].tolist()), tuple(s["full_size"].tolist()))
        clean = render(s["diffuse"], s["specular"], s["roughness"], s["normal"], ds.rig.light_set(), pts)
        assert (s["inputs"] - clean.clamp(0, 1)).abs().max() <= 0.5 / 65535 + 1e-6


def test_mixing_and_stage_composite():
    g = torch.Generator().manual_seed(0)
    a, b = random_maps(16, 1), random_maps(16, 2)
    m = mix_materials(a, b, g)
    lo = torch.minimum(a.diffuse, b.diffuse) - 1e-6
    hi = torch.maximum(a.diffuse, b.diffuse) + 1e-6
    assert ((m.diffuse >= lo) & (m.diffuse <= hi)).all()
    torch.testing.assert_close(m.normal.norm(dim=0), torch.ones(16, 16), atol=1e-5, rtol=0)
    holes = MapSet(**a.present(), alpha=torch.zeros(1, 16, 16))
    stage = composite_over_stage(holes)
    assert torch.allclose(stage.diffuse, torch.full_like(stage.diffuse, 0.02))
    assert torch.allclose(stage.normal[2], torch.ones(16, 16))


#: Samples 0–2 of DataConfig(crop=32, compile=False), computed before prior v2 existed
#: (commit a72f59b): sum of the photos, mean |n_x|, |n_y| of the normals, crop offset.
V1_SAMPLES = [(12576.0754, 0.062223, [845, 98]), (224.3874, 0.044338, [379, 366]), (3656.6691, 0.136833, [490, 321])]


def test_the_default_prior_keeps_the_samples_of_earlier_runs():
    for prior in (None, "v1"):
        ds = SvbrdfDataset(DataConfig(crop=32, compile=False, **({} if prior is None else {"prior": prior})))
        for i, (total, tilt, offset) in enumerate(V1_SAMPLES):
            s = ds[i]
            assert float(s["inputs"].double().sum()) == pytest.approx(total, rel=1e-5)
            assert float(s["normal"][:2].double().abs().mean()) == pytest.approx(tilt, abs=2e-6)
            assert s["offset"].tolist() == offset


def test_prior_v2_reaches_the_samples():
    v1 = SvbrdfDataset(DataConfig(crop=16, compile=False))
    v2 = SvbrdfDataset(DataConfig(crop=16, compile=False, prior="v2"))
    assert any(not torch.equal(v1[i]["diffuse"], v2[i]["diffuse"]) for i in range(4))
    assert v2[0]["inputs"].shape == (24, 3, 16, 16)
    with pytest.raises(MatscanError, match="prior: 'v9' is not one of v1, v2, v3, v4, v5"):
        DataConfig(prior="v9")
