"""Map set folders: every encoding round-trips within its quantisation; bad sets are named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import random_maps

from matscan.color import linear_to_srgb
from matscan.errors import MatscanError
from matscan.imagefile import write_image
from matscan.mapset import MapSet, read_mapset, write_mapset


def full_maps(size=12, seed=0) -> MapSet:
    base = random_maps(size, seed)
    g = torch.Generator().manual_seed(seed + 1)
    return MapSet(
        **base.present(),
        alpha=torch.rand(1, size, size, generator=g),
        metallic=torch.rand(1, size, size, generator=g),
        basecolor=torch.rand(3, size, size, generator=g),
        emissive=torch.rand(3, size, size, generator=g),
        height=torch.randn(1, size, size, generator=g) * 0.3,
    )


def test_png_round_trip_within_quantisation(tmp_path):
    maps = full_maps()
    write_mapset(tmp_path / "m", maps)
    back = read_mapset(tmp_path / "m")
    for name in ("diffuse", "specular", "basecolor", "emissive"):  # 8-bit sRGB
        err = (linear_to_srgb(getattr(back, name)) - linear_to_srgb(getattr(maps, name))).abs().max()
        assert err <= 0.5 / 255 + 1e-6, name
    for name in ("alpha", "metallic"):  # 8-bit linear
        assert (getattr(back, name) - getattr(maps, name)).abs().max() <= 0.5 / 255 + 1e-6
    assert (back.roughness - maps.roughness).abs().max() <= 0.5 / 65535 + 1e-7  # 16-bit
    # 16-bit normals: each component within 1/65535 after renormalising, so under 0.005°
    cross = torch.linalg.cross(back.normal.double(), maps.normal.double(), dim=0).norm(dim=0)
    assert torch.rad2deg(torch.asin(cross)).max() < 0.005
    span = float(maps.height.max() - maps.height.min())
    assert (back.height - maps.height).abs().max() <= span * 0.5 / 65535 + 1e-6
    meta = json.loads((tmp_path / "m" / "mapset.json").read_text())
    assert meta["files"]["normal"]["bits"] == 16 and meta["files"]["diffuse"]["bits"] == 8
    assert "conventions" in meta


def test_exr_round_trip_is_exact(tmp_path):
    maps = full_maps()
    write_mapset(tmp_path / "m", maps, file_format="exr")
    back = read_mapset(tmp_path / "m")
    for name, t in maps.present().items():
        atol = 1e-6 if name == "normal" else 0
        torch.testing.assert_close(getattr(back, name), t, rtol=0, atol=atol)


def test_grey_as_rgb_and_colour_as_grey(tmp_path):
    maps = random_maps(8)
    write_mapset(tmp_path / "m", maps)
    rough = maps.roughness[0].numpy()
    write_image(tmp_path / "m" / "roughness.png", np.stack([rough] * 3, axis=-1), bits=16)
    back = read_mapset(tmp_path / "m")
    assert back.roughness.shape == (1, 8, 8)
    assert (back.roughness - maps.roughness).abs().max() < 1e-4


def test_normal_png_encoding_is_half_plus_half(tmp_path):
    # a normal tilted toward +x by 30° is stored as ((sin 30° + 1)/2, 0.5, (cos 30° + 1)/2)
    n = torch.tensor([0.5, 0.0, 3**0.5 / 2]).view(3, 1, 1).expand(3, 2, 2)
    maps = MapSet(torch.zeros(3, 2, 2), torch.zeros(3, 2, 2), torch.zeros(1, 2, 2), n.clone())
    write_mapset(tmp_path / "m", maps)
    from matscan.imagefile import read_image

    px = read_image(tmp_path / "m" / "normal.png").pixels[0, 0]
    assert px.tolist() == pytest.approx([0.75, 0.5, (3**0.5 / 2 + 1) / 2], abs=1 / 65535)


def test_errors_name_the_file(tmp_path):
    maps = random_maps(8)
    write_mapset(tmp_path / "m", maps)
    (tmp_path / "m" / "normal.png").unlink()
    with pytest.raises(MatscanError, match=r"no normal map .*found diffuse\.png"):
        read_mapset(tmp_path / "m")
    write_mapset(tmp_path / "m", maps, overwrite=True)
    write_image(tmp_path / "m" / "roughness.png", np.zeros((4, 4, 1)), bits=16)
    with pytest.raises(MatscanError, match=r"roughness\.png: is 4×4 pixels but the diffuse map is 8×8"):
        read_mapset(tmp_path / "m")
    write_image(tmp_path / "m" / "roughness.png", np.random.default_rng(0).random((8, 8, 3)), bits=8)
    with pytest.raises(MatscanError, match=r"roughness\.png: a roughness map must be grey"):
        read_mapset(tmp_path / "m")
    write_image(tmp_path / "m" / "roughness.exr", np.zeros((8, 8, 1)), bits=32)
    with pytest.raises(MatscanError, match=r"more than one roughness map"):
        read_mapset(tmp_path / "m")
    with pytest.raises(MatscanError, match="no such map set folder"):
        read_mapset(tmp_path / "nowhere")


def test_output_folder_is_not_clobbered(tmp_path):
    maps = random_maps(4)
    write_mapset(tmp_path / "m", maps)
    with pytest.raises(MatscanError, match="not empty"):
        write_mapset(tmp_path / "m", maps)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize(
    ("name", "values", "words"),
    [
        ("roughness", 1e30, r"roughness\.exr: holds values from .* to 1e\+30; a roughness map's lie within ±1e\+06"),
        ("diffuse", -5e6, r"diffuse\.exr: holds values from -5e\+06 to .*; a diffuse map's lie within ±1e\+06"),
        ("normal", float("nan"), r"normal\.exr: holds NaN or infinite values"),
        ("height", -3e6, r"height\.exr: holds values from -3e\+06 .* mm; a height map's lie within ±1e\+06 mm"),
        ("roughness", 80.0, r"roughness\.exr: holds values from .* to 80; a roughness map's lie within 0 to 1 \(is"),
        ("diffuse", 255.0, r"diffuse\.exr: holds values from .* to 255; a diffuse map's lie within 0 to 1"),
        ("specular", -0.7, r"specular\.exr: holds values from -0\.7 to .*; a specular map's lie within 0 to 1"),
    ],
)
def test_float_map_files_hold_what_their_maps_can(tmp_path, name, values, words):
    """A float file can hold any number; one far past anything its map can mean (units
    mistaken, a blown-up export) is refused naming the file, before it reaches a renderer."""
    write_mapset(tmp_path / "m", full_maps(8), file_format="exr")
    path = tmp_path / "m" / f"{name}.exr"
    t = read_mapset(tmp_path / "m").present()[name].permute(1, 2, 0).numpy().copy()
    t[2, 3] = values
    write_image(path, t, bits=32)
    with pytest.raises(MatscanError, match=words) as info:
        read_mapset(tmp_path / "m")
    assert "\n" not in str(info.value)


def test_float_maps_read_back_as_written(tmp_path):
    # an albedo a little over 1, an emission far over it, a negative ringing: kept as they are
    maps = full_maps(8)
    maps.diffuse[0, 0, 0], maps.emissive[1, 2, 2], maps.emissive[0, 1, 1] = 1.05, 400.0, -1e-6
    write_mapset(tmp_path / "m", maps, file_format="exr")
    back = read_mapset(tmp_path / "m")
    for name, t in maps.present().items():
        torch.testing.assert_close(getattr(back, name), t, rtol=0, atol=1e-6 if name == "normal" else 0)


def test_library_float_maps_are_checked_as_matscans(tmp_path):
    from matscan.materials.library import read_map_folder

    lib = tmp_path / "Rock01"
    lib.mkdir()
    write_image(lib / "Rock01_Color.exr", np.full((8, 8, 3), 0.4, np.float32), bits=32)
    write_image(lib / "Rock01_NormalGL.png", np.full((8, 8, 3), 0.5, np.float32) + [0, 0, 0.5], bits=8)
    rough = np.full((8, 8, 1), 0.5, np.float32)
    rough[1, 1] = np.nan
    write_image(lib / "Rock01_Roughness.exr", rough, bits=32)
    with pytest.raises(MatscanError, match=r"Rock01_Roughness\.exr: holds NaN or infinite values"):
        read_map_folder(lib)
    write_image(lib / "Rock01_Roughness.exr", np.full((8, 8, 1), 1e9, np.float32), bits=32)
    with pytest.raises(MatscanError, match=r"Rock01_Roughness\.exr: holds values from 1e\+09 to 1e\+09"):
        read_map_folder(lib)
    write_image(lib / "Rock01_Roughness.exr", np.full((8, 8, 1), 0.5, np.float32), bits=32)
    write_image(lib / "Rock01_Metalness.exr", np.full((8, 8, 1), 100.0, np.float32), bits=32)  # percent
    with pytest.raises(MatscanError, match=r"Rock01_Metalness\.exr: .* to 100; a metalness map's lie within 0 to 1"):
        read_map_folder(lib)


def test_write_maps_never_leaves_a_torn_mapset_json(tmp_path, monkeypatch):
    # a write that breaks half way (disk full, a kill) leaves the old mapset.json whole
    from pathlib import Path

    from matscan.mapset import write_maps

    folder = write_mapset(tmp_path / "set", random_maps(8, 0))
    before = (folder / "mapset.json").read_text(encoding="utf-8")
    real = Path.write_text

    def torn(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", torn)
    with pytest.raises((OSError, MatscanError)):  # MatscanError: the one line the commands print
        write_maps(folder, random_maps(8, 1))
    monkeypatch.undo()
    assert (folder / "mapset.json").read_text(encoding="utf-8") == before
    json.loads(before)


def test_map_channel_counts(tmp_path):
    """Grey + alpha and RGB + alpha read as grey and RGB (the alpha dropped); five
    channels (a TIFF with extra samples) is refused naming the file."""
    import tifffile

    maps = random_maps(8)
    write_mapset(tmp_path / "m", maps)
    rough = maps.roughness[0].numpy()
    codes = np.rint(rough * 65535).astype(np.uint16)
    (tmp_path / "m" / "roughness.png").unlink()
    tifffile.imwrite(
        tmp_path / "m" / "roughness.tif",
        np.stack([codes, np.full_like(codes, 65535)], axis=-1),
        photometric="minisblack",
        extrasamples=["unassalpha"],
    )
    back = read_mapset(tmp_path / "m")
    assert back.roughness.shape == (1, 8, 8)
    np.testing.assert_allclose(back.roughness[0].numpy(), codes / 65535, atol=1e-6)
    tifffile.imwrite(
        tmp_path / "m" / "roughness.tif", np.zeros((8, 8, 5), np.uint8), photometric="minisblack", planarconfig="contig"
    )
    with pytest.raises(MatscanError, match=r"roughness\.tif: has 5 channels; a map has 1 \(grey\) or 3"):
        read_mapset(tmp_path / "m")
    (tmp_path / "m" / "roughness.tif").unlink()
    write_mapset(tmp_path / "n", maps)  # an XY normal map (two channels) is no grey + alpha
    (tmp_path / "n" / "normal.png").unlink()
    two = np.zeros((8, 8, 2), np.uint8)
    tifffile.imwrite(tmp_path / "n" / "normal.tif", two, photometric="minisblack", extrasamples=["unassalpha"])
    with pytest.raises(MatscanError, match=r"normal\.tif: has 2 channels; a normal map needs 3"):
        read_mapset(tmp_path / "n")


def test_write_maps_that_fails_part_way_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    """A write that fails on one map (a full disk) replaced the maps written before it,
    leaving new diffuse and specular beside an old roughness and the old mapset.json."""
    import matscan.mapset as mapset

    folder = write_mapset(tmp_path / "set", random_maps(8, 0))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    real = mapset.write_image

    def full_disk(path, *args, **kwargs):
        if Path(path).name.startswith(".roughness.png"):
            raise MatscanError(f"{path}: no space left on the device; nothing was written")
        real(path, *args, **kwargs)

    monkeypatch.setattr(mapset, "write_image", full_disk)
    with pytest.raises(MatscanError, match="no space left"):
        mapset.write_maps(folder, random_maps(8, 1))
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before  # no temporaries either
    monkeypatch.undo()
    mapset.write_maps(folder, random_maps(8, 1))
    assert (folder / "diffuse.png").read_bytes() != before["diffuse.png"]
    torch.testing.assert_close(read_mapset(folder).roughness, random_maps(8, 1).roughness, rtol=0, atol=1e-4)


def test_a_full_disk_while_writing_maps_names_the_map(tmp_path, monkeypatch):
    """The error named the hidden temporary the map was being written to (gone by then)."""
    import errno

    from matscan.mapset import write_maps

    folder = write_mapset(tmp_path / "set", random_maps(8, 0))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    real = Path.write_bytes

    def full(self, data):
        if "roughness.png" in self.name:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    with pytest.raises(MatscanError) as info:
        write_maps(folder, random_maps(8, 1))
    assert str(info.value) == f"{folder / 'roughness.png'}: no space left on the device; nothing was written"
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
