"""The artist-style evaluation map sets: valid maps, the relief, metal and gloss each set
promises (checked against geometry and physics, not against stored outputs), and their
place in ``matscan evaluate``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from matscan.errors import MatscanError
from matscan.materials.artist import ARTIST_NAMES, artist_material

pytest.importorskip("skimage")

#: Gold's F0 (Unreal Engine 4 documentation, "Physically Based Materials"); glTF's dielectric F0.
GOLD = (1.000, 0.766, 0.336)
DIELECTRIC = 0.04
#: shared/design.md, "The dome24 rig": radius, camera height, sample field, ring elevations.
DOME_R = 225.0
FIELD = 120.0


def tilt_degrees(normal: torch.Tensor) -> torch.Tensor:
    """Angle between each normal and +z (the flat surface's normal), degrees."""
    return torch.rad2deg(torch.acos(normal[2].clamp(-1, 1)))


@pytest.mark.parametrize("name", ARTIST_NAMES)
def test_every_set_is_a_valid_deterministic_map_set(name):
    maps = artist_material(name, 64).check(name)
    assert maps.size == (64, 64) and maps.height is not None
    for key in ("diffuse", "specular", "roughness"):
        t = getattr(maps, key)
        assert torch.isfinite(t).all() and float(t.min()) >= 0 and float(t.max()) <= 1, key
    torch.testing.assert_close(maps.normal.norm(dim=0), torch.ones(64, 64), atol=1e-5, rtol=0)
    assert float(maps.normal[2].min()) > 0
    again = artist_material(name, 64)
    assert all(torch.equal(t, again.present()[k]) for k, t in maps.present().items())


@pytest.mark.parametrize("name", ARTIST_NAMES)
def test_normals_are_the_slopes_of_the_height_map(name):
    # independent computation: NumPy central differences, design.md's frame (+x right,
    # +y up while rows grow downward), n = (−∂h/∂x, −∂h/∂y, 1) normalised; interior pixels
    maps = artist_material(name, 64)
    h = maps.height[0].double().numpy()
    mm = FIELD / 64
    dhdx = np.gradient(h, mm, axis=1)
    dhdy = -np.gradient(h, mm, axis=0)
    n = np.stack([-dhdx, -dhdy, np.ones_like(h)])
    n /= np.linalg.norm(n, axis=0)
    np.testing.assert_allclose(maps.normal.double().numpy()[:, 1:-1, 1:-1], n[:, 1:-1, 1:-1], atol=1e-5)


@pytest.mark.parametrize(("name", "covered"), [("black-leather", 0.8), ("embossed-coins", 0.3)])
def test_strong_relief_sets_tilt_20_to_40_degrees(name, covered):
    tilt = tilt_degrees(artist_material(name, 96).normal)
    relief = tilt > 5  # pixels that are not flat
    assert float(relief.float().mean()) >= covered
    assert 20 <= float(tilt[relief].median()) <= 40


def test_foil_print_is_metal_foil_on_dielectric_paper():
    maps = artist_material("foil-print", 64)
    gold = (maps.specular - torch.tensor(GOLD).view(3, 1, 1)).abs().amax(0) < 0.005
    paper = (maps.specular - DIELECTRIC).abs().amax(0) < 0.005
    assert float(gold.float().mean()) > 0.15 and float(paper.float().mean()) > 0.3
    assert float(maps.diffuse[:, gold].max()) < 0.01  # metals have no diffuse albedo
    assert float(maps.diffuse[:, paper].mean()) > 0.3
    rough = maps.roughness[0]  # within 0.005: a pixel picked may hold up to 0.5% of the other
    assert 0.115 <= float(rough[gold].min()) and float(rough[gold].max()) <= 0.205
    assert 0.595 <= float(rough[paper].min()) and float(rough[paper].max()) <= 0.705


def test_worn_metal_shows_steel_through_the_paint():
    maps = artist_material("worn-metal", 64)
    steel = maps.specular.amin(0) > 0.5
    paint = (maps.specular - DIELECTRIC).abs().amax(0) < 0.005
    assert float(steel.float().mean()) > 0.05 and float(paint.float().mean()) > 0.5
    assert float(maps.diffuse[:, steel].max()) < 0.05
    assert float(maps.roughness[0][steel].mean()) + 0.2 < float(maps.roughness[0][paint].mean())


def test_lacquer_saturates_8bit_photos_at_the_mirror_points_of_the_top_ring():
    from matscan.capture.virtual import CameraModel, simulate_images
    from matscan.rig import builtin_rig

    size = 64
    maps = artist_material("lacquer", size)
    assert float(maps.roughness.max()) <= 0.1
    rig = builtin_rig("dome24")
    photos = simulate_images(maps, rig.light_set(), rig.field_mm, CameraModel(encoding="srgb", bits=8))
    saturated = (photos >= 1).any(1)  # (24, H, W)
    assert 0 < float(saturated.float().mean()) < 0.02  # highlights, on a dark lacquer
    # mirror geometry of a flat surface, camera on the axis at height R: the reflection
    # of a light at elevation e lies R cos e · R / (R + R sin e) from the centre
    # (44.8 mm for ring 2; 93.2 mm for ring 1 and 145 mm for ring 0, outside the ±60 mm field)
    centre = (torch.arange(size) + 0.5) / size * FIELD - FIELD / 2
    for k in range(24):
        e, a = math.radians(22.5 * (k // 8 + 1)), math.radians(45.0 * (k % 8))
        d = DOME_R * math.cos(e) * DOME_R / (DOME_R + DOME_R * math.sin(e))
        x, y = d * math.cos(a), d * math.sin(a)
        if max(abs(x), abs(y)) > FIELD / 2:
            assert not saturated[k].any(), k
            continue
        rows, cols = torch.nonzero(saturated[k], as_tuple=True)
        assert len(rows) > 0, k
        cx, cy = float(centre[cols].mean()), float(-centre[rows].mean())  # row 0 is the +y edge
        assert math.hypot(cx - x, cy - y) < 4.0, (k, (cx, cy), (x, y))


def test_unknown_name_lists_the_choices():
    with pytest.raises(MatscanError, match="artist material: 'velvet' is not one of foil-print, black-leather"):
        artist_material("velvet", 32)


def test_evaluate_names_them_artist_and_tables_them_by_source(tmp_path, monkeypatch):
    import matscan.evaluate
    from matscan.cli import main
    from matscan.evaluate import source_of, summary_table

    assert source_of("artist-foil-print") == "artist"
    seen = {}

    def fake_evaluate(materials, out, *args, **kwargs):
        seen.update(materials)
        return {"rows": 0, "seconds": 0.0}

    monkeypatch.setattr(matscan.evaluate, "evaluate_to_folder", fake_evaluate)
    assert main(["evaluate", "artist", "--out", str(tmp_path / "ev"), "--size", "16"]) == 0
    assert list(seen) == [f"artist-{n}" for n in ARTIST_NAMES]
    assert all(maps.size == (16, 16) for maps in seen.values())
    rows = [
        {"material": "artist-lacquer", "encoding": "srgb8", "lights": "1", "method": "fit", "rmse_diffuse": 0.25},
        {"material": "photo-brick", "encoding": "srgb8", "lights": "1", "method": "fit", "rmse_diffuse": 0.5},
    ]
    text = summary_table(rows, "source")
    assert "| fit | artist | 0.2500 |" in text and "| fit | photo | 0.5000 |" in text


def test_without_scikit_image_the_error_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "skimage", None)  # import skimage.data now raises ImportError
    monkeypatch.setitem(sys.modules, "skimage.data", None)
    with pytest.raises(MatscanError, match=r"artist materials need scikit-image: pip install 'matscan\[eval\]'"):
        artist_material("lacquer", 32)
