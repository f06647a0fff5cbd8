"""Time one training step of the map networks, and the share of it the rendering loss takes.

For each batch size, a fixed batch of the training data (prior v1, crop 128), the `cpu`
preset's four networks: forward, loss, backward and Adam's step, with the rendering loss
(``--render-lights``, 8 as in training) and without it. Prints the median seconds of
``--repeats`` steps after two warm-up steps, and the ratio of the two, measured in one run.
On a GPU the rendering loss was once most of a step: thousands of small kernels.

Run: .venv/bin/python bench/train_step.py [--batch 4,32] [--device cpu|cuda] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from matscan.data import SvbrdfDataset  # noqa: E402
from matscan.nets import network_input  # noqa: E402
from matscan.rig import resolve_rig  # noqa: E402
from matscan.train import (  # noqa: E402
    TrainConfig,
    _groups,
    batch_to,
    build_nets,
    data_config,
    loss_lights,
    resolve_device,
    step_loss,
    to_device,
)


def step_seconds(cfg: TrainConfig, b: dict, device: torch.device, repeats: int) -> float:
    rig = resolve_rig(cfg.rig)
    torch.manual_seed(0)
    nets = build_nets(cfg).to(device)
    opt = torch.optim.Adam(nets.parameters(), lr=cfg.lr)
    times = []
    for i in range(repeats + 2):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t = time.perf_counter()
        x = network_input(b["inputs"], b["present"], b["offset"], b["full_size"], rig)
        total, _ = step_loss(nets(x), b, cfg, rig, loss_lights(b, cfg, rig, device))
        opt.zero_grad(set_to_none=True)
        total.backward()
        for params in _groups(nets).values():
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if i >= 2:
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", default="4,32")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--render-lights", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    device = resolve_device(args.device)
    batches = [int(v) for v in args.batch.split(",")]
    data = SvbrdfDataset(data_config(TrainConfig()))
    samples = [data[i] for i in range(max(batches))]
    print(f"device {device}, torch {torch.__version__}, threads {torch.get_num_threads()}")
    print("batch  with rendering loss  without   ratio")
    for n in batches:
        b = to_device(batch_to(samples[:n]), device)
        with_r = step_seconds(TrainConfig(batch=n, render_lights=args.render_lights), b, device, args.repeats)
        without = step_seconds(TrainConfig(batch=n, render_lights=0), b, device, args.repeats)
        print(f"{n:5d}  {with_r:17.4f} s  {without:7.4f} s  {with_r / without:5.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
