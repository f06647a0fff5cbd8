"""Fuzzing the command line: any arguments end in a result (exit 0) or one error line
(exit 2), never a traceback, and never change an input.

The number of examples comes from ``MATSCAN_FUZZ_EXAMPLES`` (default 60, about
half a minute here); run with e.g. ``MATSCAN_FUZZ_EXAMPLES=3000`` for a long search.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest
import torch
from conftest import random_maps
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from matscan.capture.folder import write_capture
from matscan.cli import main
from matscan.mapset import write_mapset
from matscan.rig import builtin_rig

EXAMPLES = int(os.environ.get("MATSCAN_FUZZ_EXAMPLES", "60"))

#: Values that break careless parsers: non-finite, huge, negative, empty, wrong shape.
VALUES = [
    "0",
    "-1",
    "1",
    "2",
    "16",
    "3.5",
    "nan",
    "inf",
    "-inf",
    "1e400",
    "9" * 5000,
    "",
    "abc",
    "0,0,225",
    "-50,0,150",
    "nan,0,200",
    "1,2",
    "0,0,0",
    "auto",
    "on",
    "off",
    "none",
    "default",
    "srgb",
    "linear",
    "6",
    "0,4,8",
    "dome24",
    "flash",
    "@sample",
    "@nope",
    "\x00",
    "../..",
]

COMMANDS = {
    "render": (["MAPS"], ["--out", "--light", "--rig", "--intensity", "--exponent", "--overwrite"]),
    "simulate": (
        ["MAPS"],
        [
            "--out",
            "--rig",
            "--lights",
            "--size",
            "--noise",
            "--full-well",
            "--exposure",
            "--encoding",
            "--bits",
            "--seed",
        ],
    ),
    "reconstruct": (["CAPTURE"], ["--out", "--model", "--refine", "--steps", "--tile", "--validate", "--overwrite"]),
    "calibrate": ([], ["--out", "--grey", "--chart", "--corners", "--chart-encoding", "--flat-fields", "--overwrite"]),
    "sheet": (["CAPTURE"], ["--out", "--maps", "--columns", "--overwrite"]),
    "export": (
        ["MAPS"],
        ["--out", "--field-mm", "--rig", "--exr", "--directx-normals", "--normal-convention", "--overwrite"],
    ),
}
FLAGS = {"--overwrite", "--flat-fields", "--exr", "--directx-normals"}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fuzz")
    maps = random_maps(16, seed=3)
    write_mapset(root / "maps", maps)
    images = torch.rand(6, 3, 16, 16, generator=torch.Generator().manual_seed(2)) * 0.5 + 0.1
    write_capture(root / "cap", images, builtin_rig("dome24"), light_indices=[0, 4, 8, 12, 16, 20])
    return {"MAPS": root / "maps", "CAPTURE": root / "cap", "root": root}


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.as_posix().encode() + p.read_bytes())
    return h.hexdigest()


@st.composite
def argvs(draw, inputs: dict[str, Path], out_dir: Path) -> list[str]:
    command = draw(st.sampled_from(sorted(COMMANDS)))
    positional, options = COMMANDS[command]
    argv = [command]
    for name in positional:
        argv.append(draw(st.sampled_from([str(inputs[name]), str(inputs["MAPS"]), *VALUES])))
    for opt in draw(st.lists(st.sampled_from(options), max_size=5, unique=True)):
        if opt in FLAGS:
            argv.append(opt)
        elif opt == "--out":
            name = draw(st.sampled_from(["o.png", "o.exr", "o", "o.json", "cap", "maps", "o.txt"]))
            target = {"cap": inputs["CAPTURE"], "maps": inputs["MAPS"]}.get(name, out_dir / name)
            argv += [opt, str(target)]
        elif opt in ("--grey",):
            argv += [opt, draw(st.sampled_from([str(inputs["CAPTURE"]), *VALUES]))]
        else:
            argv += [opt, draw(st.sampled_from(VALUES))]
    return argv


def test_cli_arguments_never_crash(inputs, tmp_path_factory, capsys):
    before = {k: _digest(inputs[k]) for k in ("MAPS", "CAPTURE")}
    out_dir = tmp_path_factory.mktemp("fuzz-out")
    outcomes = {0: 0, 2: 0}

    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
        database=None,
    )
    @given(argvs(inputs, out_dir))
    def check(argv):
        capsys.readouterr()
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse: bad or missing arguments
            code = exc.code
        err = capsys.readouterr().err
        assert code in (0, 2), (argv, code, err)
        errors = [line for line in err.splitlines() if "error:" in line]
        if code == 2:
            assert len(errors) == 1, (argv, err)
        assert "Traceback" not in err, (argv, err)
        outcomes[code] += 1

    check()
    assert {k: _digest(inputs[k]) for k in ("MAPS", "CAPTURE")} == before
    assert outcomes[2] > 0  # the generator does reach the error paths
    assert not [p for p in inputs["root"].rglob("*") if ".matscan-" in p.name]
