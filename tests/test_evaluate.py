"""Evaluation: the trivial baseline recovers a flat Lambertian albedo exactly; scores are RMSEs."""

from __future__ import annotations

import torch

from matscan.data import DataConfig, SvbrdfDataset
from matscan.evaluate import Scores, baseline_maps
from matscan.mapset import MapSet, write_mapset


def test_baseline_recovers_flat_lambertian_albedo(tmp_path):
    size = 24
    n = torch.zeros(3, size, size)
    n[2] = 1
    rho = torch.tensor([0.4, 0.25, 0.1]).view(3, 1, 1).expand(3, size, size).clone()
    write_mapset(
        tmp_path / "flat",
        MapSet(rho, torch.zeros(3, size, size), torch.full((1, size, size), 0.5), n),
        file_format="exr",
    )
    ds = SvbrdfDataset(
        DataConfig(
            crop=16,
            library=(str(tmp_path / "flat"),),
            library_prob=1.0,
            mix_prob=0.0,
            read_noise=(0.0, 0.0),
            exposure_jitter=0.0,
            white_balance_jitter=0.0,
            led_jitter=0.0,
            srgb_prob=0.0,
            compile=False,
            subsets="6",
        )
    )
    sample = ds[0]
    est = baseline_maps(sample, ds.rig)
    # 16-bit linear quantisation of photos of about 0.1–0.5: relative error well under 1e-3
    torch.testing.assert_close(est["diffuse"], sample["diffuse"], atol=2e-4, rtol=1e-3)
    assert torch.equal(est["normal"][2], torch.ones(16, 16))


def test_scores_are_rmse_and_degrees():
    s = Scores()
    truth = {"diffuse": torch.zeros(1, 3, 2, 2), "normal": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)}
    pred = {"diffuse": torch.full((1, 3, 2, 2), 0.5), "normal": torch.tensor([1.0, 0.0, 0.0]).view(1, 3, 1, 1)}
    s.add(pred, truth)
    res = s.result()
    assert res["rmse_diffuse"] == 0.5 and abs(res["normal_degrees"] - 90.0) < 1e-4


def test_map_scores_of_the_truth_are_perfect():
    from conftest import random_maps

    from matscan.evaluate import map_scores, rendering_scores
    from matscan.rig import builtin_rig

    truth = random_maps(16, seed=3)
    s = map_scores(truth, truth)
    assert all(s[f"rmse_{m}"] == 0 for m in ("diffuse", "specular", "roughness", "normal"))
    assert s["normal_degrees"] < 0.05 and abs(s["ssim_diffuse"] - 1) < 1e-6
    r = rendering_scores(truth, truth, builtin_rig("dome24").light_set([0, 9]), (120.0, 120.0), "rig")
    assert r["rig_rmse"] == 0 and r.get("rig_flip", 0.0) == 0.0


def test_study_writes_results(tmp_path):
    import json

    from matscan.evaluate import evaluate_to_folder
    from matscan.materials.photos import photo_material
    from matscan.materials.procedural import random_material

    materials = [("proc", random_material(24, 2**41)[1]), ("brick", photo_material("brick", 24))]
    res = evaluate_to_folder(materials, tmp_path / "ev", ["3", "24"], ["fit"], ["srgb8"], refine_steps=10)
    assert res["rows"] == 4
    rows = json.loads((tmp_path / "ev" / "results.json").read_text())["rows"]
    assert {r["lights"] for r in rows} == {"3", "24"}
    assert all(0 <= r["novel_rmse"] < 0.5 for r in rows)
    text = (tmp_path / "ev" / "results.md").read_text()
    assert "| fit | 3 |" in text and "| fit | 24 |" in text


def test_photo_materials_are_deterministic_and_in_range():
    from matscan.materials.photos import photo_material

    a, b = photo_material("gravel", 32), photo_material("gravel", 32)
    assert torch.equal(a.diffuse, b.diffuse)
    assert 0.04 <= float(a.diffuse.min()) and float(a.diffuse.max()) <= 0.76
    torch.testing.assert_close(a.normal.norm(dim=0), torch.ones(32, 32), atol=1e-5, rtol=0)
