"""The matscan command: summaries on success, one-line errors (no traceback) on bad input."""

from __future__ import annotations

import subprocess
import sys

import pytest

from matscan.capture import load_capture
from matscan.cli import main
from matscan.imagefile import read_image


def _commands(parser) -> list[list[str]]:
    """Every command and subcommand of ``parser``, as argument lists."""
    import argparse

    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.append([name])
                found += [[name, *rest] for rest in _commands(sub)]
    return found


def test_every_command_prints_its_help(capsys):
    # argparse formats help lazily: a stray % in one option's text fails only there
    from matscan.cli import build_parser

    commands = _commands(build_parser())
    assert ["reconstruct"] in commands and ["rig", "from-lp"] in commands
    for argv in commands:
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--help"])
        assert exc.value.code == 0, argv
        assert "usage: matscan " + " ".join(argv) in capsys.readouterr().out


def test_simulate_render_sheet(tmp_path, capsys):
    assert main(["simulate", "@sample", "--out", str(tmp_path / "c"), "--lights", "6", "--size", "32"]) == 0
    assert "wrote 6 photos" in capsys.readouterr().out
    cap = load_capture(tmp_path / "c")
    assert cap.light_indices == (0, 4, 8, 12, 16, 20) and cap.size == (32, 32)

    assert main(["render", "@sample", "--out", str(tmp_path / "r.exr"), "--light", "0,0,225"]) == 0
    assert read_image(tmp_path / "r.exr").pixels.shape == (256, 256, 3)
    assert main(["render", "@sample", "--out", str(tmp_path / "r.png"), "--light", "100,0,100"]) == 0

    assert main(["sheet", str(tmp_path / "c"), "--maps", "@sample", "--out", str(tmp_path / "s.png")]) == 0
    assert read_image(tmp_path / "s.png").pixels.shape[2] == 3


@pytest.mark.parametrize(("lights", "said"), [("1", "networks: the rule for one photo"), ("2", "left out")])
def test_reconstruct_says_what_refine_auto_chose(tmp_path, capsys, lights, said):
    # with one photo the choice is a rule, with two it is measured on photos left out
    assert main(["simulate", "@sample", "--out", str(tmp_path / "c"), "--lights", lights, "--size", "32"]) == 0
    capsys.readouterr()
    assert main(["reconstruct", str(tmp_path / "c"), "--out", str(tmp_path / "m")]) == 0
    out = capsys.readouterr().out
    assert "reconstruct: wrote maps" in out and said in out
    assert "refined no" in out if lights == "1" else "refined yes" in out


def test_reconstruct_reads_the_calibration_it_is_given(tmp_path, monkeypatch, capsys):
    """``--calibration FILE``, given relative to the current folder: the scale it gives
    light 0 reaches the fit (a photo divided by 2 is re-rendered as half as bright: the
    fit's diffuse halves where only that photo lights the sample), and matscan.json names
    the file by its absolute path."""
    import json

    import torch

    from matscan.color import srgb_to_linear

    assert main(["simulate", "@sample", "--out", str(tmp_path / "c"), "--lights", "0,", "--size", "16"]) == 0
    (tmp_path / "cal.json").write_text(json.dumps({"format": "matscan-calibration/1", "light_scales": {"0": 2.0}}))
    monkeypatch.chdir(tmp_path)
    assert main(["reconstruct", "c", "--out", "plain", "--model", "none", "--refine", "on"]) == 0
    assert (
        main(["reconstruct", "c", "--out", "m", "--model", "none", "--refine", "on", "--calibration", "cal.json"]) == 0
    )
    capsys.readouterr()
    record = json.loads((tmp_path / "m" / "matscan.json").read_text())
    assert record["config"]["calibration"] == str((tmp_path / "cal.json").resolve())
    plain, halved = (
        srgb_to_linear(torch.from_numpy(read_image(tmp_path / d / "diffuse.png").pixels)) for d in ("plain", "m")
    )
    assert abs(float(halved.mean()) / float(plain.mean()) - 0.5) < 0.05


def test_simulate_exact_mode(tmp_path):
    assert (
        main(
            [
                "simulate",
                "@sample",
                "--out",
                str(tmp_path / "c"),
                "--lights",
                "0,",
                "--size",
                "16",
                "--noise",
                "0",
                "--encoding",
                "linear",
            ]
        )
        == 0
    )
    assert (tmp_path / "c" / "led_00.exr").is_file()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["simulate", "nowhere", "--out", "x"], "nowhere: no such map set folder"),
        (["simulate", "@nope", "--out", "x"], "@nope: not a built-in sample"),
        (["simulate", "@sample", "--out", "x", "--lights", "7"], "lights: '7' is not a subset"),
        (["simulate", "@sample", "--out", "x", "--rig", "dome99"], "not a built-in rig"),
        (["simulate", "@sample", "--out", "x", "--encoding", "srgb", "--bits", "32"], "32-bit float files are linear"),
        (["render", "@sample", "--out", "x.png", "--light", "0,0"], "--light: '0,0' is not 3"),
        (["render", "@sample", "--out", "x.png", "--light", "0,0,-5"], "not above the sample plane"),
        (["render", "@sample", "--out", "x.bmp", "--light", "0,0,5"], "write .png"),
        (["sheet", "nowhere", "--out", "x.png"], "nowhere: no such map set folder"),
        (["reconstruct", "@sample", "--out", "x", "--calibration", "nope.json"], "nope.json: no such file"),
        (["batch", "@sample", "--out", "x", "--calibration", "."], ".: is not a file"),
    ],
)
def test_bad_input_is_one_line(tmp_path, monkeypatch, capsys, argv, words):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("matscan: error: ") and words in err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_console_script_reports_without_traceback(tmp_path):
    bad = tmp_path / "cap"
    bad.mkdir()
    (bad / "capture.json").write_text(
        '{"format": "matscan-capture/1", "rig": "dome24", "images": '
        '[{"light": 0, "file": "led_00.png"}, {"light": 0, "file": "b.png"}]}'
    )
    proc = subprocess.run(
        [sys.executable, "-m", "matscan.cli", "sheet", str(bad), "--out", str(tmp_path / "s.png")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert "light 0 appears twice" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(p.name for p in bad.iterdir()) == ["capture.json"]


def test_synth(tmp_path, capsys):
    assert main(["synth", "--out", str(tmp_path / "s"), "--count", "2", "--size", "32", "--lights", "6"]) == 0
    assert "wrote 2 materials" in capsys.readouterr().out
    folders = sorted(p.name for p in (tmp_path / "s").iterdir())
    assert folders[-2:] == ["contact_sheet.png", "matscan.json"] and len(folders) == 4
    cap = load_capture(tmp_path / "s" / folders[0] / "capture")
    assert cap.light_indices == (0, 4, 8, 12, 16, 20)
    assert main(["synth", "--out", str(tmp_path / "t"), "--count", "1", "--size", "32", "--family", "velvet"]) == 2
