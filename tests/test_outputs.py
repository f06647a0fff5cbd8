"""A capture is never lost: outputs checked before the work, never over an input,
written atomically by one writer at a time (issue: safe outputs).

Every refusal is checked end to end through the command: exit status 2, one line
on stderr naming the path and the problem, every input byte-identical (sha256),
and nothing left behind (no temporaries, no lock files).
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from matscan.atomic import atomic_folder, clean_stale, exchange, output_lock, replace_folder, write_text
from matscan.capture.folder import write_capture
from matscan.cli import main
from matscan.errors import MatscanError
from matscan.outputs import check_destination, claim_output, foreign_entries
from matscan.rig import builtin_rig

ROOT = Path(__file__).resolve().parents[1]


def tree_digest(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (relative path → digest)."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def litter(folder: Path) -> list[str]:
    """matscan temporaries and lock files anywhere under ``folder``."""
    return [p.name for p in folder.rglob("*") if ".matscan-" in p.name]


@pytest.fixture
def capture(tmp_path) -> Path:
    """A tiny 6-light dome24 capture in ``lab/cap`` beside a user's notes."""
    g = torch.Generator().manual_seed(1)
    images = torch.rand(6, 3, 16, 16, generator=g) * 0.5 + 0.1
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "notes.txt").write_text("swatch 17, autumn collection\n")
    write_capture(lab / "cap", images, builtin_rig("dome24"), light_indices=[0, 4, 8, 12, 16, 20])
    return lab / "cap"


def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()  # what earlier commands printed
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


def assert_refused(argv, capsys, lab: Path, words: str) -> None:
    before = tree_digest(lab)
    code, err = run_cli(argv, capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("matscan: error: "), err
    assert words in lines[0], lines[0]
    assert tree_digest(lab) == before
    assert litter(lab) == []


# --- outputs never touch inputs -------------------------------------------------------------


@pytest.mark.parametrize(
    "out, extra, words",
    [
        ("cap", ["--overwrite"], "is the input"),
        ("cap", ["--overwrite", "--overwrite-any"], "is the input"),
        (".", ["--overwrite"], "contains the input"),  # lab holds the capture and the notes
        ("cap/maps", [], "lies inside the input"),
    ],
)
def test_reconstruct_never_writes_over_its_capture(capture, capsys, out, extra, words):
    lab = capture.parent
    out_path = lab if out == "." else lab / out
    argv = ["reconstruct", str(capture), "--out", str(out_path), "--model", "none", "--steps", "1", *extra]
    assert_refused(argv, capsys, lab, words)


def test_single_file_outputs_never_replace_capture_files(capture, capsys):
    lab = capture.parent
    for argv in (
        ["calibrate", "--grey", str(capture), "--out", str(capture / "capture.json")],
        ["calibrate", "--grey", str(capture), "--out", str(capture / "capture.json"), "--overwrite"],
        ["render", "@sample", "--out", str(capture / "led_00.png"), "--light", "0,0,225", "--overwrite"],
        ["sheet", str(capture), "--out", str(capture / "led_04.png"), "--overwrite"],
    ):
        assert_refused(argv, capsys, lab, str(capture))


def test_a_file_of_another_capture_is_never_replaced(capture, capsys, tmp_path):
    # not an input of this command, but listed by the capture.json beside it
    argv = ["render", "@sample", "--out", str(capture / "led_08.png"), "--light", "0,0,225", "--overwrite"]
    assert_refused(argv, capsys, capture.parent, "belongs to the capture")


@pytest.mark.parametrize(
    "command",
    [
        ["reconstruct", "@sample", "--model", "none", "--steps", "1"],
        ["simulate", "@sample", "--size", "16", "--lights", "6"],
    ],
)
@pytest.mark.parametrize("flags", [["--overwrite"], ["--overwrite", "--overwrite-any"]])
def test_overwrite_never_turns_a_capture_into_another_output(capture, capsys, command, flags):
    # the capture's matscan.json lists every file in it, as a previous output's does, but
    # it was written as a capture (write_capture): no other command may replace it
    argv = [*command, "--out", str(capture), *flags]
    assert_refused(argv, capsys, capture.parent, "holds a capture (capture.json)")


def test_a_capture_below_the_output_is_never_replaced(capture, capsys, tmp_path):
    # a capture moved into a previous output's folder (a batch folder, say)
    out = tmp_path / "maps"
    assert main(["reconstruct", str(capture), "--out", str(out), "--model", "none", "--steps", "1"]) == 0
    capture.rename(out / "cap")
    lab = tmp_path
    argv = ["reconstruct", "@sample", "--out", str(out), "--model", "none", "--steps", "1", "--overwrite"]
    assert_refused(argv, capsys, lab, "holds a capture (cap/capture.json)")


def test_too_few_photos_to_self_calibrate_names_the_flag_that_asked(capture, capsys, tmp_path):
    # --shared-f0 implies the self-calibration, which 6 photos cannot support
    argv = ["reconstruct", str(capture), "--out", str(tmp_path / "o"), "--model", "none", "--shared-f0"]
    assert_refused(argv, capsys, capture.parent, "--shared-f0")
    assert not (tmp_path / "o").exists()


def test_a_simulated_capture_is_replaced_by_simulate_again(tmp_path, capsys):
    out = tmp_path / "sim"
    argv = ["simulate", "@sample", "--out", str(out), "--size", "16", "--lights", "6"]
    assert main(argv) == 0
    first = tree_digest(out)
    assert main([*argv, "--seed", "1", "--overwrite"]) == 0  # its own command: allowed
    assert tree_digest(out).keys() == first.keys() and tree_digest(out) != first


def test_a_file_inside_a_capture_is_never_replaced(capture, capsys):
    # files the capture.json does not list (a dark frame, a journal, notes) are the capture's too
    (capture / "dark.png").write_bytes(b"not listed")
    (capture / "raw").mkdir()
    (capture / "raw" / "lights.lp").write_text("1\nx.png 0 0 1\n")
    lab = capture.parent
    for argv in (
        ["render", "@sample", "--out", str(capture / "dark.png"), "--light", "0,0,225", "--overwrite"],
        ["rig", "to-lp", "dome24", "--out", str(capture / "raw" / "lights.lp"), "--overwrite"],
    ):
        assert_refused(argv, capsys, lab, f"lies in the capture {capture}")


def test_an_rti_light_file_is_never_replaced(tmp_path, capsys):
    rti = tmp_path / "rti"
    rti.mkdir()
    for name in ("a.png", "b.png"):
        (rti / name).write_bytes(b"photo")
    (rti / "dirs.lp").write_text("2\na.png 0.1 0.2 0.97\nb.png -0.3 0.1 0.95\n")
    argv = ["rig", "to-lp", "dome24", "--out", str(rti / "dirs.lp"), "--overwrite"]
    assert_refused(argv, capsys, rti, "is the light file of the RTI photos beside it (a.png")
    # an .lp file whose photos are not beside it is an ordinary output
    lone = tmp_path / "old.lp"
    lone.write_text("1\nelsewhere.png 0 0 1\n")
    assert main(["rig", "to-lp", "dome24", "--out", str(lone), "--overwrite"]) == 0
    assert len(lone.read_text().split("\n")) > 20  # dome24's 24 lights now


def test_single_file_outputs_need_overwrite(tmp_path, capsys):
    out = tmp_path / "r.png"
    out.write_bytes(b"mine")
    argv = ["render", "@sample", "--out", str(out), "--light", "0,0,225"]
    assert_refused(argv, capsys, tmp_path, "exists (pass --overwrite")
    assert main([*argv, "--overwrite"]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG" and litter(tmp_path) == []
    cal = tmp_path / "calibration.json"
    cal.write_text("{}")
    assert_refused(["calibrate", "--chart", str(out), "--out", str(cal)], capsys, tmp_path, "exists (pass --overwrite")


def test_overwrite_replaces_only_previous_outputs(capture, capsys, tmp_path):
    out = tmp_path / "out"
    argv = ["reconstruct", str(capture), "--out", str(out), "--model", "none", "--steps", "2"]
    assert main(argv) == 0
    assert foreign_entries(out) == []  # matscan.json lists every file it wrote
    assert main([*argv, "--overwrite"]) == 0  # a previous output is replaced
    (out / "my-notes.txt").write_text("do not lose me")
    assert_refused([*argv, "--overwrite"], capsys, tmp_path, "my-notes.txt")
    assert main([*argv, "--overwrite", "--overwrite-any"]) == 0  # the explicit second flag
    assert not (out / "my-notes.txt").exists() and litter(tmp_path) == []


def test_folder_without_record_is_foreign(tmp_path, capsys, capture):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "IMG_0001.JPG").write_bytes(b"\xff\xd8")
    argv = ["reconstruct", str(capture), "--out", str(out), "--model", "none", "--overwrite"]
    assert_refused(argv, capsys, tmp_path, "IMG_0001.JPG")


# --- checks before the work ----------------------------------------------------------------


def test_existing_output_is_refused_before_reading_the_capture(capture, tmp_path, monkeypatch):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    from matscan.reconstruct import job as rec

    def no_work(*args, **kwargs):
        raise AssertionError("the capture was read before the output was checked")

    monkeypatch.setattr(rec, "load_capture", no_work)
    with pytest.raises(MatscanError, match="folder exists and is not empty"):
        rec.reconstruct(capture, tmp_path / "full", rec.ReconstructConfig(model="none"))


@pytest.mark.parametrize(
    "make_out, words",
    [
        (lambda t: t / "afile" / "out", "is not a folder"),
        (lambda t: t / ("n" * 240), "the name is 240 characters"),
        (lambda t: t / "dangling", "dangling symbolic link"),
    ],
)
def test_unusable_outputs(capture, capsys, tmp_path, make_out, words):
    (tmp_path / "afile").write_text("a file, not a folder")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    out = make_out(tmp_path)
    argv = ["reconstruct", str(capture), "--out", str(out), "--model", "none"]
    assert_refused(argv, capsys, tmp_path, words)


def test_current_folder_is_refused(capture, capsys, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert_refused(["reconstruct", str(capture), "--out", ".", "--model", "none"], capsys, tmp_path, "current folder")


def test_unwritable_and_full_file_systems_are_refused_before_the_work(capture, tmp_path, monkeypatch):
    import shutil
    from collections import namedtuple

    monkeypatch.setattr(os, "access", lambda path, mode: False)
    with pytest.raises(MatscanError, match="is not writable"):
        check_destination(tmp_path / "out", [capture])
    monkeypatch.undo()
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 1000, 1000))
    from matscan.reconstruct import job as rec

    with pytest.raises(MatscanError, match="MiB are free"):
        rec.reconstruct(capture, tmp_path / "out", rec.ReconstructConfig(model="none"))
    assert not (tmp_path / "out").exists() and litter(tmp_path) == []


@pytest.mark.parametrize(
    "argv, words",
    [
        (["render", "@sample", "--out", "r.png", "--light", "0,0,200", "--intensity", "nan"], "not a finite number"),
        (["render", "@sample", "--out", "r.png", "--light", "nan,0,200"], "not finite"),
        (["simulate", "@sample", "--out", "c", "--noise", "nan"], "not a finite number"),
        (["reconstruct", "@sample", "--out", "o", "--steps", "-1"], "must be at least 1"),
        (["evaluate", "photos", "--out", "e", "--size", "0"], "must be at least 8"),
        (["evaluate", "procedural:0", "--out", "e"], "procedural:N with N from 1 to 10000"),
        (["evaluate", "procedural:99999999999999999999", "--out", "e"], "procedural:N with N from 1 to 10000"),
        (["simulate", "@sample", "--out", "c", "--lights", ","], "',' names no light"),
        (["synth", "--out", "s", "--count", "1", "--size", "16", "--lights", ", ,"], "', ,' names no light"),
        (["simulate", "@sample", "--out", "c", "--exposure", "1e308"], "must be at most 1e+06"),
        (["simulate", "@sample", "--out", "c", "--seed", "9" * 23], "must be at most 2147483647"),
        (["synth", "--out", "s", "--count", "1", "--size", "8", "--seed", str(2**62)], "must be at most 2147483647"),
        (["simulate", "@sample", "--out", "c", "--size", "100000"], "must be at most 16384"),
        (["render", "@sample", "--out", "r.png", "--light", "0,0,100", "--exponent", "1e308"], "at most 1000"),
        (["render", "@sample", "--out", "r.png", "--light", "0,0,100", "--intensity", "1e308"], "at most 1e+06"),
        (["render", "@sample", "--out", "r.png", "--light", "0,0,1e308"], "farther than 1e+06 mm"),
        (["reconstruct", "@sample", "--out", "o", "--emissive", "--refine", "off"], "drop --emissive or --refine off"),
        (["calibrate", "--chart", "c.png", "--out", "c.json", "--corners", "nan,0,1,0,1,1,0,1"], "not finite"),
    ],
)
def test_argument_ranges(tmp_path, capsys, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        code = main(argv)
        raise SystemExit(code)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_negative_vector_values_parse(tmp_path, capsys):
    out = tmp_path / "r.png"
    assert main(["render", "@sample", "--out", str(out), "--light", "-50,0,150"]) == 0
    assert "(-50.0, 0.0, 150.0)" in capsys.readouterr().out


def test_reconstruct_config_checks_itself():
    from matscan.reconstruct import ReconstructConfig

    for bad in ({"refine_steps": 0}, {"refine_lr": float("nan")}, {"refine": "maybe"}, {"tile": 3}):
        with pytest.raises(MatscanError):
            ReconstructConfig(**bad)


# --- atomic and exclusive writes -----------------------------------------------------------


def _python(code: str, stderr=None) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], env=env, stderr=stderr, text=True)


def _wait_for(predicate, seconds: float = 20.0) -> None:
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > seconds:
            raise AssertionError("timed out")
        time.sleep(0.02)


def test_second_writer_fails_at_once(capture, tmp_path, capsys):
    out = tmp_path / "out"
    holder = _python(
        f"""
        import time
        from matscan.atomic import output_lock
        with output_lock({str(out)!r}):
            open({str(tmp_path / "locked")!r}, "w").close()
            time.sleep(60)
        """
    )
    try:
        _wait_for((tmp_path / "locked").exists)
        t0 = time.monotonic()
        code, err = run_cli(["reconstruct", str(capture), "--out", str(out), "--model", "none"], capsys)
        assert code == 2 and "another matscan process is writing this output" in err
        assert time.monotonic() - t0 < 10  # it did not wait for, or do, the work
    finally:
        holder.kill()
        holder.wait()
    assert not out.exists()


def test_lock_is_reentrant_in_one_process_and_removed_after(tmp_path):
    out = tmp_path / "o"
    with output_lock(out), output_lock(out):
        assert (tmp_path / ".o.matscan-lock").exists()
    assert litter(tmp_path) == []


def test_killed_writer_leaves_temporaries_that_the_next_run_removes(tmp_path, capture):
    out = tmp_path / "out"
    victim = _python(
        f"""
        import os, signal
        from matscan.atomic import atomic_folder
        with atomic_folder({str(out)!r}) as tmp:
            (tmp / "half.png").write_bytes(b"half")
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    victim.wait()
    assert victim.returncode == -signal.SIGKILL
    left = litter(tmp_path)
    assert any(".out.matscan-tmp-" in name for name in left)
    with claim_output(out, "test", [capture]) as claim, claim.folder() as tmp:
        (tmp / "whole.png").write_bytes(b"whole")
    assert sorted(p.name for p in out.iterdir()) == ["matscan.json", "whole.png"]
    assert litter(tmp_path) == []


def test_a_killed_file_writer_leaves_a_temporary_that_the_next_write_removes(tmp_path):
    # as when `matscan acquire` is killed while rewriting capture.json after a frame
    path = tmp_path / "capture.json"
    victim = _python(
        f"""
        import os, signal
        from matscan.atomic import atomic_file
        with atomic_file({str(path)!r}) as tmp:
            tmp.write_text("half")
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    victim.wait()
    assert victim.returncode == -signal.SIGKILL
    assert any(".capture.json.matscan-tmp-" in name for name in litter(tmp_path))
    write_text(path, "whole")
    assert path.read_text() == "whole" and litter(tmp_path) == []


def test_atomic_files_get_the_permissions_a_plain_write_would(tmp_path):
    """safetensors' save_file creates its file for its owner only; written through
    atomic_file, a new file has what open() gives under the umask, a replaced one keeps its own."""
    import os
    import stat

    import torch
    from safetensors.torch import save_file

    from matscan.atomic import atomic_file

    def mode(p):
        return stat.S_IMODE(p.stat().st_mode)

    old = os.umask(0o027)
    try:
        (tmp_path / "plain.txt").write_text("x")  # the reference: a plain write under this umask
        new = tmp_path / "weights.safetensors"
        with atomic_file(new) as tmp:
            save_file({"a": torch.zeros(2)}, tmp)
        assert mode(new) == mode(tmp_path / "plain.txt") == 0o640
        new.chmod(0o604)
        with atomic_file(new) as tmp:
            save_file({"a": torch.ones(2)}, tmp)
        assert mode(new) == 0o604
    finally:
        os.umask(old)


def test_temporaries_of_a_live_process_are_kept(tmp_path):
    out = tmp_path / "out"
    mine = tmp_path / f".out.matscan-tmp-{os.getppid()}-0badcafe"  # our parent process is alive
    mine.mkdir()
    assert clean_stale(out) == [] and mine.exists()


def test_interrupt_between_two_renames_restores_the_output(tmp_path):
    out = tmp_path / "out"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    old = tmp_path / f".out.matscan-old-{dead.pid}-0123abcd"
    old.mkdir()
    (old / "matscan.json").write_text('{"files": []}')
    clean_stale(out)  # the next writer's first step
    assert (out / "matscan.json").exists() and not old.exists()


def test_replacement_never_leaves_the_final_name_empty(tmp_path, monkeypatch):
    import matscan.atomic as atomic

    out = tmp_path / "out"
    out.mkdir()
    (out / "v").write_text("1")
    new = tmp_path / "new"
    new.mkdir()
    (new / "v").write_text("2")
    if exchange(tmp_path / "new", out):  # the swap itself: both names exist at every moment
        exchange(tmp_path / "new", out)  # swap back for the fallback test below
    monkeypatch.setattr(atomic, "exchange", lambda a, b: False)
    real_rename = Path.rename

    def interrupted(self, target):
        if self == new:
            raise KeyboardInterrupt
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", interrupted)
    with pytest.raises(KeyboardInterrupt):
        replace_folder(new, out)
    assert (out / "v").read_text() == "1"  # the old output is back under its name
    monkeypatch.setattr(Path, "rename", real_rename)
    replace_folder(new, out)
    assert (out / "v").read_text() == "2" and litter(tmp_path) == []


def test_sigterm_is_handled_like_ctrl_c(tmp_path):
    out = tmp_path / "out"
    started = tmp_path / "started"
    proc = _python(
        f"""
        import sys, time
        import matscan.cli as cli

        def slow(args):
            from matscan.outputs import claim_output
            with claim_output(args.out, "test", overwrite=False) as claim, claim.folder() as tmp:
                (tmp / "x.png").write_bytes(b"partial")
                open({str(started)!r}, "w").close()
                time.sleep(60)
            return "done"

        cli.cmd_synth = slow
        sys.exit(cli.main(["synth", "--out", {str(out)!r}, "--count", "1"]))
        """,
        stderr=subprocess.PIPE,
    )
    _wait_for(started.exists)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 130
    assert proc.stderr.read().strip() == "matscan: interrupted; nothing was written"
    assert not out.exists()
    assert litter(tmp_path) == []


def test_atomic_folder_turns_os_errors_into_one_line(tmp_path, monkeypatch):
    import errno

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(MatscanError, match="no space left") as exc:
        with atomic_folder(tmp_path / "o") as tmp:
            monkeypatch.setattr(Path, "write_bytes", full)
            (tmp / "a").write_bytes(b"x")
    assert "\n" not in str(exc.value)
    assert litter(tmp_path) == [] and not (tmp_path / "o").exists()


def test_a_file_added_to_the_old_output_during_the_work_is_kept(capture, tmp_path):
    out = tmp_path / "out"
    with claim_output(out, "test", [capture]) as claim, claim.folder() as tmp:
        (tmp / "a.png").write_bytes(b"first")
    with pytest.raises(MatscanError, match="appeared there during the work"):
        with claim_output(out, "test", [capture], overwrite=True) as claim, claim.folder() as tmp:
            (out / "notes.txt").write_text("written by the user while matscan worked")
            (tmp / "a.png").write_bytes(b"second")
    assert (out / "notes.txt").exists() and (out / "a.png").read_bytes() == b"first"
    assert litter(tmp_path) == []


def test_older_outputs_are_recognised_by_exact_names_only(tmp_path):
    old = tmp_path / "old"
    (old / "exr").mkdir(parents=True)
    (old / "matscan.json").write_text('{"format": "matscan-reconstruction/1"}')
    for name in ("diffuse.png", "report.html", "exr/normal.exr"):
        (old / name).write_bytes(b"x")
    assert foreign_entries(old) == []
    (old / "diffuse.psd").write_bytes(b"a user's file")
    (old / "exr" / "thesis.docx").write_bytes(b"a user's file")
    assert foreign_entries(old) == ["diffuse.psd", "exr/thesis.docx"]


def test_inline_calibration_flat_fields_are_inputs(tmp_path):
    from matscan.outputs import capture_inputs

    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.json").write_text(
        '{"format": "matscan-capture/1", "rig": "dome24", "images": [{"light": 0, "file": "a.png"}],'
        ' "calibration": {"format": "matscan-calibration/1", "flat_fields": {"0": "../flats/flat0.exr"}}}'
    )
    assert cap / "../flats/flat0.exr" in capture_inputs(cap)
    with pytest.raises(MatscanError, match="contains the input"):
        check_destination(tmp_path / "flats", [*capture_inputs(cap)], overwrite=True, overwrite_any=True)


# --- found by an audit of the command line (2026-11-30) ---------------------------------


@pytest.mark.parametrize("command", ["simulate", "synth"])
def test_a_capture_moved_into_an_output_of_the_command_that_makes_captures_is_kept(capture, capsys, tmp_path, command):
    """simulate and synth may replace their own captures, not one put among them since,
    whatever the flags."""
    out = tmp_path / "out"
    argv = {
        "simulate": ["simulate", "@sample", "--out", str(out), "--size", "16", "--lights", "6"],
        "synth": ["synth", "--out", str(out), "--count", "1", "--size", "16"],
    }[command]
    assert main(argv) == 0
    capture.rename(out / "real")
    assert_refused([*argv, "--overwrite", "--overwrite-any"], capsys, tmp_path, "holds a capture (real/capture.json)")


def test_synth_replaces_its_own_output(tmp_path, capsys):
    # its materials' own matscan.json files are files of its output, listed as such
    argv = ["synth", "--out", str(tmp_path / "s"), "--count", "1", "--size", "16"]
    assert main(argv) == 0
    assert main([*argv, "--seed", "3", "--overwrite"]) == 0, capsys.readouterr().err


def test_files_named_by_a_capture_json_with_a_byte_order_mark_are_inputs(tmp_path, capsys):
    """load_capture reads a capture.json that starts with a UTF-8 BOM; the output checks
    must see the photos it names as well."""
    assert main(["simulate", "@sample", "--out", str(tmp_path / "photos"), "--size", "16", "--lights", "6"]) == 0
    for p in tmp_path.glob("photos/*.json"):
        p.unlink()
    doc = {
        "format": "matscan-capture/1",
        "rig": "dome24",
        "images": [{"light": k, "file": f"../photos/led_{k:02d}.png"} for k in (0, 4, 8, 12, 16, 20)],
    }
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "capture.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(doc).encode())
    argv = ["reconstruct", str(tmp_path / "cap"), "--out", str(tmp_path / "photos"), "--overwrite", "--overwrite-any"]
    assert_refused([*argv, "--model", "none"], capsys, tmp_path, "contains the input")


def test_an_rti_light_file_naming_windows_paths_is_never_replaced(tmp_path, capsys):
    rti = tmp_path / "rti"
    rti.mkdir()
    for name in ("a.png", "b.png"):
        (rti / name).write_bytes(b"photo")
    (rti / "dirs.lp").write_text("2\nC:\\dome\\a.png 0.1 0.2 0.97\nC:\\dome\\b.png -0.3 0.1 0.95\n")
    argv = ["rig", "to-lp", "dome24", "--out", str(rti / "dirs.lp"), "--overwrite"]
    assert_refused(argv, capsys, rti, "is the light file of the RTI photos beside it (a.png")


def test_an_rti_light_file_in_the_windows_code_page_is_never_replaced(tmp_path, capsys):
    rti = tmp_path / "rti"
    rti.mkdir()
    for name in ("étude-a.png", "étude-b.png"):
        (rti / name).write_bytes(b"photo")
    (rti / "dirs.lp").write_bytes("2\nétude-a.png 0.1 0.2 0.97\nétude-b.png -0.3 0.1 0.95\n".encode("cp1252"))
    argv = ["rig", "to-lp", "dome24", "--out", str(rti / "dirs.lp"), "--overwrite"]
    assert_refused(argv, capsys, rti, "is the light file of the RTI photos beside it (étude-a.png")


def test_import_rti_counts_its_light_file_as_an_input(tmp_path, capsys):
    rti, lights = tmp_path / "rti", tmp_path / "lights"
    rti.mkdir()
    lights.mkdir()
    for name in ("a.png", "b.png"):
        (rti / name).write_bytes(b"photo")
    (lights / "dirs.lp").write_text("2\na.png 0.1 0.2 0.97\nb.png -0.3 0.1 0.95\n")
    argv = ["import-rti", str(rti), "--lp", str(lights / "dirs.lp"), "--out", str(lights)]
    assert_refused([*argv, "--overwrite", "--overwrite-any"], capsys, tmp_path, "contains the input")


def test_capture_checks_where_it_writes_before_opening_a_device(capture, capsys, tmp_path, monkeypatch):
    maps = tmp_path / "maps"
    (tmp_path / "elsewhere").mkdir()
    from matscan.mapset import read_mapset, write_mapset

    write_mapset(maps, read_mapset("@sample"))
    base = ["capture", "--leds", "virtual", "--lights", "6"]
    assert_refused(
        [*base, "--camera", f"virtual:{maps}", "--out", str(maps / "cap")], capsys, tmp_path, "lies inside the input"
    )
    assert_refused(
        [*base, "--camera", "virtual:@sample", "--out", str(capture / "new")], capsys, tmp_path, "lies in the capture"
    )
    assert_refused(
        [*base, "--camera", f"folder:{tmp_path / 'incoming'}", "--out", str(tmp_path / "incoming" / "c")],
        capsys,
        tmp_path,
        "lies inside the input",
    )
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert_refused([*base, "--camera", "virtual:@sample", "--out", "."], capsys, tmp_path, "is the current folder")


def test_a_failed_command_leaves_no_folders_it_made_for_its_output(tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "capture.json").write_text("{")
    code, err = run_cli(["reconstruct", str(bad), "--out", str(tmp_path / "new" / "a" / "out")], capsys)
    assert code == 2 and "capture.json: not valid JSON" in err
    assert not (tmp_path / "new").exists()
    (tmp_path / "kept").mkdir()  # a folder that was there stays
    code, err = run_cli(["reconstruct", str(bad), "--out", str(tmp_path / "kept" / "a" / "out")], capsys)
    assert code == 2 and (tmp_path / "kept").is_dir() and not (tmp_path / "kept" / "a").exists()


@pytest.mark.skipif(sys.platform == "darwin", reason="macOS file systems refuse names that are not UTF-8")
def test_a_path_that_is_not_utf8_is_refused_before_the_work(capture, capsys, tmp_path):
    odd = Path(os.fsdecode(bytes(tmp_path) + b"/cap\xff"))
    capture.rename(odd)
    argv = ["reconstruct", str(odd), "--out", str(tmp_path / "o"), "--model", "none"]
    assert_refused(argv, capsys, tmp_path, "cap\\xff: the path is not valid UTF-8")
    assert not (tmp_path / "o").exists()


def test_evaluate_checks_its_output_before_making_any_material(tmp_path, capsys, monkeypatch):
    import matscan.materials.procedural as procedural

    def never(*args, **kwargs):
        raise AssertionError("a material was made before the output was checked")

    monkeypatch.setattr(procedural, "random_material", never)
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "notes.txt").write_text("mine")
    assert_refused(["evaluate", "procedural:300", "--out", str(tmp_path / "e")], capsys, tmp_path, "not empty")


def test_running_out_of_memory_is_one_line(tmp_path, capsys, monkeypatch):
    import matscan.cli as cli

    def hungry(args):
        raise RuntimeError(
            "[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: not enough memory: you tried "
            "to allocate 120000000000 bytes."
        )

    monkeypatch.setattr(cli, "cmd_render", hungry)
    code, err = run_cli(["render", "@sample", "--out", str(tmp_path / "r.png"), "--light", "0,0,100"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "not enough memory" in err
    monkeypatch.setattr(cli, "cmd_render", lambda args: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):  # other errors are not dressed up as memory
        main(["render", "@sample", "--out", str(tmp_path / "r.png"), "--light", "0,0,100"])


def test_the_cli_keeps_the_rig_files_limits():
    import matscan.cli as cli
    import matscan.rig as rig

    assert (cli.MAX_MM, cli.MAX_INTENSITY, cli.MAX_EXPONENT) == (rig.MAX_MM, rig.MAX_INTENSITY, rig.MAX_EXPONENT)


def test_a_sheet_has_no_more_columns_than_tiles(tmp_path, capsys):
    from PIL import Image

    assert main(["sheet", "@sample", "--out", str(tmp_path / "a.png"), "--columns", "24"]) == 0
    assert main(["sheet", "@sample", "--out", str(tmp_path / "b.png"), "--columns", "100000"]) == 0
    assert Image.open(tmp_path / "b.png").size == Image.open(tmp_path / "a.png").size


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_a_pipe_named_as_a_json_file_is_refused_not_read(tmp_path):
    from matscan.jsonfile import read_json

    os.mkfifo(tmp_path / "rig.json")  # reading it would wait for a writer for ever
    with pytest.raises(MatscanError, match=r"rig\.json: not a regular file"):
        read_json(tmp_path / "rig.json")
    with pytest.raises(MatscanError, match=f"{tmp_path}: not a regular file"):
        read_json(tmp_path)


def test_control_characters_in_a_message_are_shown_escaped(tmp_path, capsys):
    lp = tmp_path / "lights.lp"
    lp.write_text("1\na\x07.png 0 0 1\n")
    code, err = run_cli(["import-rti", str(tmp_path), "--out", str(tmp_path.parent / "imported")], capsys)
    assert code == 2 and "\x07" not in err and "\\x07" in err


@pytest.mark.parametrize("family", [None, "leather"])
def test_the_largest_seed_is_one_every_command_can_use(tmp_path, capsys, family):
    # synth derives seed × 100003 + i, training (seed × 1000003 + i) × 7 + 3: within 2^63 − 1
    argv = ["synth", "--out", str(tmp_path / "s"), "--count", "2", "--size", "8", "--seed", str(2**31 - 1)]
    assert main([*argv, *(["--family", family] if family else [])]) == 0, capsys.readouterr().err


# --- inputs named by options, file kinds, training run folders ------------------------------


def _rig_file(path: Path) -> Path:
    from matscan.jsonfile import dumps
    from matscan.rig import rig_to_dict

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dumps(rig_to_dict(builtin_rig("dome24")), str(path)))
    return path


def test_synth_never_deletes_its_rig_file(tmp_path, capsys):
    # --overwrite --overwrite-any replaced the folder, the --rig file in it too
    rig = _rig_file(tmp_path / "d" / "rig.json")
    argv = ["synth", "--rig", str(rig), "--out", str(tmp_path / "d"), "--count", "1", "--size", "16", "--lights", "6"]
    assert_refused([*argv, "--overwrite", "--overwrite-any"], capsys, tmp_path / "d", "contains the input")


def test_evaluate_never_deletes_the_weights_its_methods_name(tmp_path, capsys):
    import shutil

    w = tmp_path / "w"
    w.mkdir()
    shutil.copy(ROOT / "matscan" / "weights" / "dome24-cpu.safetensors", w / "mine.safetensors")
    argv = ["evaluate", "artist", "--methods", f"nets:{w / 'mine.safetensors'}", "--lights", "6", "--size", "16"]
    assert_refused([*argv, "--out", str(w), "--overwrite", "--overwrite-any"], capsys, w, "contains the input")


@pytest.mark.parametrize(
    "argv, words",
    [
        (["rig", "from-lp", "LP", "--out", "PHOTO", "--overwrite"], "rig from-lp writes a .json file"),
        (["rig", "to-lp", "dome24", "--out", "PHOTO", "--overwrite"], "rig to-lp writes a .lp file"),
        (["calibrate", "--grey", "@sample", "--out", "PHOTO", "--overwrite"], "calibrate writes a .json file"),
        (["sheet", "@sample", "--out", "NOTES", "--overwrite"], "sheet writes a .png file"),
        (["rig", "from-lp", "LP", "--out", "UPPER", "--overwrite"], "rig from-lp writes a .json file"),
        # the right kind of file, but a capture's or a map set's
        (["sheet", "@sample", "--out", "PHOTO", "--overwrite"], "is a photo of the RTI capture"),
        (["rig", "from-lp", "LP", "--out", "MAPSET", "--overwrite"], "is the record of the map set"),
        (["sheet", "@sample", "--out", "MAP", "--overwrite"], "is a map of the map set"),
    ],
)
def test_a_command_writes_only_its_kind_of_file(tmp_path, capsys, argv, words):
    # rig from-lp --overwrite replaced an RTI photo its own .lp lists with rig JSON
    rti = tmp_path / "rti"
    rti.mkdir()
    (rti / "img_00.png").write_bytes(b"\x89PNG photo bytes")
    (rti / "notes").write_text("the lab's notes\n")
    (rti / "lights.lp").write_text("1\nimg_00.png 0 0 1\n")
    (rti / "rig.JSON").write_text("{}")  # the readers take .json only
    from conftest import random_maps

    from matscan.mapset import write_mapset

    write_mapset(rti / "set", random_maps(8))
    names = {
        "LP": str(rti / "lights.lp"),
        "PHOTO": str(rti / "img_00.png"),
        "NOTES": str(rti / "notes"),
        "UPPER": str(rti / "rig.JSON"),
        "MAPSET": str(rti / "set" / "mapset.json"),
        "MAP": str(rti / "set" / "diffuse.png"),
    }
    assert_refused([names.get(a, a) for a in argv], capsys, rti, words)


def test_training_runs_only_in_their_own_folders(tmp_path, capsys, capture):
    lab = capture.parent
    assert main(["synth", "--out", str(tmp_path / "s"), "--count", "1", "--size", "16"]) == 0
    maps = next((tmp_path / "s").glob("000_*/maps"))
    tiny = ["--preset", "tiny", "--crop", "16", "--batch", "1", "--workers", "0", "--max-steps", "1", "--device", "cpu"]
    assert_refused(["train", *tiny, "--out", str(capture)], capsys, lab, "is a capture folder")
    assert_refused(["train", *tiny, "--out", str(capture / "run")], capsys, lab, "lies in the capture")
    (lab / "log.csv").write_text("date,swatch\n2026-11-30,17\n")  # the lab's own log, where a run keeps its
    assert_refused(["train", *tiny, "--out", str(lab)], capsys, lab, "holds log.csv but no training run")
    anyrig = ["--max-steps", "1", "--size", "16", "--batch", "1", "--device", "cpu"]
    assert_refused(["train-anyrig", *anyrig, "--out", str(lab)], capsys, lab, "holds log.csv but no training run")
    assert_refused(["train-anyrig", *anyrig, "--out", str(maps)], capsys, maps.parent, "is a map set folder")
    (lab / "config.json").write_text("{}")  # a file of the lab's, by the name a run's config has
    assert_refused(["train", *tiny, "--out", str(lab)], capsys, lab, "is not a matscan train run's config")
    (lab / "log.csv").unlink()
    (lab / "config.json").write_text('{"exposure": 0.5}')
    assert_refused(["train-anyrig", *anyrig, "--out", str(lab)], capsys, lab, "is not a train-anyrig run's config")
    assert_refused(["train", *tiny, "--out", str(lab)], capsys, lab, "is not a matscan train run's config")


def test_a_training_run_resumes_in_the_current_folder(tmp_path, capsys, monkeypatch):
    # it never replaces its folder, so --out . is its own folder, not one to protect
    tiny = ["--preset", "tiny", "--crop", "16", "--batch", "1", "--workers", "0", "--device", "cpu", "--val-every", "0"]
    assert main(["train", *tiny, "--max-steps", "1", "--out", str(tmp_path / "run")]) == 0
    monkeypatch.chdir(tmp_path / "run")
    code, err = run_cli(["train", *tiny, "--max-steps", "1", "--out", "."], capsys)
    assert code == 0, err
    rows = (tmp_path / "run" / "log.csv").read_text().splitlines()
    assert rows[-1].split(",")[0] == "2", rows  # step 2: the run went on


def test_a_failed_training_start_leaves_no_run_behind(tmp_path, capsys):
    # config.json was written before the init weights were read, and blocked the corrected command
    bad = tmp_path / "w.safetensors"
    bad.write_text("x")
    run = tmp_path / "run"
    tiny = ["--preset", "tiny", "--crop", "16", "--batch", "1", "--workers", "0", "--device", "cpu", "--val-every", "0"]
    code, err = run_cli(["train", *tiny, "--max-steps", "1", "--out", str(run), "--init", str(bad)], capsys)
    assert code == 2 and "w.safetensors" in err and len(err.strip().splitlines()) == 1, err
    assert not (run / "config.json").exists()
    code, err = run_cli(["train", *tiny, "--max-steps", "1", "--out", str(run)], capsys)
    assert code == 0, err


@pytest.mark.parametrize(
    "settings, words",
    [
        ({"crop": "abc"}, "crop: expected an integer"),
        ({"maps": 5}, "maps: expected a non-empty list of map names, got 5"),
        ({"lr": "x"}, "lr: expected a finite number"),
        ({"steps": None}, "steps: expected an integer"),
        ({"batch": 0}, "batch: 0 must be at least 1"),
        ({"seed": -1}, "seed: -1 must be in"),
        ({"library": "folder"}, "library: expected a list of map set folders"),
    ],
)
def test_a_training_config_file_is_checked_setting_by_setting(tmp_path, capsys, settings, words):
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"preset": "tiny", "crop": 16, "workers": 0, **settings}))
    code, err = run_cli(["train", "--config", str(cfg), "--max-steps", "1", "--out", str(tmp_path / "run")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda p: p.write_text("garbage"), "is not a readable safetensors file"),
        (lambda p: p.write_bytes((ROOT / "matscan/weights/dome24-cpu.safetensors").read_bytes()), "no step"),
    ],
)
def test_train_anyrig_refuses_a_checkpoint_that_is_not_one(tmp_path, capsys, make, words):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text('{"train": {}, "net": {}}')
    make(run / "checkpoint.safetensors")
    argv = ["train-anyrig", "--max-steps", "1", "--size", "16", "--batch", "1", "--device", "cpu", "--out", str(run)]
    code, err = run_cli(argv, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, err


def test_train_anyrig_checks_its_device(tmp_path, capsys):
    argv = ["train-anyrig", "--max-steps", "1", "--size", "16", "--device", "tpu", "--out", str(tmp_path / "run")]
    code, err = run_cli(argv, capsys)
    assert code == 2 and "device: 'tpu' is not one of auto, cpu, cuda, cuda:N" in err, err
    assert not (tmp_path / "run").exists()


def test_evaluate_counts_the_shipped_networks_its_methods_use_as_inputs(tmp_path):
    # --methods nets (the default weights) with --out the weights' folder would delete them
    from matscan.evaluate import method_inputs
    from matscan.weights import model_path

    shipped = model_path("default")
    assert method_inputs(["baseline", "nets", "auto"]) == [shipped]
    assert method_inputs(["fit", "hsh"]) == []
    with pytest.raises(MatscanError, match="contains the input"):
        check_destination(shipped.parent, method_inputs(["nets"]), "folder", True, True, command="evaluate")
