"""Reconstruction cost end to end: `matscan reconstruct` as a user runs it.

Each case is a fresh process running the default command path
(`matscan reconstruct CAPTURE --out OUT`: load, networks, solver, maps, exports,
report) on a capture that `matscan simulate` wrote from the built-in sample (8-bit
sRGB, resampled to the size). Wall seconds include Python's start; the peak resident
memory is the OS's figure for that process (getrusage of the finished child).

Printed last: seconds per million pixel-lights for each case over the smallest
case's, so linear scaling in pixels × lights reads as ratios near 1 (measured in one
run: these machines are noisy).

With ``--mirrors`` each case runs again with ``reconstruct --mirrors`` (the networks'
maps averaged over the rig's mirrors), and the ratio of the two times is printed.

Run by hand: .venv/bin/python bench/reconstruct.py [SIZE ...] [--lights 6,24] [--solver lm|adam] [--mirrors]
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


def run_case(capture: Path, out: Path, solver: str, extra: tuple[str, ...] = ()) -> tuple[float, float]:
    """(wall seconds, peak RSS GiB from the child's rusage) of one reconstruction in a fresh process."""
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # the child becomes the command, so its peak memory is its own
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.dup2(null, 2)
        os.execv(sys.executable, matscan("reconstruct", str(capture), "--out", str(out), "--solver", solver, *extra))
    _, status, usage = os.wait4(pid, 0)
    seconds = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"bench: reconstruct of {capture} failed (exit {os.waitstatus_to_exitcode(status)})")
    return seconds, usage.ru_maxrss / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sizes", nargs="*", type=int, default=[256, 512, 1024])
    parser.add_argument("--lights", default="6,24")
    parser.add_argument("--solver", default="lm", choices=["lm", "adam"])
    parser.add_argument(
        "--mirrors", action="store_true", help="each case also with reconstruct --mirrors, and the ratio of the two"
    )
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            for lights in args.lights.split(","):
                cap = Path(tmp) / f"cap{size}_{lights}"
                subprocess.run(
                    matscan("simulate", "@sample", "--out", str(cap), "--size", str(size), "--lights", lights),
                    check=True,
                    capture_output=True,
                )
                seconds, peak = run_case(cap, Path(tmp) / f"out{size}_{lights}", args.solver)
                work = size * size * int(lights) / 1e6
                rows.append((size, int(lights), seconds, peak, seconds / work))
                print(f"{size:>6}² {lights:>3} lights: {seconds:7.1f} s wall, peak RSS {peak:5.2f} GiB", flush=True)
                if args.mirrors:
                    more, peak = run_case(cap, Path(tmp) / f"mirrors{size}_{lights}", args.solver, ("--mirrors",))
                    print(
                        f"{'':>7} {'':>3} with --mirrors: {more:7.1f} s wall, peak RSS {peak:5.2f} GiB, "
                        f"{more / seconds:.2f} × the time",
                        flush=True,
                    )
    base = rows[0][4]
    print(f"\nsolver {args.solver}; seconds per million pixel-lights, relative to {rows[0][0]}² × {rows[0][1]}:")
    for size, lights, _, _, per in rows:
        print(f"  {size:>6}² × {lights:>2}: {per / base:5.2f}")


if __name__ == "__main__":
    main()
