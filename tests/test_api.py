"""The Python API (docs/api.md): what ``import matscan`` offers, what it costs, and the
worked example in docs/api.md, run as written."""

from __future__ import annotations

import importlib
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

import matscan
from matscan.errors import MatscanError

DOC = Path(__file__).resolve().parent.parent / "docs" / "api.md"


def test_import_matscan_loads_no_heavy_dependency():
    # a fresh interpreter: this test process has torch loaded already
    code = "import sys, matscan; print(sorted(m for m in ('torch', 'numpy', 'cv2') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_every_api_name_is_its_module_object():
    from matscan import _API

    assert sorted(matscan.__all__) == sorted(_API)
    assert set(matscan.__all__) <= set(dir(matscan))
    for name in matscan.__all__:
        assert getattr(matscan, name) is getattr(importlib.import_module(_API[name]), name), name
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        matscan.nonsense  # noqa: B018


def test_functions_keep_their_names_beside_modules_of_the_same_name():
    # importing matscan.calibrate or matscan.reconstruct (the modules) after the package
    # must not turn matscan.calibrate / matscan.reconstruct into those modules
    code = (
        "import matscan, matscan.calibrate\n"
        "from matscan.reconstruct import job\n"
        "from matscan.calibrate import light_scales\n"
        "import matscan.reconstruct.solver\n"
        "assert matscan.reconstruct is job.reconstruct, matscan.reconstruct\n"
        "assert matscan.calibrate is sys.modules['matscan.calibrate'].calibrate, matscan.calibrate\n"
        "from matscan import calibrate, reconstruct\n"
        "assert callable(calibrate) and callable(reconstruct)\n"
    )
    subprocess.run([sys.executable, "-c", "import sys\n" + code], check=True)


def test_sample_names_the_built_in_sample():
    capture = matscan.load_capture("@sample")
    assert len(capture.files) == 24 and capture.size == (256, 256) and capture.rig.name == "dome24"
    assert matscan.read_mapset("@sample").size == (256, 256)
    with pytest.raises(MatscanError, match=r"@nope: not a built-in sample \(one of @sample\)"):
        matscan.load_capture("@nope")


def test_reconstruct_takes_the_sample(tmp_path):
    cfg = matscan.ReconstructConfig(model="none", refine="off")  # the flat start: the quickest path
    record = matscan.reconstruct("@sample", tmp_path / "out", cfg)
    assert record["size_px"] == [256, 256] and len(record["inputs"]) == 24
    assert (tmp_path / "out" / "diffuse.png").is_file() and (tmp_path / "out" / "matscan.json").is_file()
    assert (tmp_path / "out" / Path(record["capture"])).resolve() == (
        Path(matscan.__file__).parent / "samples" / "sample" / "capture"
    )


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.M | re.S)


def test_docs_api_example_runs(tmp_path, monkeypatch, capsys):
    blocks = _python_blocks(DOC.read_text(encoding="utf-8"))
    assert blocks, "docs/api.md has no ```python block"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "docs_api_example"}
    for block in blocks:
        exec(compile(block, str(DOC), "exec"), namespace)
    printed = capsys.readouterr().out
    assert "24 photos of 64×64 px" in printed

    for file in ("capture/capture.json", "capture/led_00.png", "material/diffuse.png", "material/normal.png"):
        assert (tmp_path / file).is_file(), file
    for file in ("material/matscan.json", "material/report.html", "material/material.gltf"):
        assert (tmp_path / file).is_file(), file

    record = namespace["record"]
    assert math.isfinite(record["rerender_rmse"]) and 0 <= record["rerender_rmse"] < 0.05
    maps = namespace["maps"]
    assert maps.size == (64, 64)
    assert 0 <= float(maps.diffuse.min()) and float(maps.diffuse.max()) <= 1
    assert 0 <= float(maps.roughness.min()) and float(maps.roughness.max()) <= 1
    image = namespace["image"]
    assert image.shape == (3, 64, 64) and bool(image.isfinite().all()) and float(image.min()) >= 0
    relit, true = namespace["relit"], namespace["true"]
    assert 0 < relit < 2 and abs(relit / true - 1) < 0.25  # the relit mean near the true maps'
