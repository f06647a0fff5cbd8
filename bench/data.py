"""Training-data throughput: examples per second at 256² with all 24 dome24 lights.

Also prints procedural map sets generated per second at 256² (aim: at least 20).

Runs the training Dataset through a DataLoader with 2 worker processes (this
machine's 2 cores), after a warm-up in which each worker builds its fused kernels,
and prints examples per second beside the single-process rate measured in the same
run. Aim: at least 20 examples per second, so the networks, not the data, bound training.

Run by hand: .venv/bin/python bench/data.py [crop] [examples]
"""

from __future__ import annotations

import sys
import time

import torch
from torch.utils.data import DataLoader

from matscan.data import DataConfig, SvbrdfDataset
from matscan.materials.procedural import random_material


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    crop = int(sys.argv[1]) if len(sys.argv) > 1 else 256
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 200
    torch.set_num_threads(1)
    random_material(256, 0)
    t0 = time.perf_counter()
    for i in range(100):
        random_material(256, 1 + i)
    print(f"procedural map sets at 256²: {100 / (time.perf_counter() - t0):.1f} per second (1 process)")

    ds = SvbrdfDataset(DataConfig(crop=crop, subsets="24"), length=count + 64)

    for i in range(4):  # warm-up: kernels
        ds[i]
    t0 = time.perf_counter()
    single = 24
    for i in range(single):
        ds[100 + i]
    one = single / (time.perf_counter() - t0)

    loader = DataLoader(ds, batch_size=8, num_workers=2, persistent_workers=True, prefetch_factor=4)
    it = iter(loader)
    for _ in range(4):  # warm-up: workers start and build their kernels
        next(it)
    t0 = time.perf_counter()
    seen = 0
    for _ in range(count // 8):
        batch = next(it)
        seen += batch["inputs"].shape[0]
    two = seen / (time.perf_counter() - t0)
    print(
        f"crop {crop}², 24 lights: 1 process {one:.1f} examples/s; DataLoader with 2 workers {two:.1f} examples/s "
        f"({two / one:.2f}× the single process, same run)"
    )


if __name__ == "__main__":
    main()
