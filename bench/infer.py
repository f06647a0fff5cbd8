"""Inference cost of the four map networks on a 512² dome24 capture, per preset.

For each preset (cpu, paper) it runs the four networks once to warm up and once
timed, in a fresh process, and prints seconds, peak resident memory, the FLOPs
of the forward pass (counted by torch's FlopCounterMode), the achieved GFLOP/s,
and that as a fraction of this machine's fp32 matmul GFLOP/s measured in the same
run (2048² matmul, 2 threads).

Run by hand: .venv/bin/python bench/infer.py
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from matscan.nets import MapNets, network_input, preset
from matscan.rig import builtin_rig

SIZE = 512


def matmul_gflops() -> float:
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    t0 = time.perf_counter()
    reps = 10
    for _ in range(reps):
        a @ b
    return reps * 2 * 2048**3 / (time.perf_counter() - t0) / 1e9


def case(name: str) -> dict:
    torch.set_num_threads(2)
    nets = MapNets(24, preset(name)).eval()
    photos = torch.rand(1, 24, 3, SIZE, SIZE)
    x = network_input(photos, torch.ones(1, 24), None, None, builtin_rig("dome24"))
    with torch.no_grad():
        with FlopCounterMode(display=False) as counter:
            nets(x)
        t0 = time.perf_counter()
        nets(x)
        seconds = time.perf_counter() - t0
    return {
        "seconds": seconds,
        "flops": counter.get_total_flops(),
        "peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
    }


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    if len(sys.argv) == 2:
        print(json.dumps(case(sys.argv[1])))
        return
    torch.set_num_threads(2)
    peak = matmul_gflops()
    print(f"fp32 matmul 2048²: {peak:.0f} GFLOP/s (2 threads, this run)")
    print(f"{'preset':>7} {'seconds':>8} {'GFLOP':>8} {'GFLOP/s':>8} {'of matmul':>10} {'peak GiB':>9}")
    for name in ("cpu", "paper"):
        out = subprocess.run([sys.executable, __file__, name], capture_output=True, text=True, check=True)
        r = json.loads(out.stdout)
        rate = r["flops"] / r["seconds"] / 1e9
        print(
            f"{name:>7} {r['seconds']:>8.2f} {r['flops'] / 1e9:>8.1f} {rate:>8.1f} {rate / peak:>9.0%} "
            f"{r['peak_gib']:>9.2f}"
        )


if __name__ == "__main__":
    main()
