"""Image file round trips: 8/16-bit PNG exact codes, EXR and float TIFF exact floats."""

from __future__ import annotations

import numpy as np
import pytest

from matscan.errors import MatscanError
from matscan.imagefile import read_image, write_image


@pytest.mark.parametrize("bits, channels", [(8, 3), (16, 3), (8, 1), (16, 1), (8, 4)])
def test_png_codes_round_trip(tmp_path, bits, channels):
    rng = np.random.default_rng(0)
    top = (1 << bits) - 1
    codes = rng.integers(0, top + 1, size=(7, 5, channels))
    write_image(tmp_path / "x.png", codes / top, bits=bits)
    img = read_image(tmp_path / "x.png")
    assert (img.kind, img.bits) == ("int", bits)
    assert img.pixels.shape == (7, 5, channels)
    np.testing.assert_array_equal(np.rint(img.pixels * top), codes)


def test_png_channel_order_is_rgb(tmp_path):
    red = np.zeros((2, 2, 3))
    red[..., 0] = 1
    write_image(tmp_path / "red.png", red, bits=16)
    px = read_image(tmp_path / "red.png").pixels
    assert px[0, 0].tolist() == [1.0, 0.0, 0.0]


@pytest.mark.parametrize("name", ["x.exr", "x.tif"])
@pytest.mark.parametrize("channels", [1, 3])
def test_float_round_trip_is_exact(tmp_path, name, channels):
    rng = np.random.default_rng(1)
    data = (rng.normal(size=(6, 9, channels)) * 3).astype(np.float32)  # negative and > 1 too
    write_image(tmp_path / name, data, bits=32)
    img = read_image(tmp_path / name)
    assert img.kind == "float"
    np.testing.assert_array_equal(img.pixels, data)


def test_tiff_16_bit(tmp_path):
    codes = np.arange(60, dtype=np.uint16).reshape(4, 5, 3) * 1000
    write_image(tmp_path / "x.tif", codes / 65535.0, bits=16)
    np.testing.assert_array_equal(np.rint(read_image(tmp_path / "x.tif").pixels * 65535), codes)


def test_exr_header(tmp_path):
    import OpenEXR

    write_image(tmp_path / "x.exr", np.zeros((2, 2, 3), np.float32), header={"matscan_map": "diffuse"})
    with OpenEXR.File(str(tmp_path / "x.exr")) as f:
        assert f.header()["matscan_map"] == "diffuse"


def test_write_is_atomic_and_leaves_no_temporaries(tmp_path):
    write_image(tmp_path / "a.png", np.zeros((2, 2, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]
    with pytest.raises(MatscanError):
        write_image(tmp_path / "b.jpg", np.zeros((2, 2, 3)), bits=16)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]


def test_read_errors(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"not a png at all")
    with pytest.raises(MatscanError, match=r"bad\.png: cannot read as PNG"):
        read_image(tmp_path / "bad.png")
    (tmp_path / "bad.exr").write_bytes(b"nope")
    with pytest.raises(MatscanError, match=r"bad\.exr: cannot read as EXR"):
        read_image(tmp_path / "bad.exr")
    with pytest.raises(MatscanError, match=r"gone\.png: no such file"):
        read_image(tmp_path / "gone.png")
    (tmp_path / "shelf.png").mkdir()
    with pytest.raises(MatscanError, match=r"shelf\.png: is a folder, not an image file"):
        read_image(tmp_path / "shelf.png")
    with pytest.raises(MatscanError, match=r"unsupported image type '\.gif'"):
        read_image(tmp_path / "x.gif")


def test_raw_files_need_the_extra_or_a_real_raw(tmp_path):
    (tmp_path / "x.dng").write_bytes(b"not a raw file")
    try:
        import rawpy  # noqa: F401

        words = r"x\.dng: cannot read as DNG"
    except ImportError:
        words = r"x\.dng: reading RAW files needs the 'raw' extra"
    with pytest.raises(MatscanError, match=words):
        read_image(tmp_path / "x.dng")


def test_tiff_planar_and_interleaved_read_alike(tmp_path):
    """A TIFF may store RGB one plane per channel ("planar", as some scanners and
    microscopes write it); read through tifffile's own writer, both layouts give the
    same (H, W, 3) pixels."""
    import tifffile

    rgb = np.random.default_rng(2).integers(0, 65536, size=(6, 9, 3), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "planar.tif", np.moveaxis(rgb, -1, 0), planarconfig="separate", photometric="rgb")
    tifffile.imwrite(tmp_path / "contig.tif", rgb, planarconfig="contig", photometric="rgb")
    for name in ("planar.tif", "contig.tif"):
        img = read_image(tmp_path / name)
        assert img.bits == 16
        np.testing.assert_array_equal(img.stored, rgb)


def test_tiff_stack_is_refused_naming_the_file(tmp_path):
    import tifffile

    grey = np.arange(54, dtype=np.uint8).reshape(6, 9, 1)
    tifffile.imwrite(tmp_path / "one.tif", grey)  # tifffile's own default for (H, W, 1): axes YXQ, one page
    np.testing.assert_array_equal(read_image(tmp_path / "one.tif").stored, grey)

    tifffile.imwrite(tmp_path / "pages.tif", np.zeros((5, 6, 9), np.uint8))  # five grey pages
    with pytest.raises(MatscanError, match=r"pages\.tif: holds a stack of images \(axes QYX"):
        read_image(tmp_path / "pages.tif")
