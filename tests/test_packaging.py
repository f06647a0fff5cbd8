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
