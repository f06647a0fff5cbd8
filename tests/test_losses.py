"""Losses against values computed by hand on tiny tensors."""

from __future__ import annotations

import math

import pytest
import torch

from matscan.losses import (
    LAMBDA_RENDER,
    cosine_loss,
    l1,
    map_loss,
    novel_lights,
    rendering_loss,
    ssim,
    truth_rendering,
)
from matscan.render import render, surface_points
from matscan.rig import LightSet


def test_l1():
    assert float(l1(torch.tensor([[0.0, 1.0], [2.0, 3.0]]), torch.zeros(2, 2))) == 1.5


def test_cosine_loss():
    x = torch.tensor([1.0, 0.0, 0.0]).view(1, 3, 1, 1)
    y = torch.tensor([0.0, 1.0, 0.0]).view(1, 3, 1, 1)
    z = torch.tensor([0.5, 3**0.5 / 2, 0.0]).view(1, 3, 1, 1)  # 60° from x
    assert float(cosine_loss(x, x)) == 0
    assert float(cosine_loss(x, y)) == 1
    assert float(cosine_loss(x, z)) == pytest.approx(0.5)


def test_ssim_constant_images_closed_form():
    # constant images: variances vanish, SSIM = (2ab + C1) / (a² + b² + C1)
    a, b = 0.5, 0.25
    x = torch.full((1, 1, 16, 16), a, dtype=torch.float64)
    y = torch.full((1, 1, 16, 16), b, dtype=torch.float64)
    c1 = 0.01**2
    assert float(ssim(x, y)) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-12)
    r = torch.rand(1, 3, 20, 20, generator=torch.Generator().manual_seed(0))
    assert float(ssim(r, r)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(r, 1 - r)) < 0


def _flat(size=4, diffuse=1.0):
    n = torch.zeros(1, 3, size, size)
    n[:, 2] = 1
    return {
        "diffuse": torch.full((1, 3, size, size), diffuse),
        "specular": torch.zeros(1, 3, size, size),
        "roughness": torch.full((1, 1, size, size), 0.5),
        "normal": n,
    }


def test_rendering_loss_by_hand():
    # a white Lambertian pixel at the origin, head-on light at R: truth renders 1, ρ̂ = 0.5 renders 0.5
    truth, pred = _flat(1), _flat(1, 0.5)
    lights = LightSet.points(torch.tensor([[[0.0, 0.0, 225.0]]]), torch.tensor([0.0, 0.0, 225.0]), 225.0)
    points = torch.zeros(1, 1, 1, 3)
    expected = math.log(1.01 / 0.51)
    assert float(rendering_loss(pred, truth, "diffuse", lights, points)) == pytest.approx(expected, rel=1e-5)
    assert float(rendering_loss(truth, truth, "diffuse", lights, points)) == 0
    # 11 × 11 pixels all at the origin (SSIM needs an 11 × 11 window): every pixel as above
    truth, pred = _flat(11), _flat(11, 0.5)
    total, terms = map_loss("diffuse", pred, truth, lights, torch.zeros(1, 11, 11, 3))
    # L1 0.5; SSIM of constants 0.5 vs 1: (2·0.5 + C1)/(1.25 + C1)
    c1 = 0.01**2
    expected_total = 0.5 + LAMBDA_RENDER * expected + 1 - (1 + c1) / (1.25 + c1)
    assert float(total) == pytest.approx(expected_total, rel=1e-5)
    assert set(terms) == {"l1", "render", "ssim"}


def test_joint_rendering_loss_by_hand():
    # ρ̂ = 0.5 and a normal tilted 60° under a head-on light: each alone renders 0.5,
    # together 0.5 · cos 60° = 0.25 (the truth renders 1)
    truth, pred = _flat(1), _flat(1, 0.5)
    pred["normal"] = torch.tensor([math.sin(math.pi / 3), 0.0, 0.5]).view(1, 3, 1, 1)
    lights = LightSet.points(torch.tensor([[[0.0, 0.0, 225.0]]]), torch.tensor([0.0, 0.0, 225.0]), 225.0)
    points = torch.zeros(1, 1, 1, 3)
    alone = math.log(1.01 / 0.51)
    for name in ("diffuse", "normal", ("normal",)):
        assert float(rendering_loss(pred, truth, name, lights, points)) == pytest.approx(alone, rel=1e-5)
    joint = rendering_loss(pred, truth, ("diffuse", "normal"), lights, points)
    assert float(joint) == pytest.approx(math.log(1.01 / 0.26), rel=1e-5)


def test_novel_lights_lie_above_the_sample():
    ls = novel_lights(3, 50, 225.0, (0.0, 0.0, 225.0), torch.Generator().manual_seed(0))
    assert ls.position.shape == (3, 50, 3)
    d = ls.position.norm(dim=-1)
    assert (d >= 225 - 1e-3).all() and (d <= 450 + 1e-3).all()
    elevation = torch.rad2deg(torch.asin(ls.position[..., 2] / d))
    assert elevation.min() >= 10 - 1e-4


def test_rendering_loss_in_one_chunk_with_a_shared_target_equals_the_chunked_sum():
    # the loss renders in one chunk and may take the truth's rendering from the caller:
    # value and gradient equal the definition evaluated with the renderer's small chunks
    g = torch.Generator().manual_seed(3)
    b, size = 3, 12
    truth = {
        "diffuse": torch.rand(b, 3, size, size, generator=g),
        "specular": 0.04 + 0.5 * torch.rand(b, 3, size, size, generator=g),
        "roughness": 0.1 + 0.8 * torch.rand(b, 1, size, size, generator=g),
        "normal": torch.nn.functional.normalize(
            torch.randn(b, 3, size, size, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1), dim=1
        ),
    }
    lights = novel_lights(b, 5, 225.0, (0.0, 0.0, 225.0), g)
    points = surface_points((20.0, 20.0), (size, size)).expand(b, size, size, 3)
    rough = (0.1 + 0.8 * torch.rand(b, 1, size, size, generator=g)).requires_grad_()
    loss = rendering_loss(
        {"roughness": rough}, truth, "roughness", lights, points, truth_rendering(truth, lights, points)
    )
    (grad,) = torch.autograd.grad(loss, rough)

    ref_rough = rough.detach().clone().requires_grad_()
    a = render(truth["diffuse"], truth["specular"], ref_rough, truth["normal"], lights, points, chunk=4 * b * 5)
    with torch.no_grad():
        t = render(truth["diffuse"], truth["specular"], truth["roughness"], truth["normal"], lights, points, chunk=7)
    eps = 0.01
    ref = sum(((torch.log(eps + a[:, k].clamp_min(0)) - torch.log(eps + t[:, k])).abs().mean()) for k in range(5))
    (ref_grad,) = torch.autograd.grad(ref, ref_rough)
    assert float(loss.detach()) == pytest.approx(float(ref.detach()), rel=1e-6)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-5, atol=1e-9)
