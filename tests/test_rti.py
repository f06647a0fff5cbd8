"""RTI light files and captures (matscan.capture.rti), the HSH baseline (matscan.hsh),
and the real RTI capture in tests/data/rti-icon (72 photos, MIT licence; README there)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from matscan.capture import load_capture
from matscan.capture.rti import import_rti, lp_text, normal_curl, parse_lp, read_lp, rig_from_lp
from matscan.cli import main
from matscan.errors import MatscanError
from matscan.hsh import fit_hsh, hsh_basis, relight_hsh
from matscan.reconstruct.surface import normals_from_height
from matscan.rig import builtin_rig, load_rig

ICON = Path(__file__).parent / "data" / "rti-icon"


def test_reads_the_real_light_file():
    lights = read_lp(ICON / "dirs.lp")
    assert len(lights.files) == 72 and lights.warnings == ()
    assert lights.files[0] == "image01.jpg" and lights.files[-1] == "image72.jpg"
    # the first line of the file, by hand: image01.jpg 0.205158607891401 -0.237020612397229 0.949595268999854
    norm = math.sqrt(0.205158607891401**2 + 0.237020612397229**2 + 0.949595268999854**2)
    assert lights.directions[0] == pytest.approx(
        (0.205158607891401 / norm, -0.237020612397229 / norm, 0.949595268999854 / norm)
    )
    down = read_lp(ICON / "dirs.lp", y="down")
    assert down.directions[0][1] == pytest.approx(-lights.directions[0][1])


def test_quirks_of_the_format():
    text = "3 \r\n\r\nC:\\dome\\shots\\a.jpg\t0.6 0 0.8  \r\n  b.jpg 0 0.6 0.8\r\n\r\n"
    lights = parse_lp(text, "x.lp")
    assert lights.files == ("a.jpg", "b.jpg")  # Windows path reduced to its name, blank lines skipped
    assert lights.directions[1] == pytest.approx((0.0, 0.6, 0.8))
    assert lights.warnings == ("x.lp: says 3 photos but lists 2; using the 2 listed",)
    # no count line at all; a slightly unnormalised direction is normalised
    lights = parse_lp("a.png 0 0 1.01\nb.png 0.6 0 0.8\n")
    assert lights.directions[0] == pytest.approx((0.0, 0.0, 1.0)) and lights.warnings == ()
    # file names with spaces keep them
    assert parse_lp("1\nmy photo 1.jpg 0 0 1\n").files == ("my photo 1.jpg",)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "x.lp: is empty"),
        ("2\na.jpg 0 0\n", "x.lp: line 2: expected 'FILE x y z'"),
        ("2\na.jpg 0 zero 1\n", "x.lp: line 2: '0 zero 1' is not three numbers"),
        ("a.jpg 0 0 2\n", "x.lp: line 1: direction (0, 0, 2) has length 2.000, not 1"),
        ("a.jpg 0.6 0 -0.8\n", "at or below the sample plane"),
        ("a.jpg 0 0 1\na.jpg 0 0 1\n", "a.jpg is listed twice"),
        ("two\na.jpg 0 0 1\n", "'two' is not a count of photos"),
        ("3\n", "lists no photos"),
    ],
)
def test_bad_light_files_are_named(text, message):
    with pytest.raises(MatscanError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_lp(text, "x.lp")


def test_lp_round_trip_of_a_rig():
    lights = read_lp(ICON / "dirs.lp")
    rig = rig_from_lp(lights, (80.0, 78.6))
    again = parse_lp(lp_text(rig, lights.files))
    assert again.files == lights.files
    np.testing.assert_allclose(np.array(again.directions), np.array(lights.directions), atol=1e-8)
    # y flips on the way out and back in
    flipped = parse_lp(lp_text(rig, lights.files, y="down"), y="down")
    np.testing.assert_allclose(np.array(flipped.directions), np.array(lights.directions), atol=1e-8)
    # dome24's LEDs are written as directions from the field's centre: LED 0 at 22.5° elevation
    dome = parse_lp(lp_text(builtin_rig("dome24")))
    assert dome.directions[0] == pytest.approx((math.cos(math.radians(22.5)), 0.0, math.sin(math.radians(22.5))))


def test_import_rti_copies_and_never_modifies(tmp_path):
    before = {p.name: p.read_bytes() for p in ICON.iterdir()}
    out, warnings = import_rti(ICON, tmp_path / "cap", field_width_mm=80.0)
    assert warnings == []
    assert {p.name: p.read_bytes() for p in ICON.iterdir()} == before
    cap = load_capture(out)
    assert len(cap.files) == 72 and cap.size == (395, 402)
    assert cap.field_mm == pytest.approx((80.0, 80.0 * 395 / 402))
    assert cap.rig.camera.orthographic and all(lt.directional for lt in cap.rig.lights)
    assert (out / "image01.jpg").read_bytes() == (ICON / "image01.jpg").read_bytes()
    rig = load_rig(out / "rig.json")
    assert rig.lights[0].direction == pytest.approx(read_lp(ICON / "dirs.lp").directions[0])


def test_import_rti_names_a_missing_photo(tmp_path):
    folder = tmp_path / "rti"
    folder.mkdir()
    for name in ("image01.jpg", "image02.jpg"):
        (folder / name).write_bytes((ICON / name).read_bytes())
    (folder / "lights.lp").write_text("3\nimage01.jpg 0 0 1\nimage02.jpg 0.6 0 0.8\nimage03.jpg 0 0.6 0.8\n")
    with pytest.raises(MatscanError, match=r"image03.jpg: is listed in lights.lp but missing"):
        import_rti(folder, tmp_path / "cap")
    assert not (tmp_path / "cap").exists()


def test_cli_rig_from_lp_and_to_lp(tmp_path, capsys):
    assert main(["rig", "from-lp", str(ICON / "dirs.lp"), "--out", str(tmp_path / "rig.json")]) == 0
    rig = load_rig(tmp_path / "rig.json")
    assert len(rig.lights) == 72
    assert main(["rig", "to-lp", str(tmp_path / "rig.json"), "--out", str(tmp_path / "out.lp")]) == 0
    np.testing.assert_allclose(
        np.array(parse_lp((tmp_path / "out.lp").read_text()).directions),
        np.array(read_lp(ICON / "dirs.lp").directions),
        atol=1e-8,
    )
    assert main(["rig", "from-lp", str(tmp_path / "nothing.lp"), "--out", str(tmp_path / "r2.json")]) == 2
    assert "nothing.lp: no such light file" in capsys.readouterr().err


def test_cli_rig_to_lp_of_a_capture_names_its_photos(tmp_path):
    # a rig file holds no photo names; an imported capture gives them back to RTI software
    folder = tmp_path / "rti"
    folder.mkdir()
    lines = ["image01.jpg 0 0 1", "image02.jpg 0.6 0 0.8", "image03.jpg 0 0.6 0.8"]
    for line in lines:
        name = line.split()[0]
        (folder / name).write_bytes((ICON / name).read_bytes())
    (folder / "lights.lp").write_text("3\n" + "\n".join(lines) + "\n")
    import_rti(folder, tmp_path / "cap")
    assert main(["rig", "to-lp", str(tmp_path / "cap"), "--out", str(tmp_path / "back.lp")]) == 0
    back, given = parse_lp((tmp_path / "back.lp").read_text()), read_lp(folder / "lights.lp")
    assert back.files == given.files == ("image01.jpg", "image02.jpg", "image03.jpg")
    np.testing.assert_allclose(np.array(back.directions), np.array(given.directions), atol=1e-8)


def _three_photos(folder: Path, names=("image01.jpg", "image02.jpg", "image03.jpg")) -> None:
    folder.mkdir()
    directions = ("0 0 1", "0.6 0 0.8", "0 0.6 0.8")
    for name, source in zip(names, ("image01.jpg", "image02.jpg", "image03.jpg"), strict=True):
        (folder / name).write_bytes((ICON / source).read_bytes())
    lines = [f"{n} {d}" for n, d in zip(names, directions, strict=True)]
    (folder / "lights.lp").write_text("3\n" + "\n".join(lines) + "\n")


def test_import_rti_writes_only_what_a_capture_can_hold(tmp_path, capsys):
    """What the capture's own checks would refuse is refused before anything is written:
    a field wider than a rig file allows, a photo name with a control character."""
    _three_photos(tmp_path / "rti")
    argv = ["import-rti", str(tmp_path / "rti"), "--out", str(tmp_path / "cap")]
    assert main([*argv, "--field-width-mm", "2e6"]) == 2
    assert "must be a number of mm above 0 and at most 1e+06" in capsys.readouterr().err
    _three_photos(tmp_path / "odd", names=("a\x07.jpg", "b.jpg", "c.jpg"))
    assert main(["import-rti", str(tmp_path / "odd"), "--out", str(tmp_path / "cap")]) == 2
    err = capsys.readouterr().err.strip()
    assert "lights.lp: 'a\\x07.jpg'" in err and "not a usable file name" in err and "\n" not in err
    assert not (tmp_path / "cap").exists()


def test_a_light_file_in_the_windows_code_page_finds_its_photos(tmp_path):
    """An .lp written by an RTI tool on Windows holds accented photo names in Windows-1252;
    the photos, copied to this system, have them in UTF-8."""
    _three_photos(tmp_path / "rti", names=("étude01.jpg", "étude02.jpg", "étude03.jpg"))
    lp = tmp_path / "rti" / "lights.lp"
    lp.write_bytes(lp.read_text(encoding="utf-8").encode("cp1252"))
    lights = read_lp(lp)
    assert lights.files == ("étude01.jpg", "étude02.jpg", "étude03.jpg")
    assert "read as Windows-1252" in lights.warnings[0]
    out, warnings = import_rti(tmp_path / "rti", tmp_path / "cap")
    assert len(load_capture(out).files) == 3 and any("Windows-1252" in w for w in warnings)


def test_a_light_file_with_a_byte_order_mark_reads(tmp_path):
    _three_photos(tmp_path / "rti")
    lp = tmp_path / "rti" / "lights.lp"
    lp.write_bytes(b"\xef\xbb\xbf" + lp.read_bytes())
    assert read_lp(lp).files == ("image01.jpg", "image02.jpg", "image03.jpg") and not read_lp(lp).warnings


def test_rig_from_lp_writes_rigs_that_load(tmp_path, capsys):
    _three_photos(tmp_path / "rti")
    odd = tmp_path / "a\tb.lp"
    odd.write_text((tmp_path / "rti" / "lights.lp").read_text())
    assert main(["rig", "from-lp", str(odd), "--out", str(tmp_path / "rig.json")]) == 0
    assert load_rig(tmp_path / "rig.json").name == "a_b"  # the control character made printable
    argv = ["rig", "from-lp", str(odd), "--out", str(tmp_path / "big.json"), "--field-mm", "1e308,1e308"]
    assert main(argv) == 2
    assert "at most 1e+06 mm" in capsys.readouterr().err and not (tmp_path / "big.json").exists()


def test_hsh_fits_its_own_span_exactly_and_matches_numpy():
    g = torch.Generator().manual_seed(1)
    k = 30
    z = 0.1 + 0.9 * torch.rand(k, generator=g)
    phi = 2 * math.pi * torch.rand(k, generator=g)
    d = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], 1)
    # images that are a known combination of the basis: recovered exactly, relit exactly
    true = torch.rand(9, 3, 4, 5, generator=g) * 0.1
    basis = hsh_basis(d).float()
    images = (basis @ true.reshape(9, -1)).reshape(k, 3, 4, 5)
    coef = fit_hsh(images, d)
    torch.testing.assert_close(coef, true, atol=1e-5, rtol=0)
    # a Lambertian pixel under lights fitted by numpy's least squares on the same basis
    y = (0.3 * d[:, 2] + 0.1 * d[:, 0]).double().numpy()
    ref, *_ = np.linalg.lstsq(hsh_basis(d).numpy(), y, rcond=None)
    ours = fit_hsh(torch.as_tensor(y, dtype=torch.float32).view(k, 1, 1, 1), d)[:, 0, 0, 0]
    np.testing.assert_allclose(ours.numpy(), ref, atol=1e-5)
    new = torch.tensor([[0.0, 0.0, 1.0]])
    assert float(relight_hsh(coef, new).max()) <= 1.0
    with pytest.raises(MatscanError, match="at least 9 photos"):
        fit_hsh(images[:8], d[:8])


def test_curl_tells_a_surface_from_its_mirror():
    g = torch.Generator().manual_seed(3)
    height = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 70, 70, generator=g), 5, 1)[0, 0] * 2
    n = normals_from_height(height, 0.2)
    mirrored = n.clone()
    mirrored[1] = -mirrored[1]
    assert normal_curl(n) < 0.1 < 0.5 < normal_curl(mirrored)


@pytest.fixture(scope="module")
def icon_half(tmp_path_factory):
    """The real capture at half its photos' size (2 × 2 means, 201 × 198; re-encoded as
    JPEG at quality 95): a quarter of the solver's time, the same conclusions (below)."""
    from PIL import Image

    half = tmp_path_factory.mktemp("rti") / "half"
    half.mkdir()
    (half / "dirs.lp").write_bytes((ICON / "dirs.lp").read_bytes())
    for photo in sorted(ICON.glob("*.jpg")):
        with Image.open(photo) as image:
            image.reduce(2).save(half / photo.name, quality=95)
    return half


def test_icon_leave_out_validation_beats_hsh(icon_half, tmp_path):
    """Every 4th photo of the real capture held out (18 of 72): the solver's maps relight
    them better than an order-2 HSH fit to the same 54 photos (docs/rti.md gives the full
    size's numbers; at half size 29.7 against 22.6 dB, SSIM 0.935 against 0.902 when written)."""
    from matscan.reconstruct import ReconstructConfig
    from matscan.reconstruct.job import reconstruct

    capture, _ = import_rti(icon_half, tmp_path / "cap")
    rec = reconstruct(capture, tmp_path / "out", ReconstructConfig(validate=18))
    val = rec["validation"]
    assert val["left_out"][:3] == ["image03.jpg", "image07.jpg", "image11.jpg"]
    assert val["psnr_left_out"] > val["hsh"]["psnr_left_out"] + 3
    assert val["ssim_left_out"] > val["hsh"]["ssim_left_out"]
    assert 0.8 < val["ssim_left_out"] <= 1
    assert (tmp_path / "out" / "report.html").is_file()


def test_icon_y_convention_by_curl(icon_half, tmp_path):
    """Both readings of the file's y relight equally well; the default gives the normal
    field with less curl (LP_Y_DEFAULT): 1.13 against 1.67 when written, as at full size."""
    from matscan.reconstruct.job import reconstruct_capture

    up, _ = import_rti(icon_half, tmp_path / "up")
    down, _ = import_rti(icon_half, tmp_path / "down", y="down")
    res_up = reconstruct_capture(load_capture(up))
    res_down = reconstruct_capture(load_capture(down))
    assert normal_curl(res_up.maps.normal) < 0.9 * normal_curl(res_down.maps.normal)
