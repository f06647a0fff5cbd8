"""Procedural materials: ranges, unit normals, tileability, determinism, speed-independent checks."""

from __future__ import annotations

import pytest
import torch

from matscan.data import DataConfig
from matscan.errors import MatscanError
from matscan.materials.noise import cells, spectral_noise
from matscan.materials.procedural import DARK_ALBEDO_MAX, FAMILIES, METALS, PRIORS, generate, random_material
from matscan.reconstruct.surface import normals_from_height


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


# --- material priors -----------------------------------------------------------------

#: Prior v1 draws, computed with matscan/materials/procedural.py as of commit a72f59b (the
#: last before prior v2 existed, imported on its own from `git show`): seed, mm_per_px,
#: family, and the means of diffuse, specular, roughness and |n_x|, |n_y| of a 32² draw.
V1_DRAWS = [
    (0, None, "metal_brushed", [0.0177564, 0.4275258, 0.392683, 0.0002921]),
    (1, None, "woven_satin", [0.1982689, 0.0214867, 0.2976527, 0.0012105]),
    (2, 0.05, "woven_plain", [0.2883927, 0.0387616, 0.6100761, 0.2398197]),
    (3, None, "foil_print", [0.0698363, 0.4495442, 0.3340852, 0.0033023]),
    (8, 0.3, "leather", [0.1651542, 0.049184, 0.3238417, 0.1227422]),
    (13, None, "metal_embossed", [0.0053774, 0.6118709, 0.1484295, 0.0010371]),
    (2**41 + 7, None, "woven_satin", [0.0791662, 0.0288266, 0.4139165, 0.0046874]),
]
V1_FAMILIES = (
    "metal_brushed woven_satin woven_plain foil_print leather woven_twill leather woven_satin leather foil_print "
    "foil_print foil_print lace metal_embossed metal_brushed foil_print woven_satin mesh leather painted "
    "woven_twill paper leather plastic"
).split()
V1_COMMIT = "a72f59b"


@pytest.mark.parametrize("prior", [None, "v1"])
def test_prior_v1_draws_what_it_always_drew(prior):
    # published numbers (procedural:N, the model card's validation set) are reproduced from these seeds
    kw = {} if prior is None else {"prior": prior}
    assert [random_material(8, s, **kw)[0] for s in range(len(V1_FAMILIES))] == V1_FAMILIES
    for seed, mm, family, means in V1_DRAWS:
        fam, m = random_material(32, seed, mm, **kw)
        got = [float(t.double().mean()) for t in (m.diffuse, m.specular, m.roughness, m.normal[:2].abs())]
        assert fam == family
        assert got == pytest.approx(means, abs=2e-7), (seed, family)


def test_prior_v1_is_bit_identical_to_its_release():
    # the procedural module of the last commit before prior v2, run beside today's
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    try:
        src = subprocess.run(
            ["git", "show", f"{V1_COMMIT}:matscan/materials/procedural.py"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip(f"no git history with commit {V1_COMMIT} here")
    # normals_from_height has moved beside its inverse since; the function is unchanged
    src = src.replace("    normals_from_height,\n", "", 1)
    src = src.replace(
        "from matscan.materials.noise import (",
        "from matscan.reconstruct.surface import normals_from_height\nfrom matscan.materials.noise import (",
        1,
    )
    ns: dict = {"__name__": "procedural_v1_release"}  # a namespace of its own, not in sys.modules
    exec(compile(src, f"{V1_COMMIT}:matscan/materials/procedural.py", "exec"), ns)
    for seed in [*range(40), 2**41, 2**41 + 3]:
        for mm in (None, 0.04, 0.47):
            fam_a, a = ns["random_material"](24, seed, mm)
            fam_b, b = random_material(24, seed, mm)
            assert fam_a == fam_b
            for name, t in a.present().items():
                assert torch.equal(getattr(b, name), t), (seed, mm, name)


def test_prior_v2_adds_the_new_families_at_their_share():
    new = [f for f in PRIORS["v2"] if f not in PRIORS["v1"]]
    assert set(PRIORS["v1"]) < set(PRIORS["v2"]) and set(new) < set(FAMILIES)
    share = sum(PRIORS["v2"][f] for f in new) / sum(PRIORS["v2"].values())
    assert 0.35 <= share <= 0.45
    drawn = [random_material(8, s, prior="v2")[0] for s in range(400)]
    assert abs(sum(f in new for f in drawn) / 400 - share) < 0.08
    assert set(drawn) >= set(new)
    with pytest.raises(MatscanError, match="prior: 'v9' is not one of v1, v2, v3"):
        random_material(8, 0, prior="v9")


def _training_scale(i: int) -> float:
    """mm per pixel log-uniform over the training range (DataConfig.mm_per_px), fixed per i."""
    lo, hi = DataConfig().mm_per_px
    return lo * (hi / lo) ** ((i * 0.618034) % 1.0)


def _tilt_degrees(maps) -> torch.Tensor:
    return torch.rad2deg(torch.acos(maps.normal[2].clamp(-1, 1))).flatten()


@pytest.mark.parametrize("family", ["leather_embossed", "weave_heavy", "corrugated"])
def test_relief_families_tilt_20_to_40_degrees_at_every_training_scale(family):
    medians, steep = [], []
    for i in range(12):
        tilt = _tilt_degrees(generate(family, 128, i, _training_scale(i)))
        medians.append(float(tilt.median()))
        steep.append(float((tilt > 15).float().mean()))
    assert min(medians) >= 12, medians  # no draw comes out flat, whatever its scale
    assert 20 <= float(torch.tensor(medians).median()) <= 40, medians
    assert sum(steep) / len(steep) >= 0.6  # most of the surface tilts more than 15°


def test_v1_leather_is_flatter_than_embossed_leather():
    # the gap prior v2 fills: same scales, v1's leather lies much flatter
    old = [float(_tilt_degrees(generate("leather", 128, i, _training_scale(i))).median()) for i in range(12)]
    assert float(torch.tensor(old).median()) < 15


def _spread(t: torch.Tensor) -> float:
    q = t.flatten().quantile(torch.tensor([0.05, 0.95]))
    return float(q[1] - q[0])


def test_metallic_print_holds_metal_and_dielectric():
    for s in range(16):
        m = generate("metallic_print", 128, s)
        f0 = m.specular.amax(0)  # brightest channel: a coloured foil is dark in some
        assert _spread(f0) >= 0.3, s
        assert float(f0.min()) <= 0.05 and float(f0.max()) >= 0.35, s


def test_worn_roughness_and_specular_vary_over_the_surface():
    spreads = [_spread(generate("worn", 128, s).roughness) for s in range(16)]
    assert min(spreads) >= 0.12, spreads
    f0_spreads = [_spread(generate("worn", 128, s).specular.amax(0)) for s in range(16)]
    assert sum(x >= 0.1 for x in f0_spreads) >= 6  # paint over metal and tarnished metal: two kinds in three


def test_varnished_wood_is_a_dielectric_under_a_clear_coat():
    for s in range(8):
        m = generate("varnished_wood", 96, s)
        assert 0.04 <= float(m.specular.min()) and float(m.specular.max()) <= 0.05
        assert float(m.roughness.flatten().quantile(0.25)) <= 0.42  # the varnish is glossy away from pores
        assert _spread(m.roughness) > 0.02  # pores and brush marks vary it
        assert float(m.diffuse[0].mean()) > float(m.diffuse[2].mean())  # wood is warm


def test_prior_v3_adds_deep_dark_relief_and_keeps_v2s_draws():
    assert [f for f in PRIORS["v3"] if f not in PRIORS["v2"]] == ["dark_relief"]
    assert {f: PRIORS["v3"][f] for f in PRIORS["v2"]} == PRIORS["v2"]
    drawn = [random_material(8, s, prior="v3")[0] for s in range(300)]
    share = PRIORS["v3"]["dark_relief"] / sum(PRIORS["v3"].values())
    assert abs(drawn.count("dark_relief") / 300 - share) < 0.05
    # v2's draws are its own: the family each seed draws depends on v2's table alone
    for s in range(40):
        fam, maps = random_material(16, s, prior="v2")
        assert fam != "dark_relief"
        assert torch.equal(maps.diffuse, random_material(16, s, prior="v2")[1].diffuse)


def test_prior_v4_draws_v3s_families_the_dark_glossy_ones_at_10_in_35():
    assert set(PRIORS["v4"]) == set(PRIORS["v3"])
    dark = ("dark_glossy", "dark_relief")
    assert {f: PRIORS["v4"][f] for f in PRIORS["v3"] if f not in dark} == {
        f: PRIORS["v3"][f] for f in PRIORS["v3"] if f not in dark
    }
    assert sum(PRIORS["v4"][f] for f in dark) / sum(PRIORS["v4"].values()) == pytest.approx(10 / 35)
    drawn = [random_material(8, s, prior="v4")[0] for s in range(400)]
    share = sum(drawn.count(f) for f in dark) / 400
    assert abs(share - 10 / 35) < 0.06  # binomial: 1 sd is 0.023
    # v3's table is untouched, so its seeds draw what they drew
    assert (PRIORS["v3"]["dark_glossy"], PRIORS["v3"]["dark_relief"]) == (2.0, 2.0)


def test_dark_relief_is_dark_glossy_and_tilted_18_to_40_degrees_at_every_training_scale():
    for i in range(12):
        m = generate("dark_relief", 128, i, _training_scale(i))
        assert float(m.diffuse.max()) <= DARK_ALBEDO_MAX
        assert 0.04 <= float(m.specular.min()) and float(m.specular.max()) <= 0.05
        assert 0.15 <= float(m.roughness.min()) and float(m.roughness.max()) <= 0.6
        # the height is scaled so that the median tilt is the drawn one, 18°–40°
        assert 18 - 0.5 <= float(_tilt_degrees(m).median()) <= 40 + 0.5, i
    # deeper than dark_glossy's shallow leather and lacquer at the same scales
    shallow = [float(_tilt_degrees(generate("dark_glossy", 128, i, _training_scale(i))).median()) for i in range(12)]
    assert float(torch.tensor(shallow).median()) < 15


def test_dark_glossy_is_dark_and_glossy():
    for s in range(24):
        m = generate("dark_glossy", 64, s)
        assert float(m.diffuse.max()) <= DARK_ALBEDO_MAX <= 0.05
        assert float(m.roughness.max()) <= 0.45 and float(m.roughness.min()) >= 0.03
        assert 0.04 <= float(m.specular.min()) and float(m.specular.max()) <= 0.05


def test_prior_v5_adds_bright_glossy_coats_at_5_in_40():
    assert {f: w for f, w in PRIORS["v5"].items() if f != "glossy_coat"} == PRIORS["v4"]
    assert PRIORS["v5"]["glossy_coat"] / sum(PRIORS["v5"].values()) == pytest.approx(5 / 40)
    drawn = [random_material(8, s, prior="v5")[0] for s in range(400)]
    assert 0.08 < drawn.count("glossy_coat") / 400 < 0.17
    assert "glossy_coat" not in PRIORS["v4"]  # a published prior never changes


def test_glossy_coats_are_bright_smooth_dielectrics_nearly_flat_at_every_training_scale():
    medians = []
    for i in range(16):
        m = generate("glossy_coat", 128, i, _training_scale(i))
        assert 0.02 <= float(m.roughness.min()) and float(m.roughness.max()) <= 0.38
        assert float(m.roughness.median()) <= 0.27
        assert 0.04 <= float(m.specular.min()) and float(m.specular.max()) <= 0.05
        assert float(m.diffuse.amax(0).median()) >= 0.06  # linear: sRGB value 0.3 at least in some channel
        medians.append(float(_tilt_degrees(m).median()))
    assert 0.4 <= min(medians) and max(medians) <= 4.5
