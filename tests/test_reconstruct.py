"""Reconstruction: tiled inference, refinement by inverse rendering, the written outputs."""

from __future__ import annotations

import json

import torch

from matscan.capture import load_capture
from matscan.capture.virtual import CameraModel, simulate
from matscan.cli import main
from matscan.mapset import read_mapset
from matscan.nets import PRESETS, MapNets
from matscan.reconstruct import ReconstructConfig, flat_start, predict_maps, reconstruct_capture, rerender_error
from matscan.rig import builtin_rig
from matscan.samples import sample_maps_path


def _capture(tmp_path, size=32, lights=None, name="c"):
    maps = read_mapset(sample_maps_path())
    simulate(
        maps,
        builtin_rig("dome24"),
        tmp_path / name,
        lights=lights,
        size=size,
        camera=CameraModel(read_noise=0.001, encoding="linear", bits=16),
    )
    return load_capture(tmp_path / name), maps


def test_tiled_inference_matches_one_pass(tmp_path):
    cap, _ = _capture(tmp_path, size=48)
    torch.manual_seed(0)
    nets = MapNets(24, PRESETS["tiny"]).eval()
    whole = predict_maps(nets, cap, tile=64)  # one tile: the plain forward pass
    tiled = predict_maps(nets, cap, tile=24, overlap=8)  # 3 × 3 tiles with whole-image global averages
    for name in ("diffuse", "roughness"):
        assert (whole.present()[name] - tiled.present()[name]).abs().mean() < 0.02
    assert whole.size == tiled.size == (48, 48)


def test_refinement_fits_the_photos_and_held_out_lights(tmp_path):
    # fit on 16 lights, check the 8 left out: refinement must lower their re-rendering error too
    cap, truth = _capture(tmp_path, size=32)
    fit = [i for i, k in enumerate(cap.light_indices) if k not in (1, 3, 7, 9, 13, 19, 21, 23)]
    held = [i for i in range(len(cap.files)) if i not in fit]
    start = flat_start(cap)
    from matscan.reconstruct import refine_maps

    maps, scale, hist = refine_maps(start, cap, steps=80, lights_used=fit)
    assert scale == 1.0 and hist[-1] < hist[0]
    assert rerender_error(maps, cap, held) < 0.6 * rerender_error(start, cap, held)
    assert float((maps.diffuse - truth.diffuse[:, ::8, ::8]).abs().mean()) < 0.02


def test_reconstruct_writes_maps_and_record(tmp_path, capsys):
    _capture(tmp_path, size=32, lights=[0, 4, 8, 12, 16, 20], name="six")
    assert (
        main(["reconstruct", str(tmp_path / "six"), "--out", str(tmp_path / "out"), "--model", "none", "--steps", "20"])
        == 0
    )
    assert "from 6 photos" in capsys.readouterr().out
    rec = json.loads((tmp_path / "out" / "matscan.json").read_text())
    assert rec["refined"] and rec["size_px"] == [32, 32] and rec["mm_per_pixel"] == [3.75, 3.75]
    assert any("lights 1, 2, 3" in w for w in rec["warnings"])
    maps = read_mapset(tmp_path / "out")
    assert maps.size == (32, 32)


def test_missing_led_capture_reconstructs(tmp_path):
    cap, _ = _capture(tmp_path, size=16, lights=[k for k in range(24) if k != 5])
    res = reconstruct_capture(cap, ReconstructConfig(refine="on", refine_steps=5), None)
    assert any("lights 5 of rig dome24 are missing" in w for w in res.warnings)
