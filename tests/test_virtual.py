"""The virtual rig: the exact model without noise, Poisson–Gaussian statistics, quantisation, backlight."""

from __future__ import annotations

import pytest
import torch
from conftest import random_maps

from matscan.capture import load_capture
from matscan.capture.virtual import CameraModel, apply_camera, simulate
from matscan.mapset import MapSet
from matscan.render import render_rig
from matscan.rig import builtin_rig
from matscan.samples import sample_capture_path, sample_maps_path


def test_noise_free_linear_float_is_the_exact_model(tmp_path):
    maps = random_maps(16, seed=2)
    rig = builtin_rig("dome24")
    simulate(maps, rig, tmp_path / "c", lights=[0, 9, 23], camera=CameraModel(encoding="linear", bits=32))
    cap = load_capture(tmp_path / "c")
    expected = render_rig(maps.diffuse, maps.specular, maps.roughness, maps.normal, rig, [0, 9, 23])
    torch.testing.assert_close(cap.linear(), expected, rtol=0, atol=0)


def test_poisson_gaussian_statistics():
    # variance of (Poisson(x·W)/W + N(0, σ²)) is x/W + σ², mean is x
    x, full_well, sigma = 0.25, 5000.0, 0.01
    cam = CameraModel(read_noise=sigma, full_well=full_well, encoding="linear", bits=32)
    y = apply_camera(torch.full((400_000,), x), cam, torch.Generator().manual_seed(0))
    assert abs(float(y.mean()) - x) < 1e-3
    expected_var = x / full_well + sigma**2
    assert abs(float(y.var()) / expected_var - 1) < 0.02


def test_saturation_and_quantisation():
    x = torch.tensor([-0.1, 0.0, 0.2, 0.5, 1.0, 3.0])
    out = apply_camera(x, CameraModel(encoding="linear", bits=8))
    assert out.min() == 0 and out.max() == 1
    torch.testing.assert_close(out * 255, torch.round(out * 255))
    srgb = apply_camera(x, CameraModel(encoding="srgb", bits=8))
    from matscan.color import linear_to_srgb

    codes = linear_to_srgb(srgb) * 255
    torch.testing.assert_close(codes, torch.round(codes), atol=1e-4, rtol=0)
    # 0.2 linear is 0.48453 in sRGB, code 123.55 → 124; stored back as linear 124/255 decoded
    assert float(srgb[2]) == pytest.approx(((124 / 255 + 0.055) / 1.055) ** 2.4, abs=1e-6)
    # exposure multiplies radiance before the sensor
    twice = apply_camera(torch.tensor([0.2]), CameraModel(exposure=2.0, encoding="linear", bits=32))
    torch.testing.assert_close(twice, torch.tensor([0.4]))


def test_backlight_gives_alpha_by_triangulation(tmp_path):
    # C_k = F + (1 − α) B_k for two stages: (C_g − C_b) = (1 − α)(B_g − B_b) gives α in closed form
    base = random_maps(16, seed=3)
    yy, xx = torch.meshgrid(torch.arange(16), torch.arange(16), indexing="ij")
    alpha = ((yy % 4 != 0) & (xx % 4 != 0)).float()[None]  # a mesh: 1-pixel holes every 4
    maps = MapSet(**base.present(), alpha=alpha)
    simulate(maps, builtin_rig("dome24"), tmp_path / "c", lights=[0], camera=CameraModel(encoding="linear", bits=32))
    cap = load_capture(tmp_path / "c")
    assert set(cap.backlight) == {"green", "blue", "green_empty", "blue_empty"}
    bl = cap.backlight
    diff = bl["green"] - bl["blue"]
    empty = bl["green_empty"] - bl["blue_empty"]
    est = 1 - (diff * empty).sum(0) / (empty * empty).sum(0)
    torch.testing.assert_close(est[None], alpha, atol=1e-5, rtol=0)
    # holes are black under the LEDs (the stage is dark)
    assert cap.linear([0])[0][:, alpha[0] == 0].abs().max() == 0


def test_resampling_and_flash(tmp_path):
    maps = random_maps(32, seed=4)
    simulate(maps, builtin_rig("dome24"), tmp_path / "c", lights=[3], size=16)
    assert load_capture(tmp_path / "c").size == (16, 16)
    simulate(maps, builtin_rig("flash"), tmp_path / "f")
    cap = load_capture(tmp_path / "f")
    assert len(cap.files) == 9 and cap.field_mm == (68.5, 68.5)


def test_shipped_sample_matches_its_maps():
    from matscan.mapset import read_mapset

    maps = read_mapset(sample_maps_path())
    cap = load_capture(sample_capture_path())
    assert cap.images.shape == (24, 3, 256, 256) and cap.light_indices == tuple(range(24))
    clean = render_rig(maps.diffuse, maps.specular, maps.roughness, maps.normal, cap.rig).clamp(0, 1)
    # within noise (σ 0.002 + shot) and 8-bit sRGB quantisation, away from saturated pixels
    ok = ~cap.saturated.expand_as(clean)
    rmse = float(((cap.linear() - clean)[ok] ** 2).mean().sqrt())
    assert rmse < 0.005


def test_srgb_quantisation_equals_rounding_in_float64():
    # stored values are round(srgb(x)·top) decoded, up to float32 rounding next to a code boundary
    from matscan.color import linear_to_srgb

    x = torch.rand(200_000, generator=torch.Generator().manual_seed(9))
    for bits in (8, 16):
        top = (1 << bits) - 1
        direct = torch.round(linear_to_srgb(x.double()) * top)
        stored = torch.round(linear_to_srgb(apply_camera(x, CameraModel(encoding="srgb", bits=bits)).double()) * top)
        off = (stored - direct).abs()
        assert off.max() <= 1
        assert (off > 0).float().mean() < (1e-4 if bits == 8 else 5e-3)
