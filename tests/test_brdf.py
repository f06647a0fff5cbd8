"""The reflectance model (design.md Eq. 1) against closed forms and known values."""

from __future__ import annotations

import math

import pytest
import torch

from matscan.brdf import (
    DIELECTRIC_F0,
    cook_torrance,
    fresnel_schlick,
    ggx_alpha,
    ggx_distribution,
    glossiness_to_roughness,
    metallic_to_specular,
    roughness_to_glossiness,
    smith_g,
    smith_g1,
    specular_to_metallic,
)
from matscan.color import linear_to_srgb, srgb_to_linear

D64 = torch.float64


def unit_hemisphere(n: int, g: torch.Generator) -> torch.Tensor:
    v = torch.randn(n, 3, generator=g, dtype=D64)
    v[:, 2] = v[:, 2].abs() + 0.05
    return v / v.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("roughness", [0.1, 0.3, 0.5, 0.8, 1.0])
def test_ggx_is_normalised(roughness):
    # ∫ D(h)(n·h) dω = 2π ∫_0^1 D(μ) μ dμ, integrated on a grid dense near μ = 1 (D's peak).
    s = torch.cat([torch.zeros(1, dtype=D64), torch.logspace(-14, 0, 400001, dtype=D64)])
    mu = 1 - s
    alpha = ggx_alpha(torch.tensor(roughness, dtype=D64))
    integrand = ggx_distribution(mu, alpha) * mu
    total = 2 * math.pi * torch.trapezoid(integrand, s)
    assert abs(float(total) - 1.0) < 1e-4


def test_ggx_matches_walter_tangent_form():
    # Walter et al. 2007 Eq. 33: D = 1 / (π α² cos⁴θ (1 + tan²θ / α²)²)
    theta = torch.linspace(0, 1.4, 50, dtype=D64)
    for alpha in (0.05, 0.3, 0.9):
        a = torch.tensor(alpha, dtype=D64)
        ref = 1 / (math.pi * a**2 * torch.cos(theta) ** 4 * (1 + torch.tan(theta) ** 2 / a**2) ** 2)
        torch.testing.assert_close(ggx_distribution(torch.cos(theta), a), ref, rtol=1e-12, atol=0)


def test_alpha_is_roughness_squared_with_floor():
    r = torch.tensor([0.0, 0.01, 0.5, 1.0])
    torch.testing.assert_close(ggx_alpha(r), torch.tensor([1e-3, 1e-3, 0.25, 1.0]))


def test_fresnel_known_values():
    f0 = torch.tensor([0.04, 0.5, 0.95], dtype=D64)
    torch.testing.assert_close(fresnel_schlick(f0, torch.tensor(1.0, dtype=D64)), f0)  # normal incidence
    torch.testing.assert_close(fresnel_schlick(f0, torch.tensor(0.0, dtype=D64)), torch.ones(3, dtype=D64))
    # v·h = 0.5: F0 + (1 − F0)/32
    torch.testing.assert_close(fresnel_schlick(f0, torch.tensor(0.5, dtype=D64)), f0 + (1 - f0) / 32)


def test_smith_g1_known_values():
    alpha = torch.tensor([0.001, 0.2, 0.7, 1.0], dtype=D64)
    torch.testing.assert_close(smith_g1(torch.ones(4, dtype=D64), alpha), torch.ones(4, dtype=D64))
    # α = 1: G1(c) = 2c / (c + 1)
    c = torch.tensor(0.3, dtype=D64)
    assert float(smith_g1(c, torch.tensor(1.0, dtype=D64))) == pytest.approx(0.6 / 1.3, abs=1e-15)
    # G1 = 2 / (1 + sqrt(1 + α² tan²θ)), Walter et al. 2007 Eq. 34
    theta = torch.tensor(1.1, dtype=D64)
    a = torch.tensor(0.4, dtype=D64)
    ref = 2 / (1 + torch.sqrt(1 + a**2 * torch.tan(theta) ** 2))
    torch.testing.assert_close(smith_g1(torch.cos(theta), a), ref)
    torch.testing.assert_close(smith_g(c, c, a), smith_g1(c, a) ** 2)


def test_helmholtz_reciprocity():
    g = torch.Generator().manual_seed(1)
    n, l, v = (unit_hemisphere(500, g) for _ in range(3))
    rho = torch.rand(500, 3, generator=g, dtype=D64)
    f0 = torch.rand(500, 3, generator=g, dtype=D64)
    r = torch.rand(500, 1, generator=g, dtype=D64)
    a = cook_torrance(n, l, v, rho, f0, r, dim=-1)
    b = cook_torrance(n, v, l, rho, f0, r, dim=-1)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_lambertian_and_mirror_direction():
    up = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    rho = torch.tensor([0.2, 0.5, 1.0], dtype=D64)
    zero = torch.zeros(3, dtype=D64)
    # F0 = 0 at normal incidence: only ρ/π remains
    f = cook_torrance(up, up, up, rho, zero, torch.tensor([0.5], dtype=D64), dim=-1)
    torch.testing.assert_close(f, rho / math.pi)
    # at the mirror configuration (h = n, v·h = c): D(1) G1(c)² F(c) / (4 c²) with D(1) = 1/(π α²)
    c = math.cos(0.4)
    l = torch.tensor([math.sin(0.4), 0.0, c], dtype=D64)
    v = torch.tensor([-math.sin(0.4), 0.0, c], dtype=D64)
    r, f0 = 0.5, 0.3
    alpha = r * r
    g1 = 2 * c / (c + math.sqrt(alpha**2 + (1 - alpha**2) * c * c))
    fresnel = f0 + (1 - f0) * (1 - c) ** 5
    expected = 1 / (math.pi * alpha**2) * g1 * g1 * fresnel / (4 * c * c)
    f = cook_torrance(up, l, v, zero, torch.full((3,), f0, dtype=D64), torch.tensor([r], dtype=D64), dim=-1)
    torch.testing.assert_close(f, torch.full((3,), expected, dtype=D64))


def test_below_surface_has_no_specular():
    up = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    below = torch.tensor([0.6, 0.0, -0.8], dtype=D64)
    f = cook_torrance(
        up, below, up, torch.zeros(3, dtype=D64), torch.ones(3, dtype=D64), torch.tensor([0.3], dtype=D64), dim=-1
    )
    assert torch.all(f == 0)


def test_terms_gradcheck():
    g = torch.Generator().manual_seed(2)
    cos = (torch.rand(6, generator=g, dtype=D64) * 0.8 + 0.1).requires_grad_()
    alpha = (torch.rand(6, generator=g, dtype=D64) * 0.8 + 0.1).requires_grad_()
    f0 = (torch.rand(6, generator=g, dtype=D64)).requires_grad_()
    assert torch.autograd.gradcheck(ggx_distribution, (cos, alpha))
    assert torch.autograd.gradcheck(smith_g1, (cos, alpha))
    assert torch.autograd.gradcheck(fresnel_schlick, (f0, cos))
    n, l, v = (unit_hemisphere(4, g).requires_grad_() for _ in range(3))
    rho = torch.rand(4, 3, generator=g, dtype=D64).requires_grad_()
    spec = torch.rand(4, 3, generator=g, dtype=D64).requires_grad_()
    r = (torch.rand(4, 1, generator=g, dtype=D64) * 0.7 + 0.2).requires_grad_()
    assert torch.autograd.gradcheck(lambda *a: cook_torrance(*a, dim=-1), (n, l, v, rho, spec, r))


def test_glossiness_roughness():
    r = torch.tensor([0.0, 0.25, 1.0])
    torch.testing.assert_close(roughness_to_glossiness(r), torch.tensor([1.0, 0.75, 0.0]))
    torch.testing.assert_close(glossiness_to_roughness(roughness_to_glossiness(r)), r)


def test_metallic_to_specular_gltf_values():
    # glTF 2.0 Appendix B: metallic 0 → (baseColor, 0.04); metallic 1 → (0, baseColor)
    base = torch.tensor([0.8, 0.5, 0.2]).view(3, 1, 1)
    d, s = metallic_to_specular(base, torch.zeros(1, 1, 1))
    torch.testing.assert_close(d, base)
    torch.testing.assert_close(s, torch.full((3, 1, 1), DIELECTRIC_F0))
    d, s = metallic_to_specular(base, torch.ones(1, 1, 1))
    torch.testing.assert_close(d, torch.zeros(3, 1, 1))
    torch.testing.assert_close(s, base)
    d, s = metallic_to_specular(base, torch.full((1, 1, 1), 0.5))
    torch.testing.assert_close(d, base * 0.5)
    torch.testing.assert_close(s, 0.02 + base * 0.5)


def test_specular_metallic_round_trip():
    g = torch.Generator().manual_seed(3)
    # grey basecolours with any metallic: the inversion is exact
    grey = torch.rand(1, 8, 8, generator=g).expand(3, 8, 8) * 0.9 + 0.05
    metallic = torch.rand(1, 8, 8, generator=g)
    b, m = specular_to_metallic(*metallic_to_specular(grey, metallic))
    torch.testing.assert_close(m, metallic, atol=1e-4, rtol=0)
    torch.testing.assert_close(b, grey, atol=1e-3, rtol=0)
    # coloured basecolours, pure dielectric and pure metal
    colour = torch.rand(3, 8, 8, generator=g) * 0.9 + 0.05
    for mv in (0.0, 1.0):
        met = torch.full((1, 8, 8), mv)
        b, m = specular_to_metallic(*metallic_to_specular(colour, met))
        torch.testing.assert_close(m, met, atol=1e-4, rtol=0)
        torch.testing.assert_close(b, colour, atol=2e-3, rtol=0)


def test_srgb_known_values():
    # IEC 61966-2-1: 0.5 encoded ↔ 0.214041 linear; the linear segment below 0.04045
    x = torch.tensor([0.0, 0.02, 0.5, 1.0], dtype=D64)
    torch.testing.assert_close(
        srgb_to_linear(x), torch.tensor([0.0, 0.02 / 12.92, 0.21404114048223255, 1.0], dtype=D64)
    )
    y = torch.linspace(0, 1, 1001, dtype=D64)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(y)), y)
