"""Packaging metadata: the licence pyproject.toml declares is the one the wheel ships.

Building the wheel takes a network-free but slow `pip wheel`; checked by hand with
``python -m pip wheel . --no-deps --no-build-isolation -w DIR`` and ``python -m zipfile -l``
(``matscan-*.dist-info/licenses/LICENSE``). This test checks what that build reads.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_license_is_declared_and_shipped():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert project["license"] == "MIT"
    assert project["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert text.startswith("MIT License\n") and "Copyright (c) 2026 the matscan authors" in text


def test_shipped_weights_are_package_data_and_small_enough_for_git():
    """Every shipped name's file is in the package folder, matched by the package-data glob
    the wheel takes, and all of them together stay under 64 MB."""
    from fnmatch import fnmatch

    from matscan.weights import ANYRIG_SHIPPED, SHIPPED
    from matscan.weights import ROOT as WEIGHTS

    globs = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]["package-data"]
    files = [WEIGHTS / name for name in (*SHIPPED.values(), *ANYRIG_SHIPPED.values())]
    for path in files:
        assert path.is_file(), path
        assert any(fnmatch(path.name, g) for g in globs["matscan.weights"]), path.name
    assert sum(p.stat().st_size for p in files) < 64 * 10**6
