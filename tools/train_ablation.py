"""Train the paper's ablation variants side by side: one process, one batch stream per seed.

Every (variant, seed) pair is a run of its own (``OUT/VARIANT-sSEED``: ``config.json``,
``log.csv``, ``val.csv``, ``checkpoint.safetensors``, and at the end the float16 weights
``OUT/VARIANT-sSEED.safetensors``), trained exactly as ``matscan train`` would train that
config (the same samples, novel lights, losses, clipping and Adam; a test checks one
pair's weights against ``train()``'s). What is shared is the work: the variants of one
seed see the same batches, rendered once by that seed's data workers, so they are compared
on identical data (a paired design), and seeds differ in both initial weights and data.
All pairs stop at the same step, when ``--minutes`` have passed or at ``--steps``.

Made for a GPU lease, where the data workers, not the GPU, set the pace of one run:
four variants × two seeds cost little more than one run. It runs on the CPU too (slowly).

Run (from the repository root; needs torch, numpy, safetensors, tqdm, opencv as ``matscan
train`` does):

    PYTHONPATH=. python3 tools/train_ablation.py --out runs/ablation-gpu --minutes 16 \\
        --seeds 0,1 --batch 32 --lr 2e-4 --workers 6

then score the weights (``tools/nets_unlike.py OUT/*.safetensors``).

``--resume DIR`` goes on from an earlier call's float16 weights (``DIR/VARIANT-sSEED.safetensors``,
what comes back from a GPU lease, where the checkpoints with Adam's state are too large to
bring back): every run starts at its weights and their step (all the same step), with a
fresh Adam, and each seed's batches go on where they stopped (the samples of steps
``step``, ``step`` + 1, …, as an uninterrupted run draws them). ``OUT`` must be a new folder.

``--ema D`` keeps each run's exponential moving average of its weights (decay ``D`` a
step, ``TrainConfig.ema``), as ``train()`` does: the checkpoint holds it beside the
weights, and the float16 export is the average, not the last step's weights. With a
constant learning rate the last weights wander from step to step (docs/results.md, Table
9: the variants' order turned at each budget); the average over the last ``1 / (1 - D)``
steps or so is the steadier endpoint to compare. A ``--resume`` from such exports goes on
from the averages.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from matscan.data import SvbrdfDataset, fixed_validation_set  # noqa: E402
from matscan.nets import VARIANTS, network_input  # noqa: E402
from matscan.rig import resolve_rig  # noqa: E402
from matscan.train import (  # noqa: E402
    CHECKPOINT,
    StepSampler,
    TrainConfig,
    _append_csv,
    _groups,
    build_nets,
    data_config,
    export_weights,
    loss_lights,
    resolve_device,
    save_checkpoint,
    step_loss,
    to_device,
    validate,
)


def run_name(cfg: TrainConfig) -> str:
    return f"{cfg.variant}-s{cfg.seed}"


def train_together(
    configs: list[TrainConfig], out: Path, minutes: float, progress: bool = True, resume: Path | None = None
) -> dict[str, dict[str, float]]:
    """Train every config from scratch (or from ``resume``'s weights, module doc), side by
    side, until ``minutes`` have passed or each reached its ``steps`` (all have the same);
    configs of one seed share a batch stream, so they must agree on everything that shapes
    the data. Returns each run's last validation."""
    from tqdm import tqdm

    from matscan.weights.format import load_weights

    base = configs[0]
    for cfg in configs:
        same = {k: v for k, v in asdict(cfg).items() if k not in ("variant", "seed")}
        if same != {k: v for k, v in asdict(base).items() if k not in ("variant", "seed")}:
            raise SystemExit(f"train_ablation: {run_name(cfg)} differs from {run_name(base)} beyond variant and seed")
        if cfg.init:
            raise SystemExit("train_ablation: the variants train from scratch (no init)")
    device = resolve_device(base.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    rig = resolve_rig(base.rig)
    runs = {}
    starts = {}
    averages: dict[str, dict[str, torch.Tensor]] = {}  # each run's moving average of its weights (cfg.ema)
    for cfg in configs:
        folder = out / run_name(cfg)
        if (folder / CHECKPOINT).exists():
            raise SystemExit(f"train_ablation: {folder} already holds a run; choose another --out")
        torch.manual_seed(cfg.seed)  # as train() does, so each run starts from train()'s weights
        nets = build_nets(cfg)
        if resume is not None:
            path = resume / f"{run_name(cfg)}.safetensors"
            if not path.is_file():
                raise SystemExit(f"train_ablation: {path}: no such weights file to resume {run_name(cfg)} from")
            loaded, meta = load_weights(path)
            if loaded.variant != cfg.variant or loaded.state_dict().keys() != nets.state_dict().keys():
                raise SystemExit(f"train_ablation: {path}: its networks are not those of {run_name(cfg)} here")
            nets.load_state_dict(loaded.state_dict())
            starts[run_name(cfg)] = int(meta["step"])
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "config.json").write_text(json.dumps(asdict(cfg), indent=2) + "\n")
        nets = nets.to(device)
        runs[run_name(cfg)] = (cfg, folder, nets, torch.optim.Adam(nets.parameters(), lr=cfg.lr))
        if cfg.ema:  # as train() starts it: from the weights now (those resumed from, if any)
            averages[run_name(cfg)] = {k: v.detach().clone() for k, v in nets.state_dict().items()}
    if len(set(starts.values())) > 1:
        raise SystemExit(f"train_ablation: {resume}: the runs stopped at different steps ({starts})")
    start = next(iter(starts.values()), 0)
    seeds = sorted({cfg.seed for cfg in configs})
    seed_cfg = {seed: next(c for c in configs if c.seed == seed) for seed in seeds}
    loaders = {}
    for seed, cfg in seed_cfg.items():
        loaders[seed] = iter(
            DataLoader(
                SvbrdfDataset(data_config(cfg)),
                batch_sampler=StepSampler(start, cfg.batch),
                num_workers=cfg.workers,
                persistent_workers=cfg.workers > 0,
                prefetch_factor=cfg.prefetch if cfg.workers > 0 else None,
                multiprocessing_context="spawn" if cfg.workers > 0 else None,
                pin_memory=device.type == "cuda",
            )
        )
    val_samples = fixed_validation_set(base.val_count, base.crop, base.rig) if base.val_every else []
    deadline = time.monotonic() + minutes * 60
    t0 = time.monotonic()
    step = start
    last_val: dict[str, dict[str, float]] = {}
    bar = tqdm(total=base.steps, initial=start, desc="train", unit="step", disable=not progress, mininterval=10)
    while step < base.steps and time.monotonic() < deadline:
        for seed in seeds:
            b = to_device(next(loaders[seed]), device)
            x = network_input(b["inputs"], b["present"], b["offset"], b["full_size"], rig)
            render = loss_lights(b, seed_cfg[seed], rig, device)
            for cfg, folder, nets, opt in runs.values():
                if cfg.seed != seed:
                    continue
                total, terms = step_loss(nets(x), b, cfg, rig, render)
                opt.zero_grad(set_to_none=True)
                total.backward()
                for params in _groups(nets).values():
                    torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
                opt.step()
                if cfg.ema:
                    with torch.no_grad():
                        for k, v in nets.state_dict().items():
                            averages[run_name(cfg)][k].lerp_(v, 1 - cfg.ema)
                if (step + 1) % cfg.log_every == 0:
                    row = {"step": step + 1, "seconds": round(time.monotonic() - t0, 1)}
                    _append_csv(folder / "log.csv", {**row, **{k: round(v, 6) for k, v in terms.items()}})
        step += 1
        bar.update(1)
        if base.val_every and step % base.val_every == 0:
            for name, (_cfg, folder, nets, _opt) in runs.items():
                last_val[name] = validate(nets, val_samples, rig)
                _append_csv(folder / "val.csv", {"step": step, **{k: round(v, 6) for k, v in last_val[name].items()}})
            worst = {k: max(v[k] for v in last_val.values()) for k in ("rmse_specular", "rmse_roughness")}
            print(f"step {step}, {time.monotonic() - t0:.0f} s: worst {worst}", flush=True)
    bar.close()
    seconds = time.monotonic() - t0
    for name, (cfg, folder, nets, opt) in runs.items():
        if base.val_every and step % base.val_every:
            last_val[name] = validate(nets, val_samples, rig)
            _append_csv(folder / "val.csv", {"step": step, **{k: round(v, 6) for k, v in last_val[name].items()}})
        save_checkpoint(folder / CHECKPOINT, nets, opt, step, cfg, seconds, ema=averages.get(name))
        export_weights(folder / CHECKPOINT, out / f"{name}.safetensors", {"run": str(folder)}, dtype=torch.float16)
    summary = {
        "steps": step,
        "resumed_from": None if resume is None else {"folder": str(resume), "step": start},
        "seconds": round(seconds, 1),
        "steps_per_second": round((step - start) / max(seconds, 1e-9), 3),
        "device": str(device) + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""),
        "torch": torch.__version__,
        "runs": {
            n: {"parameters": sum(p.numel() for p in r[2].parameters()), **last_val.get(n, {})} for n, r in runs.items()
        },
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return last_val


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--minutes", type=float, required=True, help="wall time of the training")
    parser.add_argument("--steps", type=int, default=1_000_000, help="or stop at this step")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--prior", default="v1")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--crop", type=int, default=128)
    parser.add_argument("--lr", type=float, default=2e-4)
    parser.add_argument("--workers", type=int, default=6, help="data worker processes per seed")
    parser.add_argument("--prefetch", type=int, default=4)
    parser.add_argument("--val-every", type=int, default=250)
    parser.add_argument("--val-count", type=int, default=32)
    parser.add_argument("--render-lights", type=int, default=8)
    parser.add_argument("--log-every", type=int, default=20)
    parser.add_argument("--device", default="auto")
    parser.add_argument(
        "--ema", type=float, default=0.0, help="keep the weights' moving average, this decay a step, and export it"
    )
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--resume", type=Path, help="go on from the float16 weights in this folder (module doc)")
    args = parser.parse_args()
    if not 0 <= args.ema < 1:
        parser.error(f"--ema: {args.ema} must be a decay per step in [0, 1) (0: no moving average)")
    variants = args.variants.split(",")
    for v in variants:
        if v not in VARIANTS:
            parser.error(f"--variants: {v!r} is not one of {', '.join(VARIANTS)}")
    common = TrainConfig(
        preset=args.preset,
        prior=args.prior,
        batch=args.batch,
        crop=args.crop,
        lr=args.lr,
        steps=args.steps,
        workers=args.workers,
        prefetch=args.prefetch,
        val_every=args.val_every,
        val_count=args.val_count,
        render_lights=args.render_lights,
        log_every=args.log_every,
        device=args.device,
        ema=args.ema,
    )
    configs = [replace(common, variant=v, seed=int(s)) for s in args.seeds.split(",") for v in variants]
    last = train_together(configs, args.out, args.minutes, progress=not args.no_progress, resume=args.resume)
    for name, val in last.items():
        print(name, " ".join(f"{k} {v:.4f}" for k, v in val.items()))
    return 0 if all(math.isfinite(v) for val in last.values() for v in val.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
