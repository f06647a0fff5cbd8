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
