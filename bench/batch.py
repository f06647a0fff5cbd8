"""Throughput of `matscan batch` against `matscan reconstruct` run in a loop.

N small virtual captures (the built-in sample through dome24, 24 lights, SIZE² px) are
reconstructed three ways, each into a fresh folder: `matscan reconstruct` once per capture
in a shell-style loop (a new process each time), `matscan batch --workers 1`, and
`matscan batch --workers 2` (torch threads per worker: cores ÷ workers). Printed:
captures per minute for each, and the ratios to the loop, measured in this one run.

Run by hand: .venv/bin/python bench/batch.py [N] [SIZE]   (default 8 captures of 128²)
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from matscan.capture.virtual import CameraModel, simulate
from matscan.mapset import read_mapset
from matscan.rig import builtin_rig


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 8
    size = int(sys.argv[2]) if len(sys.argv) > 2 else 128
    root = Path(tempfile.mkdtemp(prefix="matscan-bench-batch-"))
    maps, rig = read_mapset("@sample"), builtin_rig("dome24")
    caps = []
    for i in range(n):
        caps.append(simulate(maps, rig, root / f"cap{i:02d}", camera=CameraModel(read_noise=0.002), seed=i, size=size))
    exe = [sys.executable, "-m", "matscan.cli"]
    rates = {}
    t0 = time.perf_counter()
    for i, cap in enumerate(caps):
        subprocess.run(
            [*exe, "reconstruct", str(cap), "--out", str(root / "loop" / f"cap{i:02d}")],
            check=True,
            capture_output=True,
        )
    rates["reconstruct loop"] = n / (time.perf_counter() - t0) * 60
    for workers in (1, 2):
        t0 = time.perf_counter()
        subprocess.run(
            [*exe, "batch", *map(str, caps), "--out", str(root / f"batch{workers}"), "--workers", str(workers)],
            check=True,
            capture_output=True,
        )
        rates[f"batch, {workers} worker{'s' if workers > 1 else ''}"] = n / (time.perf_counter() - t0) * 60
    base = rates["reconstruct loop"]
    print(f"{n} captures of {size}² px, 24 lights")
    for name, rate in rates.items():
        print(f"  {name:22s} {rate:7.1f} captures/min   ×{rate / base:.2f}")
    print(f"(files under {root})")


if __name__ == "__main__":
    main()
