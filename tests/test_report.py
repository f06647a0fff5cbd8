"""report.html in headless Chromium: no console errors, the viewer draws, and moving the light changes it."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from matscan.capture.virtual import CameraModel, simulate
from matscan.imagefile import read_image
from matscan.mapset import read_mapset
from matscan.reconstruct import ReconstructConfig, reconstruct
from matscan.rig import builtin_rig
from matscan.samples import sample_maps_path

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = [
    "--headless=new",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    "--window-size=700,1400",
    "--virtual-time-budget=8000",
    "--enable-logging=stderr",
    "--v=0",
]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    simulate(
        read_mapset(sample_maps_path()),
        builtin_rig("dome24"),
        tmp / "cap",
        lights=[0, 4, 8, 12, 16, 20],
        size=64,
        camera=CameraModel(read_noise=0.001),
    )
    reconstruct(tmp / "cap", tmp / "out", ReconstructConfig(model="none", refine_steps=10, exr=True))
    return tmp / "out" / "report.html"


def test_report_content(report):
    text = report.read_text()
    assert text.count("alt='photo'") == 6 and text.count("alt='re-rendering'") == 6
    assert "http://" not in text and "https://" not in text  # nothing fetched: works offline
    assert "u_light" in text  # the viewer's shader is inlined
    # the title names the capture, not a path on this machine
    assert re.search(r"<title>matscan report: cap</title>", text)
    # every file written is linked (the exr/ folder's too), and every link leads to a file
    links = re.findall(r"<a href='([^']+)'>", text)
    written = {p.relative_to(report.parent).as_posix() for p in report.parent.rglob("*") if p.is_file()} - {
        "report.html"
    }
    assert "exr/diffuse.exr" in written
    assert set(links) == written, set(links) ^ written
    # the conventions are stated on the page, as matscan.json records them
    import json

    conventions = json.loads((report.parent / "matscan.json").read_text())["conventions"]
    for key in ("normal", "roughness", "colour"):
        assert f"<th>{key}</th>" in text and conventions[key].split(";")[0].split(",")[0][:20] in text


def _chromium(args, tmp_path):
    proc = subprocess.run(
        [CHROMIUM, *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    return proc


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (make test installs it)")
def test_viewer_in_headless_chromium(report, tmp_path):
    dom = {}
    for name, light in (("left", "-150,0,150"), ("right", "150,0,150")):
        proc = _chromium(["--dump-dom", f"file://{report}?light={light}&stats=1"], tmp_path)
        assert 'data-viewer="ok"' in proc.stdout, proc.stdout[-500:] + proc.stderr[-2000:]
        assert not re.search(r"Uncaught|CONSOLE\(\d+\).*[Ee]rror", proc.stderr), proc.stderr[-2000:]
        mean = float(re.search(r'data-mean="([0-9.]+)"', proc.stdout).group(1))
        std = float(re.search(r'data-std="([0-9.]+)"', proc.stdout).group(1))
        assert mean > 0.02 and std > 0.01  # the canvas is not blank
        dom[name] = mean
        shot = tmp_path / f"{name}.png"
        _chromium([f"--screenshot={shot}", f"file://{report}?light={light}"], tmp_path)
        dom[name + "_png"] = read_image(shot).pixels
    assert dom["left"] != dom["right"]
    changed = np.abs(dom["left_png"] - dom["right_png"]).max(axis=2) > 0.02
    assert changed.mean() > 0.01  # the screenshot changes where the viewer is


def _canvas_mean(page, tmp_path):
    proc = _chromium(["--dump-dom", f"file://{page}?light=0,0,150&stats=1"], tmp_path)
    assert 'data-viewer="ok"' in proc.stdout, proc.stdout[-500:] + proc.stderr[-2000:]
    return float(re.search(r'data-mean="([0-9.]+)"', proc.stdout).group(1))


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (make test installs it)")
def test_viewer_shows_alpha_and_emission(report, tmp_path):
    # the same maps with holes, and glowing: the viewer's canvas must change visibly each time
    import json
    from dataclasses import replace

    import torch

    from matscan.capture import load_capture
    from matscan.report.html import write_report

    out = report.parent
    maps = read_mapset(out)
    capture = load_capture(out.parent / "cap")
    record = json.loads((out / "matscan.json").read_text())
    h, w = maps.size
    holes = torch.ones(1, h, w)
    holes[:, :, : w // 2] = 0  # the left half is a hole: the checkerboard (grey 0.35-0.65) shows
    variants = {
        "plain": replace(maps, alpha=None, emissive=None),
        "holes": replace(maps, alpha=holes, emissive=None),
        "glow": replace(maps, alpha=None, emissive=torch.full((3, h, w), 0.3)),
    }
    means = {}
    for name, variant in variants.items():
        page = tmp_path / f"{name}.html"
        write_report(page, capture, variant, record)
        means[name] = _canvas_mean(page, tmp_path)
    assert means["glow"] > means["plain"] + 0.05  # emission 0.3 adds light everywhere
    assert abs(means["holes"] - means["plain"]) > 0.02


@pytest.fixture(scope="module")
def rti_report(tmp_path_factory):
    """The report of an RTI-style capture: directional lights on rings at 20°, 45° and 70°
    and the zenith (as `rig from-lp` makes them), an orthographic camera."""
    import math

    from matscan.capture.rti import LightFile, rig_from_lp

    directions = [(0.0, 0.0, 1.0)]
    for elevation in (20.0, 45.0, 70.0):
        for k in range(4):
            e, a = math.radians(elevation), math.radians(90.0 * k + elevation)
            directions.append((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)))
    names = tuple(f"image{k:02d}.png" for k in range(len(directions)))
    rig = rig_from_lp(LightFile(names, tuple(directions), ()), field_mm=(40.0, 40.0))
    assert rig.camera_w == 0 and all(light.direction is not None for light in rig.lights)
    tmp = tmp_path_factory.mktemp("rti-report")
    simulate(read_mapset(sample_maps_path()), rig, tmp / "cap", size=64, camera=CameraModel(read_noise=0.001))
    reconstruct(tmp / "cap", tmp / "out", ReconstructConfig(model="none", refine_steps=10, exr=True))
    return tmp / "out" / "report.html"


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (make test installs it)")
def test_viewer_renders_an_rti_capture(rti_report, tmp_path):
    # the page carries the orthographic camera, and the viewer draws it and relights it:
    # a light as far as the rig's reference distance (1 m) gives the lights' irradiance
    text = rti_report.read_text()
    assert re.search(r'"camera_w":\s*0(\.0)?\b', text), "the viewer is not told the camera is orthographic"
    means = {}
    for name, light in (("left", "-700,0,700"), ("right", "700,0,700")):
        proc = _chromium(["--dump-dom", f"file://{rti_report}?light={light}&stats=1"], tmp_path)
        assert 'data-viewer="ok"' in proc.stdout, proc.stdout[-500:] + proc.stderr[-2000:]
        assert not re.search(r"Uncaught|CONSOLE\(\d+\).*[Ee]rror", proc.stderr), proc.stderr[-2000:]
        means[name] = float(re.search(r'data-mean="([0-9.]+)"', proc.stdout).group(1))
        std = float(re.search(r'data-std="([0-9.]+)"', proc.stdout).group(1))
        assert means[name] > 0.02 and std > 0.01  # the canvas is not blank
    assert means["left"] != means["right"]
