"""The any-rig network (matscan.anyrig): its inputs against closed forms, pooling over any
number and order of photos, the random rigs it trains on, and that it learns."""

from __future__ import annotations

import math

import pytest
import torch

from matscan.anyrig import AnyRigNet, TrainAnyRig, _batch, loss, photo_input, pool, random_lights
from matscan.render import surface_points
from matscan.rig import Camera, Light, Rig


def test_photo_input_closed_form():
    # a white Lambertian card under a directional light at 30° elevation, seen from an
    # orthographic camera: photo = sin 30° = irradiance, so the ratio is 1 everywhere
    d = (math.cos(math.radians(30)), 0.0, math.sin(math.radians(30)))
    rig = Rig("t", 500.0, Camera(direction=(0.0, 0.0, 1.0)), (40.0, 40.0), (Light(direction=d),))
    pts = surface_points(rig.field_mm, (8, 8))
    x = photo_input(torch.full((3, 8, 8), 0.5), rig.light_set(), pts)
    assert x.shape == (10, 8, 8)
    torch.testing.assert_close(x[:3], torch.ones(3, 8, 8), atol=1e-5, rtol=0)  # log1p(100·1)/log1p(100)
    torch.testing.assert_close(x[3:6], torch.tensor(d).view(3, 1, 1).expand(3, 8, 8).float(), atol=1e-6, rtol=0)
    torch.testing.assert_close(x[6:9], torch.tensor([0.0, 0, 1]).view(3, 1, 1).expand(3, 8, 8), atol=1e-6, rtol=0)
    torch.testing.assert_close(x[9], torch.zeros(8, 8), atol=1e-6, rtol=0)  # no falloff
    # a point light at twice the reference distance straight above the centre: falloff (1/2)², log/4
    near = Rig("t", 100.0, Camera(position_mm=(0.0, 0.0, 300.0)), (40.0, 40.0), (Light(position_mm=(0, 0, 200.0)),))
    x = photo_input(torch.zeros(3, 9, 9), near.light_set(), surface_points(near.field_mm, (9, 9)))
    assert float(x[9, 4, 4]) == pytest.approx(math.log(0.25) / 4, abs=1e-5)


def test_pooling_takes_any_number_and_order_of_photos():
    torch.manual_seed(0)
    net = AnyRigNet().eval()
    x = torch.randn(1, 5, 10, 16, 16)
    with torch.no_grad():
        a = net(x, torch.ones(1, 5))
        b = net(x[:, [3, 0, 4, 1, 2]], torch.ones(1, 5))
        c = net(torch.cat([x, torch.randn(1, 2, 10, 16, 16)], 1), torch.tensor([[1.0, 1, 1, 1, 1, 0, 0]]))
        one = net(x[:, :1], torch.ones(1, 1))
    for key in a:
        torch.testing.assert_close(a[key], b[key], atol=1e-5, rtol=0)  # order does not matter
        torch.testing.assert_close(a[key], c[key], atol=1e-5, rtol=0)  # absent photos do not count
    streamed = net.predict(iter(x[0]))
    for key in a:
        torch.testing.assert_close(streamed[key], a[key][0], atol=1e-5, rtol=0)
    assert one["normal"].shape == (1, 3, 16, 16)
    torch.testing.assert_close(one["normal"].norm(dim=1), torch.ones(1, 16, 16), atol=1e-5, rtol=0)
    f = torch.tensor([[[[[1.0]]], [[[5.0]]]]])  # (B=1, K=2, C=1, 1, 1)
    assert pool(f, torch.tensor([[1.0, 0.0]])).flatten().tolist() == [1.0, 1.0]


def test_random_rigs_are_valid():
    g = torch.Generator().manual_seed(3)
    kinds = set()
    for _ in range(40):
        lights, _ = random_lights(g, 5)
        d = lights.position / lights.position.norm(dim=-1, keepdim=True)
        assert bool((d[:, 2] > math.sin(math.radians(9))).all())  # above 10° (flashes: far above)
        assert torch.isfinite(lights.intensity).all() and bool((lights.intensity > 0).all())
        kinds.add(("point" if bool((lights.w == 1).all()) else "dir", float(lights.camera_w[0])))
    assert {("dir", 0.0), ("dir", 1.0), ("point", 1.0)} <= kinds


def test_it_learns_a_batch():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    batch = _batch(g, TrainAnyRig(size=16, batch=2, max_photos=4))
    net = AnyRigNet()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    present = torch.ones(batch["x"].shape[:2])
    with torch.no_grad():
        first = float(loss(net(batch["x"], present), batch))
    for _ in range(40):
        value = loss(net(batch["x"], present), batch)
        opt.zero_grad()
        value.backward()
        opt.step()
    with torch.no_grad():
        assert float(loss(net(batch["x"], present), batch)) < 0.6 * first
