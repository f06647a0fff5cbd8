"""Procedural materials: ranges, unit normals, tileability, determinism, speed-independent checks."""

from __future__ import annotations

import pytest
import torch

from matscan.errors import MatscanError
from matscan.materials.noise import cells, normals_from_height, spectral_noise
from matscan.materials.procedural import FAMILIES, METALS, generate, random_material


@pytest.mark.parametrize("family", FAMILIES)
def test_family_ranges_and_units(family):
    for seed in range(3):
        maps = generate(family, 64, seed)
        maps.check()
        for name in ("diffuse", "specular", "roughness", "alpha", "emissive"):
            t = getattr(maps, name)
            if t is not None:
                assert t.min() >= 0 and t.max() <= 1, (family, name)
        torch.testing.assert_close(maps.normal.norm(dim=0), torch.ones(64, 64), atol=1e-5, rtol=0)
        assert (maps.normal[2] > 0).all()
        assert torch.isfinite(maps.height).all()


@pytest.mark.parametrize("family", FAMILIES)
def test_family_is_deterministic_and_seed_dependent(family):
    a, b, c = generate(family, 32, 5), generate(family, 32, 5), generate(family, 32, 6)
    for name, t in a.present().items():
        torch.testing.assert_close(getattr(b, name), t, rtol=0, atol=0)
    assert any(not torch.equal(getattr(c, n), t) for n, t in a.present().items())


def _jumps(t: torch.Tensor) -> tuple[float, float]:
    """Mean jump across the wrap-around seam, and the largest mean jump across any
    interior column or row boundary (patterns with hard edges have some)."""
    cols = (t[..., :, 1:] - t[..., :, :-1]).abs().mean(dim=(0, 1))
    rows = (t[..., 1:, :] - t[..., :-1, :]).abs().mean(dim=(0, 2))
    seam = max(float((t[..., :, 0] - t[..., :, -1]).abs().mean()), float((t[..., 0, :] - t[..., -1, :]).abs().mean()))
    return seam, max(float(cols.max()), float(rows.max()))


@pytest.mark.parametrize("family", FAMILIES)
def test_family_tiles_without_seams(family):
    # across the wrap-around edge, maps change no more than across the sharpest interior edge
    # (a non-tileable noise would jump there like two unrelated pixels)
    for seed in range(3):
        maps = generate(family, 96, seed)
        for name, t in maps.present().items():
            seam, inner = _jumps(t)
            assert seam <= 1.05 * inner + 1e-4, (family, name, seam, inner)


def test_seam_check_catches_a_seam():
    t = torch.linspace(0, 1, 96)[None, None, :].expand(1, 96, 96)  # a ramp: one big jump at the wrap
    seam, inner = _jumps(t)
    assert seam > 1.05 * inner + 1e-4


def test_metals_are_metals_and_fabrics_dielectric():
    foil_f0 = max(float(generate("metal_brushed", 32, s).specular.mean()) for s in range(4))
    assert foil_f0 > 0.4
    for s in range(4):
        m = generate("metal_brushed", 32, s)
        assert float(m.diffuse.max()) <= 0.03
        f = generate("woven_plain", 32, s)
        assert 0.02 <= float(f.specular.min()) and float(f.specular.max()) <= 0.05
        leather = generate("leather", 32, s)
        assert 0.2 <= float(leather.roughness.mean()) <= 0.85
    assert all(0 <= c <= 1 for rgb in METALS.values() for c in rgb)


def test_special_families_have_their_maps():
    assert generate("mesh", 64, 0).alpha is not None
    lace = generate("lace", 64, 0)
    assert lace.alpha is not None and float(lace.alpha.min()) < 0.1 and float(lace.alpha.max()) > 0.9
    fluo = generate("fluorescent_print", 64, 0)
    assert fluo.emissive is not None and float(fluo.emissive.max()) > 0.04


def test_random_material_and_errors():
    fam, maps = random_material(32, 3)
    assert fam in FAMILIES and maps.size == (32, 32)
    with pytest.raises(MatscanError, match="not one of"):
        generate("velvet", 32)


def test_noise_primitives():
    g = torch.Generator().manual_seed(0)
    n = spectral_noise(64, g, 0.1)
    assert abs(float(n.mean())) < 1e-5 and abs(float(n.std()) - 1) < 1e-4
    f1, f2, v = cells(64, g, 16)
    assert (f2 >= f1).all() and float(f1.max()) < 64 / 4 * 1.5
    # a plane tilted by dh/dx = 1 gives normals at 45° toward −x
    x = torch.arange(16, dtype=torch.float32)
    ramp = x[None, :].expand(16, 16).clone()
    n = normals_from_height(ramp, 1.0)[:, :, 4:12]
    torch.testing.assert_close(n[:, 5, 3], torch.tensor([-(0.5**0.5), 0.0, 0.5**0.5]), atol=1e-6, rtol=0)
