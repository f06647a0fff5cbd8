"""Readers of map libraries: each layout on a tiny fixture written here, converted to our conventions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import random_maps

from matscan.brdf import metallic_to_specular
from matscan.color import linear_to_srgb
from matscan.errors import MatscanError
from matscan.imagefile import write_image
from matscan.mapset import write_mapset
from matscan.materials.library import classify, read_any, read_deschaintre, read_map_folder, tokens


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.permute(1, 2, 0).numpy()


def test_tokens_and_classification():
    assert tokens("Fabric030_2K_NormalGL") == ["fabric", "k", "normal", "gl"]
    from pathlib import Path

    cases = {
        "Fabric030_2K_Color.jpg": "basecolor",
        "oak_diff_2k.png": "diffuse",
        "brick_rough.png": "roughness",
        "Metal_Metalness.png": "metalness",
        "wood_nor_dx_1k.png": "normal",
        "tile_Glossiness.png": "glossiness",
        "mesh_Opacity.png": "opacity",
        "x_AmbientOcclusion.png": "ignore",
        "x_Displacement.png": "height",
        "readme.png": None,
    }
    for name, kind in cases.items():
        assert classify(Path(name)) == kind, name


def test_metallic_folder_with_directx_normal(tmp_path):
    # a tilt toward +x and +y in OpenGL; the DirectX file stores −y, so green must be flipped back
    n_gl = torch.tensor([0.3, 0.4, (1 - 0.25) ** 0.5]).view(3, 1, 1).expand(3, 8, 8)
    n_dx = n_gl * torch.tensor([1.0, -1.0, 1.0]).view(3, 1, 1)
    base = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    metal = (torch.arange(8) >= 4).float().view(1, 1, 8).expand(1, 8, 8)
    rough = torch.full((1, 8, 8), 0.6)
    folder = tmp_path / "Metal007"
    folder.mkdir()
    write_image(folder / "Metal007_1K_Color.png", _hwc(linear_to_srgb(base)), bits=16)
    write_image(folder / "Metal007_1K_NormalDX.png", _hwc((n_dx + 1) / 2), bits=16)
    write_image(folder / "Metal007_1K_Roughness.png", _hwc(rough), bits=16)
    write_image(folder / "Metal007_1K_Metalness.png", _hwc(metal), bits=16)
    write_image(folder / "Metal007_1K_AmbientOcclusion.png", _hwc(rough), bits=8)
    maps = read_any(folder)
    torch.testing.assert_close(maps.normal, n_gl, atol=1e-4, rtol=0)
    d, s = metallic_to_specular(base, metal)
    torch.testing.assert_close(maps.diffuse, d, atol=1e-4, rtol=0)
    torch.testing.assert_close(maps.specular, s, atol=1e-4, rtol=0)
    torch.testing.assert_close(maps.roughness, rough, atol=1e-4, rtol=0)


def test_specular_gloss_folder_and_explicit_convention(tmp_path):
    folder = tmp_path / "lib"
    folder.mkdir()
    n = torch.tensor([0.0, 0.6, 0.8]).view(3, 1, 1).expand(3, 4, 4)
    write_image(folder / "a_diffuse.png", _hwc(torch.full((3, 4, 4), 0.5)), bits=8)
    write_image(folder / "a_specular.png", _hwc(torch.full((3, 4, 4), 0.2)), bits=8)
    write_image(folder / "a_gloss.png", _hwc(torch.full((1, 4, 4), 0.75)), bits=16)
    write_image(folder / "a_normal.png", _hwc((n + 1) / 2), bits=16)
    maps = read_map_folder(folder)
    torch.testing.assert_close(maps.roughness, torch.full((1, 4, 4), 0.25), atol=1e-4, rtol=0)
    assert float(maps.normal[1, 0, 0]) == pytest.approx(0.6, abs=1e-4)
    flipped = read_map_folder(folder, normal_convention="directx")
    assert float(flipped.normal[1, 0, 0]) == pytest.approx(-0.6, abs=1e-4)


def test_deschaintre_panels(tmp_path):
    maps = random_maps(16, seed=2)
    photo = torch.zeros(3, 16, 16)
    panels = [
        photo,
        (maps.normal + 1) / 2,
        linear_to_srgb(maps.diffuse),
        maps.roughness.expand(3, 16, 16),
        linear_to_srgb(maps.specular),
    ]
    write_image(tmp_path / "0001.png", _hwc(torch.cat(panels, dim=-1)), bits=16)
    back = read_deschaintre(tmp_path / "0001.png")
    torch.testing.assert_close(back.diffuse, maps.diffuse, atol=2e-4, rtol=0)
    torch.testing.assert_close(back.specular, maps.specular, atol=2e-4, rtol=0)
    torch.testing.assert_close(back.roughness, maps.roughness, atol=2e-5, rtol=0)
    torch.testing.assert_close(back.normal, maps.normal, atol=1e-4, rtol=0)
    write_image(tmp_path / "bad.png", np.zeros((16, 48, 3)), bits=8)
    with pytest.raises(MatscanError, match=r"bad\.png: a panel image is 4 or 5 square panels"):
        read_deschaintre(tmp_path / "bad.png")


def test_matscan_mapset_and_unknown_layout(tmp_path):
    maps = random_maps(8)
    write_mapset(tmp_path / "ours", maps)
    torch.testing.assert_close(read_any(tmp_path / "ours").roughness, maps.roughness, atol=1e-4, rtol=0)
    (tmp_path / "odd").mkdir()
    write_image(tmp_path / "odd" / "picture.png", np.zeros((4, 4, 3)))
    write_image(tmp_path / "odd" / "x_normal.png", np.zeros((4, 4, 3)))
    with pytest.raises(MatscanError, match=r"odd: not a map folder .*found picture\.png, x_normal\.png"):
        read_any(tmp_path / "odd")


def test_a_matscan_mapset_missing_a_map_says_which(tmp_path):
    # not read as another layout, where a confidence_normal.png passed for the normal map
    write_mapset(tmp_path / "ours", random_maps(8))
    write_image(tmp_path / "ours" / "confidence_normal.png", np.zeros((8, 8, 1)))
    (tmp_path / "ours" / "normal.png").unlink()
    with pytest.raises(MatscanError, match=r"ours: no normal map \(expected normal.png"):
        read_any(tmp_path / "ours")


def test_an_unknown_normal_convention_is_refused_whatever_the_layout(tmp_path):
    # it used to be checked only where a library folder's normal map was read
    from matscan.export import export_maps

    folder = write_mapset(tmp_path / "set", random_maps(8))
    with pytest.raises(MatscanError, match="normal_convention: 'x' is not one of auto, opengl, directx"):
        read_any(folder, normal_convention="x")
    with pytest.raises(MatscanError, match="normal_convention: 'x'"):
        export_maps(folder, tmp_path / "out", normal_convention="x")
    assert not (tmp_path / "out").exists()
