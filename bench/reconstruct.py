"""Reconstruction cost end to end: `matscan reconstruct` as a user runs it.

Each case is a fresh process running the default command path
(`matscan reconstruct CAPTURE --out OUT`: load, networks, solver, maps, exports,
report) on a capture that `matscan simulate` wrote from the built-in sample (8-bit
sRGB, resampled to the size). Wall seconds include Python's start; the peak resident
memory is the OS's figure for that process (getrusage of the finished child).

Printed last: seconds per million pixel-lights for each case over the smallest
case's, so linear scaling in pixels × lights reads as ratios near 1 (measured in one
run: these machines are noisy).

With ``--allocator`` each case runs again with ``MATSCAN_MALLOC=system`` (glibc's own
allocation policy, not the one the command sets: ``matscan.allocator``), and the ratios
of time and memory are printed.

With ``--mirrors`` each case runs again with ``reconstruct --mirrors`` (the networks'
maps averaged over the rig's mirrors), and the ratio of the two times is printed.

With ``--self-calibrate`` the sample is photographed by a dome24 whose LEDs are off
their rig-file places and brightness as in bench/nearcal.py (±5 mm per axis, ±20%
brightness and ±3% colour with no gradient across the dome; its first draw), the
capture naming the plain dome24, and each case runs again with ``--self-calibrate``,
``--own-f0`` (the positions too, each pixel its own F0) and ``--self-calibrate-positions``
(one F0 for the dielectric pixels, its default), with their ratios to the plain run.

Run by hand: .venv/bin/python bench/reconstruct.py [SIZE ...] [--lights 6,24] [--solver lm|adam] [--mirrors]
[--allocator] [--self-calibrate]
(sizes default 256 512 1024; 3072 takes minutes and GBs: ask for it by name).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def matscan(*args: str) -> list[str]:
    return [sys.executable, "-m", "matscan.cli", *args]


def run_case(
    capture: Path, out: Path, solver: str, extra: tuple[str, ...] = (), env: dict[str, str] | None = None
) -> tuple[float, float]:
    """(wall seconds, peak RSS GiB from the child's rusage) of one reconstruction in a fresh process."""
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # the child becomes the command, so its peak memory is its own
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.dup2(null, 2)
        command = matscan("reconstruct", str(capture), "--out", str(out), "--solver", solver, *extra)
        os.execve(sys.executable, command, {**os.environ, **(env or {})})
    _, status, usage = os.wait4(pid, 0)
    seconds = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"bench: reconstruct of {capture} failed (exit {os.waitstatus_to_exitcode(status)})")
    return seconds, usage.ru_maxrss / 2**20


def off_rig(path: Path) -> Path:
    """A dome24 rig file whose LEDs are where and as bright as bench/nearcal.py's first
    draw puts them, for ``--self-calibrate``."""
    import dataclasses

    import torch

    sys.path.insert(0, str(Path(__file__).parent))
    from selfcal import led_gains

    from matscan.rig import builtin_rig, save_rig

    rig = builtin_rig("dome24")
    gains = led_gains(100)
    delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200)) * 2 - 1) * 5
    lights = tuple(
        dataclasses.replace(
            light,
            position_mm=tuple(float(v) for v in torch.tensor(light.position_mm) + delta[k]),
            intensity=tuple(float(v) for v in gains[k]),
        )
        for k, light in enumerate(rig.lights)
    )
    save_rig(dataclasses.replace(rig, name="dome24-off", lights=lights), path)
    return path


def named_dome24(capture: Path) -> None:
    """The capture's rig set to the plain dome24 (the one it would name: the rig file)."""
    import json

    meta = json.loads((capture / "capture.json").read_text())
    meta["rig"] = "dome24"
    (capture / "capture.json").write_text(json.dumps(meta, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sizes", nargs="*", type=int, default=[256, 512, 1024])
    parser.add_argument("--lights", default="6,24")
    parser.add_argument("--solver", default="lm", choices=["lm", "adam"])
    parser.add_argument(
        "--mirrors", action="store_true", help="each case also with reconstruct --mirrors, and the ratio of the two"
    )
    parser.add_argument(
        "--self-calibrate",
        dest="self_calibrate",
        action="store_true",
        help="LEDs off their rig-file places; each case also with the three self-calibrations",
    )
    parser.add_argument(
        "--allocator",
        action="store_true",
        help="each case also with MATSCAN_MALLOC=system (glibc's own policy), and the ratio of the two",
    )
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        rig = ["--rig", str(off_rig(Path(tmp) / "off.json"))] if args.self_calibrate else []
        for size in args.sizes:
            for lights in args.lights.split(","):
                cap = Path(tmp) / f"cap{size}_{lights}"
                subprocess.run(
                    matscan("simulate", "@sample", "--out", str(cap), "--size", str(size), "--lights", lights, *rig),
                    check=True,
                    capture_output=True,
                )
                if args.self_calibrate:
                    named_dome24(cap)
                seconds, peak = run_case(cap, Path(tmp) / f"out{size}_{lights}", args.solver)
                work = size * size * int(lights) / 1e6
                rows.append((size, int(lights), seconds, peak, seconds / work))
                print(f"{size:>6}² {lights:>3} lights: {seconds:7.1f} s wall, peak RSS {peak:5.2f} GiB", flush=True)
                if args.allocator:
                    env = {"MATSCAN_MALLOC": "system"}
                    more, more_peak = run_case(cap, Path(tmp) / f"system{size}_{lights}", args.solver, env=env)
                    print(
                        f"{'':>7} {'':>3} glibc's own policy: {more:7.1f} s wall, peak RSS {more_peak:5.2f} GiB; "
                        f"the command's: {seconds / more:.2f} × the time, {peak / more_peak:.2f} × the memory",
                        flush=True,
                    )
                if args.mirrors:
                    more, peak = run_case(cap, Path(tmp) / f"mirrors{size}_{lights}", args.solver, ("--mirrors",))
                    print(
                        f"{'':>7} {'':>3} with --mirrors: {more:7.1f} s wall, peak RSS {peak:5.2f} GiB, "
                        f"{more / seconds:.2f} × the time",
                        flush=True,
                    )
                if args.self_calibrate:
                    for flag in ("--self-calibrate", "--own-f0", "--self-calibrate-positions"):
                        more, peak = run_case(cap, Path(tmp) / f"{flag[2:]}{size}_{lights}", args.solver, (flag,))
                        print(
                            f"{'':>7} {'':>3} with {flag}: {more:7.1f} s wall, peak RSS {peak:5.2f} GiB, "
                            f"{more / seconds:.2f} × the time",
                            flush=True,
                        )
    base = rows[0][4]
    print(f"\nsolver {args.solver}; seconds per million pixel-lights, relative to {rows[0][0]}² × {rows[0][1]}:")
    for size, lights, _, _, per in rows:
        print(f"  {size:>6}² × {lights:>2}: {per / base:5.2f}")


if __name__ == "__main__":
    main()
