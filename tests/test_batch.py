"""``matscan batch``: captures on a local Dask cluster, one broken, interrupted and resumed;
the manifest; the catalogue in headless Chromium."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from matscan.batch import cluster_shape, expand_captures, output_names
from matscan.errors import MatscanError

pytest.importorskip("distributed")

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> Path:
    """Four tiny virtual captures (6 lights, 40 px) and one whose photo is missing."""
    from matscan.capture.virtual import CameraModel, simulate
    from matscan.mapset import read_mapset
    from matscan.rig import builtin_rig

    root = tmp_path_factory.mktemp("batch")
    maps = read_mapset("@sample")
    rig = builtin_rig("dome24")
    for i, name in enumerate(("brass", "cork", "denim", "felt")):
        simulate(maps, rig, root / name, lights=rig.subset("6"), camera=CameraModel(read_noise=0.002), seed=i, size=40)
    (root / "torn").mkdir()
    (root / "torn" / "capture.json").write_text(
        json.dumps({"format": "matscan-capture/1", "rig": "dome24", "images": [{"light": 0, "file": "gone.png"}]})
    )
    return root


def test_inputs_and_cluster_shape(captures, tmp_path):
    listing = tmp_path / "list.txt"
    listing.write_text(f"# this week's swatches\n{captures / 'cork'}\n\n{captures / 'brass'}  # the brass one\n")
    found = expand_captures([str(listing), str(captures / "c*"), str(captures / "felt")])
    assert [p.name for p in found] == ["cork", "brass", "felt"]  # each once, in order
    assert output_names([captures / "cork", tmp_path / "cork"]) == ["cork", "cork-2"]
    with pytest.raises(MatscanError, match="is not a capture folder"):
        expand_captures([str(tmp_path)])
    with pytest.raises(MatscanError, match="matches no folder"):
        expand_captures([str(tmp_path / "zz*")])
    assert cluster_shape(None, 2) == (2, 1) and cluster_shape(1, 2) == (1, 2) and cluster_shape(2, 16) == (2, 8)
    from matscan.batch import batch
    from matscan.reconstruct import ReconstructConfig

    with pytest.raises(MatscanError, match="not both"):  # before any work: nothing written
        batch([str(captures / "cork")], tmp_path / "out", workers=2, scheduler="tcp://127.0.0.1:1")
    with pytest.raises(MatscanError, match="no such weights file"):
        batch([str(captures / "cork")], tmp_path / "out", ReconstructConfig(model=str(tmp_path / "nope.safetensors")))
    with pytest.raises(MatscanError, match=f"lies inside the input capture {captures / 'cork'}"):
        batch([str(captures / "cork")], captures / "cork" / "batch")
    assert not (tmp_path / "out").exists() and not (captures / "cork" / "batch").exists()
    with pytest.raises(MatscanError, match="cannot reach"):  # a batch that cannot start leaves nothing
        batch([str(captures / "cork")], tmp_path / "out", scheduler="tcp://127.0.0.1:1")
    assert not (tmp_path / "out").exists()


def _manifest(out: Path) -> dict:
    try:
        return json.loads((out / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}


def test_interrupted_batch_resumes_and_reports_the_broken_capture(captures, tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "matscan.cli", "batch", str(captures / "*"), "--out", str(out), "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        states = [e["state"] for e in _manifest(out).get("captures", {}).values()]
        if "done" in states or proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    first = _manifest(out)["captures"]
    assert len(first) == 5 and sum(e["state"] == "done" for e in first.values()) >= 1
    done_before = {n: (out / n / "matscan.json").stat().st_mtime_ns for n, e in first.items() if e["state"] == "done"}

    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode == 1, again.stderr  # done, but one capture failed
    assert "batch: 4 done, 1 failed of 5" in again.stdout
    manifest = _manifest(out)
    states = {n: e["state"] for n, e in manifest["captures"].items()}
    assert states == {"brass": "done", "cork": "done", "denim": "done", "felt": "done", "torn": "failed"}
    assert "gone.png: no such file" in manifest["captures"]["torn"]["error"]
    for name, mtime in done_before.items():  # finished before the kill: not recomputed
        assert (out / name / "matscan.json").stat().st_mtime_ns == mtime
    for name in ("brass", "cork", "denim", "felt"):
        assert manifest["captures"][name]["rerender_rmse"] < 0.02
        assert (out / name / "report.html").is_file()

    page = (out / "index.html").read_text()
    assert page.count("<tr data-name=") == 5 and "4 done, 1 failed, 0 pending" in page
    assert "gone.png: no such file" in page and "thumbs/cork_relit.png" in page

    # a third run does nothing; --retry-failed runs the broken one again
    mtimes = {n: (out / n / "matscan.json").stat().st_mtime_ns for n in ("brass", "cork", "denim", "felt")}
    third = subprocess.run([*cmd, "--retry-failed"], capture_output=True, text=True, timeout=300)
    assert third.returncode == 1 and "torn: " in third.stderr
    assert {n: (out / n / "matscan.json").stat().st_mtime_ns for n in mtimes} == mtimes
    other = subprocess.run([*cmd, "--validate", "2"], capture_output=True, text=True, timeout=300)
    assert other.returncode == 2 and "other reconstruction settings" in other.stderr


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (make test installs it)")
def test_catalogue_sorts_and_filters_in_chromium(captures, tmp_path):
    from matscan.batch import batch
    from matscan.reconstruct import ReconstructConfig

    out = tmp_path / "out"
    batch(
        [str(captures / "brass"), str(captures / "cork"), str(captures / "torn")], out, ReconstructConfig(), workers=1
    )
    manifest = _manifest(out)["captures"]
    order_by_error = sorted(("brass", "cork"), key=lambda n: manifest[n]["rerender_rmse"])

    def view(query: str) -> tuple[list[str], str]:
        proc = subprocess.run(
            [
                CHROMIUM,
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                f"--user-data-dir={tmp_path / 'p'}",
                "--virtual-time-budget=3000",
                "--dump-dom",
                f"file://{out / 'index.html'}?{query}",
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        order = re.search(r'data-order="([^"]*)"', proc.stdout).group(1)
        shown = re.search(r"(\d+ of \d+) shown", proc.stdout).group(1)
        return (order.split(",") if order else []), shown

    assert view("sort=name") == (["brass", "cork", "torn"], "3 of 3")
    assert view("sort=error") == ([*order_by_error, "torn"], "3 of 3")  # the failed one sorts last
    assert view("sort=error&desc=1")[0] == ["torn", *reversed(order_by_error)]
    assert view("name=co") == (["cork"], "1 of 3")
    limit = manifest[order_by_error[0]]["rerender_rmse"] + 1e-9
    assert view(f"max_error={limit}") == ([order_by_error[0]], "1 of 3")
    # the 6-light captures warn that lights are missing; the torn one counts its error
    assert view("warnings=without") == ([], "0 of 3")
    assert view("warnings=with")[1] == "3 of 3"


def test_a_manifest_from_before_the_shared_f0_default_still_resumes(tmp_path):
    """A manifest written when ``shared_f0`` was False unless asked for: without the
    positions' fit that is today's setting (None) and the batch resumes; with it, False was
    each pixel's own F0, which is ``--own-f0`` today, and the default is refused."""
    from dataclasses import asdict, replace

    from matscan.batch import MANIFEST, MANIFEST_FORMAT, _open_manifest, json_safe
    from matscan.errors import MatscanError
    from matscan.reconstruct import ReconstructConfig

    for positions in (False, True):
        cfg = ReconstructConfig(self_calibrate=positions, self_calibrate_positions=positions)
        now = json_safe(asdict(cfg))
        old = {**now, "shared_f0": False}
        out = tmp_path / f"out{positions}"
        out.mkdir()
        (out / MANIFEST).write_text(json.dumps({"format": MANIFEST_FORMAT, "settings": old, "captures": {}}))
        if positions:
            with pytest.raises(MatscanError, match="other reconstruction settings"):
                _open_manifest(out, now)
            assert _open_manifest(out, json_safe(asdict(replace(cfg, shared_f0=False))))["settings"] == old
        else:
            assert _open_manifest(out, now)["settings"] == old


def test_a_manifest_from_before_calibration_files_resumes_without_one(tmp_path):
    """Settings written before ``calibration`` (``--calibration FILE``) existed named none:
    the batch resumes without one and refuses one."""
    from dataclasses import asdict, replace

    from matscan.batch import MANIFEST, MANIFEST_FORMAT, _open_manifest, json_safe
    from matscan.errors import MatscanError
    from matscan.reconstruct import ReconstructConfig

    cfg = ReconstructConfig()
    old = json_safe(asdict(cfg))
    del old["calibration"]
    (tmp_path / MANIFEST).write_text(json.dumps({"format": MANIFEST_FORMAT, "settings": old, "captures": {}}))
    assert _open_manifest(tmp_path, json_safe(asdict(cfg)))["settings"] == old
    with pytest.raises(MatscanError, match="other reconstruction settings"):
        _open_manifest(tmp_path, json_safe(asdict(replace(cfg, calibration=str(tmp_path / "cal.json")))))


def test_a_list_file_that_is_not_text_is_one_line(captures, tmp_path):
    (tmp_path / "latin1.txt").write_bytes(f"{captures / 'cork'}\n\xe9t\xe9\n".encode("latin-1"))
    for spec in (tmp_path / "latin1.txt", next((captures / "cork").glob("*.png"))):
        with pytest.raises(MatscanError, match="is a file but not a text list of capture folders") as info:
            expand_captures([str(spec)])
        assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("captures_value", "words"),
    [
        (None, "captures: expected an object"),
        ({"cork": 5}, "captures.cork: expected an object"),
        ({"cork": {"capture": "/x"}}, "captures.cork.state: expected a non-empty string"),
        ({"cork": {"capture": "/x", "state": "lost"}}, "captures.cork.state: 'lost' is not one of"),
        ({"cork": {"capture": "/x", "state": "done"}}, "captures.cork.rerender_rmse: expected a number"),
        ({"cork": {"capture": "/x", "state": "done", "rerender_rmse": 0.1, "warnings": "x"}}, "expected a list"),
    ],
)
def test_a_damaged_manifest_is_one_line_naming_it(tmp_path, captures_value, words):
    from dataclasses import asdict

    from matscan.batch import MANIFEST, MANIFEST_FORMAT, _open_manifest, json_safe
    from matscan.reconstruct import ReconstructConfig

    settings = json_safe(asdict(ReconstructConfig()))
    doc = {"format": MANIFEST_FORMAT, "settings": settings}
    if captures_value is not None:
        doc["captures"] = captures_value
    (tmp_path / MANIFEST).write_text(json.dumps(doc))
    with pytest.raises(MatscanError, match=words) as info:
        _open_manifest(tmp_path, settings)
    assert MANIFEST in str(info.value) and "\n" not in str(info.value)
    (tmp_path / MANIFEST).write_text("[1, 2]")
    with pytest.raises(MatscanError, match="is not a matscan-batch"):
        _open_manifest(tmp_path, settings)


def test_a_capture_named_as_the_batchs_own_files_gets_another_name(tmp_path):
    names = output_names([tmp_path / "thumbs", tmp_path / "a" / "thumbs", tmp_path / ".hidden", tmp_path / "cork"])
    assert names == ["thumbs-2", "thumbs-3", "hidden", "cork"]


@pytest.mark.skipif(sys.platform == "darwin", reason="macOS file systems refuse names that are not UTF-8")
def test_a_capture_path_that_is_not_utf8_is_refused_before_any_manifest(captures, tmp_path):
    import os
    import shutil

    from matscan.batch import batch

    odd = Path(os.fsdecode(bytes(tmp_path) + b"/cork\xff"))
    shutil.copytree(captures / "cork", odd)
    with pytest.raises(MatscanError, match=r"cork\\xff: the path is not valid UTF-8"):
        batch([str(odd)], tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("document", "words"),
    [
        ("{not json", r"cal\.json: .*JSON"),
        (
            '{"format": "matscan-calibration/1", "light_scales": {"x": 1}}',
            r"light_scales: key 'x' is not a light index",
        ),
        (
            '{"format": "matscan-calibration/1", "light_scales": {"3": -1}}',
            r"light_scales\['3'\]: light 3 has scale -1",
        ),
        (
            '{"format": "matscan-calibration/1", "flat_fields": {"3": "flat_03.exr"}}',
            r"flat_fields\['3'\]: no such file",
        ),
    ],
)
def test_a_bad_calibration_stops_a_batch_before_any_capture(captures, tmp_path, document, words):
    """``--calibration`` applies to every capture: a bad file is one line before any work,
    not one failure per capture (it used to fail all five, one by one)."""
    from matscan.batch import batch
    from matscan.reconstruct import ReconstructConfig

    (tmp_path / "cal.json").write_text(document)
    cfg = ReconstructConfig(model="none", refine="off", calibration=str(tmp_path / "cal.json"))
    with pytest.raises(MatscanError, match=words) as info:
        batch([str(captures)], tmp_path / "out", cfg, workers=1)
    assert str(tmp_path / "cal.json") in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()


def test_a_good_calibration_passes_the_batchs_check(tmp_path):
    """The check before a batch takes what ``calibrate`` writes: scales and flat fields."""
    import numpy as np

    from matscan.calibrate import check_calibration_file
    from matscan.imagefile import write_image

    write_image(tmp_path / "flat_03.exr", np.full((6, 6, 1), 1.02, np.float32), bits=32)
    doc = {
        "format": "matscan-calibration/1",
        "light_scales": {"3": [1.0, 0.9, 1.1], "200": 0.8},  # light 200: any rig's, until a capture's rig reads it
        "flat_fields": {"3": "flat_03.exr"},
        "exposure_s": 0.01,
    }
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    check_calibration_file(tmp_path / "cal.json")
    (tmp_path / "cal.json").write_text(json.dumps({**doc, "exposure_s": -1}))
    with pytest.raises(MatscanError, match=r"cal\.json: exposure_s"):
        check_calibration_file(tmp_path / "cal.json")


@pytest.mark.parametrize("option", ["model", "anyrig"])
def test_damaged_weights_stop_a_batch_before_any_capture(captures, tmp_path, option):
    from matscan.batch import batch
    from matscan.reconstruct import ReconstructConfig

    (tmp_path / "notes.safetensors").write_text("not weights")
    cfg = ReconstructConfig(refine="off", **{option: str(tmp_path / "notes.safetensors")})
    with pytest.raises(MatscanError, match=r"notes\.safetensors: .*safetensors") as info:
        batch([str(captures)], tmp_path / "out", cfg, workers=1)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()
