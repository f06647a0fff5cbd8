"""One shared model tester over every network variant, plus the paper preset's size."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from matscan.errors import MatscanError
from matscan.nets import (
    LOG_SCALE,
    MAPS,
    PHOTO_STATISTICS,
    PRESETS,
    VARIANTS,
    MapNets,
    NetConfig,
    encode_inputs,
    input_channels,
    network_input,
    photo_albedo,
    preset,
)

TINY = PRESETS["tiny"]


def _inputs(b=2, h=16, w=16, n=24, seed=0):
    g = torch.Generator().manual_seed(seed)
    photos = torch.rand(b, n, 3, h, w, generator=g)
    present = (torch.rand(b, n, generator=g) < 0.5).float()
    present[:, 0] = 1
    return encode_inputs(photos * present[..., None, None, None], present)


@pytest.mark.parametrize("variant", VARIANTS)
class TestEveryNetwork:
    def test_forward_backward_and_ranges(self, variant):
        torch.manual_seed(0)
        nets = MapNets(24, TINY, variant)
        out = nets(_inputs())
        assert set(out) == set(MAPS)
        for name, c in (("diffuse", 3), ("specular", 3), ("roughness", 1), ("normal", 3)):
            assert out[name].shape == (2, c, 16, 16)
        sum(v.square().mean() for v in out.values()).backward()
        grads = [p.grad for p in nets.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert sum(float(g.abs().sum()) for g in grads) > 0
        nets.eval()
        with torch.no_grad():
            out = nets(_inputs(seed=1))
        assert 0 <= out["roughness"].min() and out["roughness"].max() <= 1
        for name in ("diffuse", "specular"):
            assert 0 <= out[name].min() and out[name].max() <= 1
        torch.testing.assert_close(out["normal"].norm(dim=1), torch.ones(2, 16, 16), atol=1e-5, rtol=0)

    def test_odd_sizes_are_padded_and_cropped(self, variant):
        nets = MapNets(24, TINY, variant).eval()
        with torch.no_grad():
            out = nets(_inputs(1, 13, 21))
        assert all(t.shape[-2:] == (13, 21) for t in out.values())

    def test_save_load_round_trip(self, variant, tmp_path):
        from safetensors.torch import load_file, save_file

        a = MapNets(24, TINY, variant).eval()
        save_file(a.state_dict(), str(tmp_path / "w.safetensors"))
        b = MapNets(24, TINY, variant).eval()
        b.load_state_dict(load_file(str(tmp_path / "w.safetensors")))
        x = _inputs(seed=2)
        with torch.no_grad():
            oa, ob = a(x), b(x)
        for k in oa:
            torch.testing.assert_close(oa[k], ob[k], rtol=0, atol=0)


def test_normal_network_has_no_global_skip_and_others_do():
    nets = MapNets(24, TINY, "four")
    assert not hasattr(nets.nets["normal"].decoder, "globals")
    assert len(nets.nets["diffuse"].decoder.globals) == TINY.depth + 1


def paper_parameter_count(cin: int, out: int, global_skip: bool) -> int:
    """The paper's U-Net counted from its description: 3×3 convs with bias, 2×2 stride-2
    transposed convs, FC–SELU–FC global skips of the level's width at every level."""
    c = [64 + 32 * i for i in range(8)]
    n = (cin * 9 + 1) * c[0]
    for i in range(1, 8):
        n += (c[i - 1] * 9 + 1) * c[i] + 2 * (c[i] * 9 + 1) * c[i]
    n += (c[7] * 9 + 1) * c[7]
    for i in range(7, 0, -1):
        n += c[i] * c[i - 1] * 4 + c[i - 1]
        n += (2 * c[i - 1] * 9 + 1) * c[i - 1] + (c[i - 1] * 9 + 1) * c[i - 1]
    if global_skip:
        n += sum(2 * (cj * cj + cj) for cj in c)
    return n + (c[0] * 9 + 1) * out


def test_paper_preset_size_and_512_forward():
    nets = MapNets(24, preset("paper"), "four")
    cin = input_channels(24)
    for name, out, gs in (("diffuse", 3, True), ("specular", 3, True), ("roughness", 1, True), ("normal", 3, False)):
        assert sum(p.numel() for p in nets.nets[name].parameters()) == paper_parameter_count(cin, out, gs)
    net = nets.nets["diffuse"].eval()
    with torch.no_grad():
        y = net(torch.zeros(1, cin, 512, 512))
    assert y.shape == (1, 3, 512, 512)


def test_encode_inputs_channels():
    photos = torch.zeros(1, 24, 3, 4, 4)
    photos[0, 5] = 1.0
    present = torch.zeros(1, 24)
    present[0, 5] = 1
    x = encode_inputs(photos, present, torch.tensor([[0, 4]]), torch.tensor([[8, 8]]))
    assert x.shape == (1, 98, 4, 4)
    assert torch.allclose(x[0, 15:18], torch.ones(3, 4, 4))  # log1p(100)/log1p(100) = 1 for radiance 1
    assert x[0, :15].abs().sum() == 0 and x[0, 72 + 5].min() == 1 and x[0, 72:96].sum() == 16
    # field coordinates of a crop at columns 4..7 of 8: x from 1/8 to 7/8, top row y = 1 − 1/8
    torch.testing.assert_close(x[0, 96, 0], torch.tensor([0.125, 0.375, 0.625, 0.875]))
    assert float(x[0, 97, 0, 0]) == pytest.approx(0.875)


def test_network_input_divides_out_flat_irradiance():
    # a white Lambertian photographed under each light reads the same, 1, in every slot and pixel
    from matscan.render import render, surface_points
    from matscan.rig import builtin_rig

    rig = builtin_rig("dome24")
    offset, full = torch.tensor([[10, 30]]), torch.tensor([[64, 64]])
    pts = surface_points(rig.field_mm, (8, 8), (10, 30), (64, 64))
    up = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 8, 8)
    photos = render(torch.full((3, 8, 8), 0.5), torch.zeros(3, 8, 8), torch.ones(1, 8, 8), up, rig.light_set(), pts)
    x = network_input(photos[None], torch.ones(1, 24), offset, full, rig)
    expected = math.log1p(0.5 * LOG_SCALE) / math.log1p(LOG_SCALE)
    torch.testing.assert_close(x[0, :72], torch.full((72, 8, 8), expected), atol=1e-4, rtol=0)


def test_bad_names():
    with pytest.raises(MatscanError, match="preset"):
        preset("huge")
    with pytest.raises(MatscanError, match="variant"):
        MapNets(24, TINY, "two_encoders")
    assert NetConfig().channels()[-1] == 64 + 32 * 7


def test_photo_albedo_order_statistics_by_hand():
    photos = torch.zeros(1, 24, 3, 2, 2)
    present = torch.zeros(1, 24)
    for k, v in ((3, 0.2), (7, 0.9), (11, 0.3)):  # a highlight (0.9) among 0.2 and 0.3
        photos[0, k] = v
        present[0, k] = 1
    x = encode_inputs(photos, present)
    # sorted 0.2, 0.3, 0.9: the median is index ⌊2/2⌋ = 1, the lower third index ⌊2/3⌋ = 0
    torch.testing.assert_close(photo_albedo(x, 24), torch.full((1, 3, 2, 2), 0.3), atol=1e-5, rtol=0)
    torch.testing.assert_close(photo_albedo(x, 24, "lower_third"), torch.full((1, 3, 2, 2), 0.2), atol=1e-5, rtol=0)
    for statistic in PHOTO_STATISTICS:
        assert float(photo_albedo(encode_inputs(photos * 0, present * 0), 24, statistic).abs().max()) == 0


@pytest.mark.parametrize("count", [1, 2, 7, 24])
@pytest.mark.parametrize("statistic", ["median", "lower_third"])
def test_photo_albedo_matches_numpy_sort_of_the_present_lights(count, statistic):
    g = torch.Generator().manual_seed(count)
    photos = torch.rand(2, 24, 3, 5, 4, generator=g) * 0.8
    present = torch.zeros(2, 24)
    for b in range(2):
        present[b, torch.randperm(24, generator=g)[:count]] = 1
    got = photo_albedo(encode_inputs(photos, present), 24, statistic).numpy()
    k = (count - 1) // {"median": 2, "lower_third": 3}[statistic]
    for b in range(2):
        lit = photos[b, present[b] > 0].numpy()  # (count, 3, H, W): the decoded ratios are these photos
        np.testing.assert_allclose(got[b], np.sort(lit, axis=0)[k], atol=1e-5, rtol=0)


def test_photo_statistic_is_checked_and_the_cpu_preset_takes_the_lower_third():
    with pytest.raises(MatscanError, match="photo_statistic: 'mean' is not one of median, lower_third"):
        NetConfig(photo_statistic="mean")
    assert preset("cpu").photo_statistic == "lower_third" and preset("paper").photo_statistic == "median"
