"""Training map sets from licensed surface photos: the photo rules against closed forms,
and tools/photo_library.py end to end on a .deb built here with dpkg-deb."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from matscan.errors import MatscanError
from matscan.imagefile import write_image
from matscan.materials.library import read_any
from matscan.materials.photos import FIELD_MM, RELIEF_MM, maps_from_photo

TOOL = Path(__file__).resolve().parent.parent / "tools" / "photo_library.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("photo_library", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_luminance_ramp_tilts_the_normal_by_the_relief_over_the_field():
    size = 128
    ramp = torch.linspace(0, 1, size).expand(size, size)
    # made periodic (up, then down) so the tileable blur and differences see no seam
    tri = torch.cat([ramp[:, ::2], ramp[:, ::2].flip(-1)], dim=1)
    maps = maps_from_photo(tri.expand(3, -1, -1).clone())
    slope = 2 * RELIEF_MM / FIELD_MM  # the relief rises over half the field
    nx = maps.normal[0, :, size // 8 : 3 * size // 8]  # the rising half, away from the turns
    assert float(nx.mean()) == pytest.approx(-slope / (1 + slope**2) ** 0.5, rel=0.05)
    assert float(maps.normal[1].abs().max()) < 1e-4  # no change along y
    assert float(maps.roughness.min()) >= 0.45 - 1e-6 and float(maps.roughness.max()) <= 0.85 + 1e-6


def test_the_diffuse_keeps_the_photos_hue_and_a_grey_photo_gets_its_range():
    grey = torch.rand(1, 64, 64, generator=torch.Generator().manual_seed(1)).expand(3, -1, -1).clone()
    maps = maps_from_photo(grey)
    d = maps.diffuse
    assert torch.equal(d[0], d[1]) and torch.equal(d[1], d[2])
    assert float(d.min()) == pytest.approx(0.05, abs=1e-6) and float(d.max()) == pytest.approx(0.75, abs=1e-6)
    tinted = grey * torch.tensor([1.0, 0.5, 0.25]).view(3, 1, 1)
    d = maps_from_photo(tinted).diffuse
    # linear ratios of the channels are those of the photo decoded from sRGB
    from matscan.color import srgb_to_linear

    want = srgb_to_linear(tinted[1]) / srgb_to_linear(tinted[0])
    lit = (tinted[0] > 0.2) & (d.max(0).values < 1)  # where no channel is clipped at 1
    assert int(lit.sum()) > 100
    assert torch.allclose((d[1] / d[0])[lit], want[lit], rtol=1e-3)
    with pytest.raises(MatscanError, match=r"\(3, H, W\)"):
        maps_from_photo(grey[0])


@pytest.mark.skipif(shutil.which("dpkg-deb") is None, reason="needs dpkg-deb (Debian)")
def test_the_tool_builds_readable_map_sets_and_names_their_sources(tmp_path):
    tool = load_tool()
    pkg = tmp_path / "pkg"
    rng = np.random.default_rng(0)
    assert not {p for p, _, _ in tool.PHOTOS.values()} & {p for p, _, _ in tool.SELECTION.values()}
    for i, (path, _, _) in enumerate([*tool.PHOTOS.values(), *tool.SELECTION.values()]):
        f = pkg / tool.ROOT.removeprefix("./") / path
        f.parent.mkdir(parents=True, exist_ok=True)
        img = rng.random((40 + i, 48, 3)).astype(np.float32)  # not square: the centre square is taken
        write_image(f.with_suffix(".png"), img, bits=8)
        if f.suffix != ".png":
            f.with_suffix(".png").rename(f)  # the reader goes by content, not only the name
    (pkg / "DEBIAN").mkdir()
    (pkg / "DEBIAN" / "control").write_text(
        "Package: supertuxkart-data\nVersion: 0.test\nArchitecture: all\nMaintainer: t <t@t>\nDescription: t\n"
    )
    deb = tmp_path / "supertuxkart-data_0.test_all.deb"
    subprocess.run(["dpkg-deb", "--build", "--root-owner-group", str(pkg), str(deb)], check=True, capture_output=True)
    out = tmp_path / "library"
    assert tool.main([str(out), "--deb", str(deb), "--size", "32"]) == 0
    folders = sorted(p for p in out.iterdir() if p.is_dir())
    assert [p.name for p in folders] == sorted(tool.PHOTOS)
    for folder in folders:
        maps = read_any(folder)
        assert maps.size == (32, 32)
        assert torch.allclose(maps.normal.norm(dim=0), torch.ones(32, 32), atol=2e-3)
    sources = (out / "SOURCES.md").read_text()
    for name, (path, licence, _) in tool.PHOTOS.items():
        assert f"| {name} | `{path}` | {licence} |" in sources
    # the selection sets: their own photos and their own heading, never the training ones
    chosen = tmp_path / "selection"
    assert tool.main([str(chosen), "--deb", str(deb), "--size", "32", "--selection"]) == 0
    assert sorted(p.name for p in chosen.iterdir() if p.is_dir()) == sorted(tool.SELECTION)
    sources = (chosen / "SOURCES.md").read_text()
    assert "never for training" in sources.splitlines()[0]
    for name, (path, licence, _) in tool.SELECTION.items():
        assert f"| {name} | `{path}` | {licence} |" in sources
    assert not any(f"`{path}`" in sources for path, _, _ in tool.PHOTOS.values())
    # a second run refuses the folder it filled; a .deb without the photos is named
    assert tool.main([str(out), "--deb", str(deb)]) == 1
    empty = tmp_path / "empty"
    (empty / "DEBIAN").mkdir(parents=True)
    (empty / "DEBIAN" / "control").write_text((pkg / "DEBIAN" / "control").read_text())
    bad = tmp_path / "bad.deb"
    subprocess.run(["dpkg-deb", "--build", "--root-owner-group", str(empty), str(bad)], check=True, capture_output=True)
    assert tool.main([str(tmp_path / "x"), "--deb", str(bad)]) == 1


def test_a_training_config_draws_from_a_library_and_refuses_a_missing_one(tmp_path):
    from matscan.data import SvbrdfDataset
    from matscan.mapset import write_mapset
    from matscan.train import TrainConfig, data_config

    photo = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(2))
    folder = write_mapset(tmp_path / "rock", maps_from_photo(photo))
    cfg = TrainConfig.from_dict({"library": [str(folder)], "library_prob": 1.0, "crop": 32})
    data = data_config(cfg)
    assert data.library == (str(folder),) and data.library_prob == 1.0
    sample = SvbrdfDataset(replace(data, compile=False))[0]
    assert sample["inputs"].shape[-2:] == (32, 32)
    # the sample came from the library: the photo rule's F0 of 0.04 everywhere (8-bit sRGB
    # in the file), where the procedural prior's materials vary
    assert torch.allclose(sample["specular"], torch.full_like(sample["specular"], 0.04), atol=2e-3)
    with pytest.raises(MatscanError, match="no such map set folder"):
        data_config(TrainConfig.from_dict({"library": [str(tmp_path / "missing")]}))
    with pytest.raises(MatscanError, match="library_prob"):
        data_config(TrainConfig(library_prob=1.5))


def test_metallize_follows_the_gltf_metallic_rules_where_it_puts_metal():
    """Each pixel of a metallized photo map set is the photo rule's dielectric mixed at
    some m in [0, 1] with a glTF full metal (spec. Appendix B at metallic 1: diffuse 0,
    F0 the base colour): diffuse = albedo (1 − m), F0 = 0.04 (1 − m) + base m, with base
    a tabled metal colour times 0.6–1 of structure. m is solved per pixel from the
    diffuse, then the base from F0."""
    from matscan.data import METAL_F0, metallize

    photo = torch.rand(3, 48, 48, generator=torch.Generator().manual_seed(4)) * 0.8 + 0.1
    maps = maps_from_photo(photo)
    full = partial = 0
    for seed in range(12):
        out = metallize(maps, torch.Generator().manual_seed(seed))
        assert torch.equal(out.normal, maps.normal)
        assert (out.roughness <= maps.roughness + 1e-6).all() and (out.roughness >= 0.05 - 1e-6).all()
        m3 = 1 - out.diffuse / maps.diffuse  # the metalness, from diffuse = base (1 − m)
        assert (m3.amax(0) - m3.amin(0)).max() < 1e-5 and (m3 > -1e-6).all() and (m3 < 1 + 1e-6).all()
        m = m3.mean(0)
        base = (out.specular - 0.04 * (1 - m)) / m.clamp_min(1e-12)  # F0 = 0.04 (1 − m) + base m
        assert torch.allclose(out.specular[:, m < 1e-7], torch.tensor(0.04), atol=1e-5)
        metal = m > 1e-3
        if metal.any():
            b = base[:, metal]  # (3, N): one metal's colour at 0.6 to 1 of its value
            match = [c for c in METAL_F0 if torch.allclose(b / b.amax(0), torch.tensor(c)[:, None] / max(c), atol=2e-3)]
            assert len(match) >= 1, f"seed {seed}: base colour {b[:, 0]} is no tabled metal's"
            scale = b / torch.tensor(match[0])[:, None]
            assert (scale >= 0.6 - 1e-3).all() and (scale <= 1 + 1e-3).all()
        full += int((m > 1 - 1e-6).all())
        partial += int(metal.any() and (m < 1e-7).any())
    assert full >= 1 and partial >= 1  # both kinds of sample occur


def test_a_library_run_can_give_a_share_of_its_samples_metal(tmp_path):
    from matscan.data import SvbrdfDataset
    from matscan.mapset import write_mapset
    from matscan.train import TrainConfig, data_config

    photo = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(2))
    folder = write_mapset(tmp_path / "rock", maps_from_photo(photo))
    cfg = TrainConfig.from_dict({"library": [str(folder)], "library_prob": 1.0, "library_metal_prob": 1.0, "crop": 32})
    data = data_config(cfg)
    sample = SvbrdfDataset(replace(data, compile=False))[0]
    assert sample["specular"].max() > 0.3  # a metal's F0, where the photo rule gives 0.04 everywhere
    with pytest.raises(MatscanError, match="library_metal_prob"):
        data_config(TrainConfig(library_metal_prob=-0.1))
