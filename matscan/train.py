"""Training: the map networks on the material prior, with checkpoints, resume and DDP.

One run lives in a folder::

    RUN/config.json              the TrainConfig (written once; a resume must match it,
                                 except in where it runs: RUNTIME_FIELDS)
    RUN/checkpoint.safetensors   weights + Adam state + step (overwritten atomically),
                                 and with ``ema`` the weights' moving average (ema.*),
                                 which exports, snapshots and ``init`` take
    RUN/log.csv                  one row per logged step: losses per map and their terms
    RUN/val.csv                  validation RMSE per map every ``val_every`` steps
    RUN/snapshots/step-N.safetensors
                                 the weights at step N, every ``snapshot_every`` steps
                                 (float16, the networks only, filled from ``init``)

A run is deterministic given its config: sample i of the data, and the novel
lights of its rendering loss, are fixed by (seed, i); step s uses samples
s·B·W … (s+1)·B·W − 1 (B batch, W processes). So stopping and resuming from the checkpoint continues the same run.

A run may start from trained weights (``init``: a checkpoint or an exported weights
file) with a fresh Adam state: a second stage of training under a changed network
config (say, another ``photo_statistic``). It records the training behind those
weights (``init_step``, ``init_elapsed_seconds``, ``init_photo_statistic``, and per
network ``init_networks``, since an assembled file's networks had different training)
and draws the samples after the ones they saw: its step s uses the samples of step
``init_step`` + s.

Checkpoints and weights store the network config they were trained with
(``net_config``); a resumed run keeps it, whatever the preset says now. Files
written before that field existed load with the median ``photo_statistic`` they
were trained with (:func:`net_config_of`).

The materials come from the procedural prior named by ``prior`` ("v1", the default,
draws what every earlier run drew; see :data:`matscan.materials.procedural.PRIORS`).
Validation always uses the v1 set, so runs on either prior compare on one scale.

Rendering loss: ``render_with`` "own" (the paper's) gives each network its own
rendering term, the other maps from the truth; "joint" renders every trained map's
prediction together (the untrained maps from the truth) and adds that term once
(:mod:`matscan.losses`), so the networks learn to relight well together.

Device: ``device`` "auto" trains on CUDA where there is one, else on the CPU. The
networks, the batch and the losses live there; the data workers render on the CPU
(``workers`` processes, each ``prefetch`` batches ahead, into pinned memory on CUDA);
checkpoints hold CPU tensors, so a run started on a GPU resumes on a CPU and back.
Where a run executes (``device``, ``workers``, ``prefetch``) does not change its
samples, so a resume may change those.

Data-parallel: started under ``torchrun --nproc_per_node N -m matscan.cli train …``
each process trains on its share of every step's samples and gradients are
averaged (DDP; gloo on CPU, NCCL on GPU, one GPU per process). Only rank 0 writes files.
"""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file
from torch import Tensor
from torch.utils.data import DataLoader, Sampler

from matscan.atomic import atomic_file, write_text
from matscan.data import DataConfig, SvbrdfDataset, fixed_validation_set
from matscan.errors import MatscanError, input_error, not_a_folder
from matscan.jsonfile import (
    check_bool,
    check_int,
    check_number,
    check_object,
    check_string,
    loads_text,
    read_json,
    short_repr,
)
from matscan.losses import LAMBDA_MAP, LAMBDA_RENDER, map_loss, novel_lights, rendering_loss, truth_rendering
from matscan.nets import MAPS, PRESETS, VARIANTS, MapNets, NetConfig, lights_to, network_input, preset
from matscan.render import surface_points
from matscan.rig import LightSet, Rig, resolve_rig
from matscan.weights.format import EMA, _trained, network_names, training_record
from matscan.weights.format import check_maps as _check_maps
from matscan.weights.format import load_weights as load_weights  # re-exported: tools and tests load through train
from matscan.weights.format import metadata as _metadata
from matscan.weights.format import net_config_of as _net_config_of

CHECKPOINT = "checkpoint.safetensors"


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run."""

    preset: str = "cpu"
    variant: str = "four"
    maps: tuple[str, ...] = MAPS
    rig: str = "dome24"
    crop: int = 128
    batch: int = 4
    lr: float = 1e-4
    steps: int = 200_000
    render_lights: int = 8
    lambda_map: float = LAMBDA_MAP
    lambda_render: float = LAMBDA_RENDER
    grad_clip: float = 1.0
    val_every: int = 1000
    val_count: int = 32
    log_every: int = 20
    checkpoint_minutes: float = 10.0
    workers: int = 1
    seed: int = 0
    init: str = ""  # start a new run from these weights (checkpoint or exported file); "" = from scratch
    prior: str = "v1"  # the procedural material prior (matscan.materials.procedural.PRIORS)
    device: str = "auto"  # "auto" (CUDA if available, else CPU), "cpu", "cuda", "cuda:N"
    prefetch: int = 4  # batches each data worker prepares ahead
    library: tuple[str, ...] = ()  # map set folders drawn instead of the prior (tools/photo_library.py)
    library_prob: float = 0.5  # the share of samples drawn from them, when given
    library_metal_prob: float = 0.0  # the share of those given metal patches (matscan.data.metallize)
    render_with: str = "own"  # "own": each network's rendering term, the rest true; "joint": one for all
    named_subset_prob: float = 0.5  # the share of samples lit by one of the rig's named subsets (the rest: random)
    snapshot_every: int = 0  # keep the weights every N steps in RUN/snapshots (0: none), to score a run along its way
    # also keep the weights' exponential moving average, this decay per step (0: none); the
    # checkpoint holds it as ema.*, and exports and snapshots take it in place of the weights
    ema: float = 0.0

    @staticmethod
    def from_dict(data: dict[str, Any], where: str = "config") -> TrainConfig:
        names = {f.name for f in fields(TrainConfig)}
        for key in data:
            if key not in names:
                raise MatscanError(f"{where}: unknown key {key!r} (expected one of {', '.join(sorted(names))})")
        data = dict(data)
        for key in ("maps", "library"):
            if key in data:
                data[key] = tuple(data[key])
        return TrainConfig(**data)


class StepSampler(Sampler[list[int]]):
    """Batches of sample indices for steps ``start``, ``start`` + 1, … (this rank's share)."""

    def __init__(self, start: int, batch: int, rank: int = 0, world: int = 1) -> None:
        self.start, self.batch, self.rank, self.world = start, batch, rank, world

    def __iter__(self) -> Iterator[list[int]]:
        step = self.start
        while True:
            base = (step * self.world + self.rank) * self.batch
            yield list(range(base, base + self.batch))
            step += 1

    def __len__(self) -> int:  # nominal
        return 2**31


def build_nets(cfg: TrainConfig, net: NetConfig | None = None) -> MapNets:
    """The networks of a run: ``net`` (a stored config), or else the preset's."""
    rig = resolve_rig(cfg.rig)
    return MapNets(len(rig.lights), net or preset(cfg.preset), cfg.variant, cfg.maps)


def data_config(cfg: TrainConfig) -> DataConfig:
    """How a run draws its samples; checks the prior, and that every library folder is
    there (before any work)."""
    for folder in cfg.library:
        if not Path(folder).is_dir():
            raise not_a_folder(folder, "map set folder (library)")
    if not 0 <= cfg.library_prob <= 1:
        raise MatscanError(f"library_prob: {cfg.library_prob!r} must be between 0 and 1")
    if not 0 <= cfg.library_metal_prob <= 1:
        raise MatscanError(f"library_metal_prob: {cfg.library_metal_prob!r} must be between 0 and 1")
    if not 0 <= cfg.named_subset_prob <= 1:
        raise MatscanError(f"named_subset_prob: {cfg.named_subset_prob!r} must be between 0 and 1")
    return DataConfig(
        rig=cfg.rig,
        crop=cfg.crop,
        seed=cfg.seed,
        prior=cfg.prior,
        library=cfg.library,
        library_prob=cfg.library_prob,
        library_metal_prob=cfg.library_metal_prob,
        named_subset_prob=cfg.named_subset_prob,
    )


#: The forms of the rendering loss (TrainConfig.render_with).
RENDER_WITH = ("own", "joint")

#: TrainConfig fields that say where a run executes, not what it computes: a resume may change them.
RUNTIME_FIELDS = ("device", "workers", "prefetch", "snapshot_every")


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """The device a run trains on: ``name`` is "auto" (CUDA if available, else the CPU),
    "cpu", "cuda" or "cuda:N". Under torchrun, "auto" and "cuda" take GPU ``local_rank``."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name != "cpu" and not (name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit())):
        raise MatscanError(f"device: {name!r} is not one of auto, cpu, cuda, cuda:N")
    if name == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise MatscanError(f"device: {name!r}, but this torch ({torch.__version__}) sees no CUDA device")
    device = torch.device(f"cuda:{local_rank}" if name == "cuda" else name)
    if device.index >= torch.cuda.device_count():
        raise MatscanError(f"device: {device} does not exist (this machine has {torch.cuda.device_count()} GPUs)")
    return device


#: Metadata of the weights a run started from (``init``), carried into its checkpoints and exports.
INIT_KEYS = ("init", "init_step", "init_elapsed_seconds", "init_photo_statistic", "init_networks")


def net_config_of(meta: dict[str, str], cfg: TrainConfig, where: str = "weights") -> NetConfig:
    """The network config a checkpoint or weights file was trained with
    (:func:`matscan.weights.format.net_config_of`, with the run's preset as the fallback)."""
    return _net_config_of(meta, cfg.preset, where)


def _config_of(meta: dict[str, str], path: Path) -> TrainConfig:
    """The training config stored in a checkpoint's or weights file's metadata, checked."""
    key = "train_config" if meta.get("train_config") else "config"
    if not meta.get(key):
        raise input_error(path, "not a matscan weights file (no training config in its metadata)")
    where = f"{path}: {key}"
    return check_train_config(loads_text(meta[key], where), where)


def check_train_config(data: Any, where: str) -> TrainConfig:
    """A :class:`TrainConfig` from its stored JSON object, every field checked by type
    (and the ones that shape the networks by value)."""
    obj = dict(check_object(data, where, {f.name: False for f in fields(TrainConfig)}))
    for f in fields(TrainConfig):
        if f.name not in obj:
            continue
        w, v = f"{where}.{f.name}", obj[f.name]
        if f.name == "maps":
            obj[f.name] = _check_maps(v, w)
        elif f.name in ("preset", "variant"):
            check_string(v, w, tuple(PRESETS) if f.name == "preset" else VARIANTS)
        elif f.name == "library":
            if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) for x in v):
                raise MatscanError(f"{w}: expected a list of map set folders, got {short_repr(v)}")
        elif f.name == "rig":  # the networks' input width is its light count
            try:
                resolve_rig(check_string(v, w))
            except MatscanError as exc:
                raise MatscanError(f"{w}: {exc}") from None
        else:  # other fields: the JSON type of their default
            _check_like(f.default, v, w)
    return TrainConfig.from_dict(obj, where)


#: Settings every run's config.json has held since the first: a file without them is not a run's.
RUN_KEYS = ("preset", "variant", "maps", "rig", "crop", "batch", "lr", "steps")


def read_run_config(run: str | Path) -> TrainConfig | None:
    """The config of the training run in folder ``run`` (its ``config.json``, checked),
    or None where there is none. A ``config.json`` that is not a run's (another tool's,
    another kind of run's, a damaged one) is a one-line error naming it."""
    path = Path(run) / "config.json"
    if not path.is_file():
        return None
    data = read_json(path)
    try:
        if not isinstance(data, dict) or not set(RUN_KEYS) <= set(data):
            raise MatscanError("lacks a run's settings")
        cfg = check_train_config(data, str(path))
        check_values(cfg)
    except MatscanError as exc:
        why = str(exc).removeprefix(f"{path}: ")
        raise input_error(path, f"is not a matscan train run's config ({why}); choose another --out") from None
    return cfg


#: The least value of each counted or sized training setting (the command line's bounds).
LEAST = {"crop": 16, "batch": 1, "steps": 1, "render_lights": 0, "val_every": 0, "val_count": 1, "log_every": 1}


def check_values(cfg: TrainConfig) -> None:
    """Settings within their ranges (the types are :func:`check_train_config`'s)."""
    for name, least in LEAST.items():
        if getattr(cfg, name) < least:
            raise MatscanError(f"{name}: {getattr(cfg, name)!r} must be at least {least}")
    if not 0 <= cfg.ema < 1:
        raise MatscanError(f"ema: {cfg.ema!r} must be a decay per step in [0, 1) (0: no moving average)")
    if not 0 <= cfg.seed < 2**31:
        raise MatscanError(f"seed: {cfg.seed!r} must be in [0, 2^31)")
    for name in ("lr", "checkpoint_minutes", "grad_clip"):
        if not 0 < getattr(cfg, name) < math.inf:
            raise MatscanError(f"{name}: {getattr(cfg, name)!r} must be a positive number")
    for name in ("lambda_map", "lambda_render"):
        if not 0 <= getattr(cfg, name) < math.inf:
            raise MatscanError(f"{name}: {getattr(cfg, name)!r} must be a number at least 0")


def _check_like(default: Any, value: Any, where: str) -> None:
    """``value`` has the JSON type of ``default`` (bool, int, float, str; others unchecked)."""
    if isinstance(default, bool):
        check_bool(value, where)
    elif isinstance(default, int):
        check_int(value, where)
    elif isinstance(default, float):
        check_number(value, where)
    elif isinstance(default, str) and not isinstance(value, str):
        raise MatscanError(f"{where}: expected a string, got {short_repr(value)}")


def sample_lights(indices: Tensor, cfg: TrainConfig, rig) -> LightSet:
    """Novel lights for the rendering loss, drawn per sample index (so a sample gets
    the same lights in any process layout)."""
    sets = [
        novel_lights(
            1,
            cfg.render_lights,
            rig.reference_distance_mm,
            rig.camera_point,
            torch.Generator().manual_seed((cfg.seed * 1_000_003 + int(i)) * 7 + 3),
        )
        for i in indices
    ]
    return LightSet.cat(sets)


def _groups(nets: MapNets) -> dict[str, list[Tensor]]:
    """Parameters per map network (for per-network gradient clipping)."""
    if nets.variant == "one_encoder":
        return {"all": list(nets.parameters())}
    return {name: list(net.parameters()) for name, net in nets.nets.items()}


# --- checkpoints ---------------------------------------------------------------------


def save_checkpoint(
    path: Path,
    nets: MapNets,
    opt: torch.optim.Optimizer,
    step: int,
    cfg: TrainConfig,
    elapsed: float,
    extra: dict[str, str] | None = None,
    ema: dict[str, Tensor] | None = None,
) -> None:
    """Weights, Adam state, step and network config in one safetensors file, written
    atomically; ``extra``: more metadata (the run's ``init`` record); ``ema``: the
    weights' moving average (``TrainConfig.ema``). Tensors are stored from CPU copies,
    so the file loads on any device."""
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in nets.state_dict().items()}
    tensors.update({f"{EMA}{k}": v.detach().cpu().contiguous() for k, v in (ema or {}).items()})
    state = opt.state_dict()
    adam_steps = {}
    for pid, st in state["state"].items():
        tensors[f"opt.{pid}.exp_avg"] = st["exp_avg"].cpu().contiguous()
        tensors[f"opt.{pid}.exp_avg_sq"] = st["exp_avg_sq"].cpu().contiguous()
        adam_steps[str(pid)] = float(st["step"])
    meta = {
        "step": str(step),
        "config": json.dumps(asdict(cfg)),
        "adam_steps": json.dumps(adam_steps),
        "elapsed_seconds": f"{elapsed:.1f}",
        "net_config": json.dumps(asdict(nets.cfg)),
        "format": "matscan-checkpoint/1",
        **(extra or {}),
    }
    with atomic_file(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def load_checkpoint(
    path: Path, nets: MapNets, opt: torch.optim.Optimizer | None, subset: bool = False, averaged: bool = False
) -> tuple[int, float, dict]:
    """Restore weights (and Adam state); returns (step, elapsed seconds, metadata).
    Without ``opt`` the file may also be an exported weights file. ``subset``: the
    file may hold more networks than ``nets`` (a run that trains some of them
    starting from all four); only ``nets``' own are taken. ``averaged``: a checkpoint's
    moving average of the weights where it keeps one, in place of the weights."""
    meta = _metadata(path)
    tensors = load_file(str(path))
    model = {name: tensors[k] for name, k in network_names(tensors, averaged).items()}
    if subset:
        own = nets.state_dict()
        model = {k: v for k, v in model.items() if k in own}
    try:
        nets.load_state_dict(model)
    except RuntimeError as exc:
        raise input_error(path, f"weights do not fit this network ({str(exc).splitlines()[0]})") from None
    if opt is not None:
        if "adam_steps" not in meta:
            raise input_error(path, "holds weights but no optimiser state, so no run resumes from it (use it as init)")
        adam_steps = loads_text(meta["adam_steps"], f"{path}: adam_steps")
        state = opt.state_dict()
        try:
            for pid_str, st in adam_steps.items():
                pid = int(pid_str)
                state["state"][pid] = {
                    "step": torch.tensor(st),
                    "exp_avg": tensors[f"opt.{pid}.exp_avg"],
                    "exp_avg_sq": tensors[f"opt.{pid}.exp_avg_sq"],
                }
            opt.load_state_dict(state)
        except (KeyError, ValueError, TypeError, AttributeError) as exc:
            raise input_error(path, f"its optimiser state is damaged ({short_repr(str(exc))})") from None
    return int(meta.get("step", 0)), float(meta.get("elapsed_seconds", 0)), meta


def export_weights(
    checkpoint: Path,
    out: Path,
    extra: dict[str, str] | None = None,
    dtype: torch.dtype = torch.float32,
    fill_from: Path | None = None,
    take: Sequence[str] | None = None,
) -> Path:
    """Weights only (no optimizer state) with what is needed to rebuild the networks,
    stored as ``dtype`` (float16 halves the file; they load into float32 networks).

    ``fill_from``: a checkpoint or weights file whose networks complete a run that
    trained only some of them (the four networks are independent, so a run may
    retrain one, e.g. G_d after a change of ``photo_statistic``). The file then holds
    every network of both; its ``maps`` metadata names them and ``networks`` says, per
    network, how many steps and seconds of training are behind it and where it came from.

    ``take``: the run's networks to export (default: all it trained); with ``fill_from``
    the others come from there, e.g. a run that improved G_d and G_n but not G_s and G_g.

    ``checkpoint`` may also be a run's exported weights (a float16 copy kept in git where
    the checkpoint, with Adam's state, is too large to commit).
    """
    meta = _metadata(checkpoint)
    cfg = _config_of(meta, checkpoint)
    net = net_config_of(meta, cfg)
    own = tuple(cfg.maps) if take is None else tuple(take)
    if not own or not set(own) <= set(cfg.maps):
        asked, trained = ", ".join(own) or "nothing", ", ".join(cfg.maps)
        raise input_error(checkpoint, f"take: {asked} is not among the networks it trained ({trained})")
    if cfg.variant != "four" and set(own) != set(cfg.maps):
        raise input_error(checkpoint, "only the four independent networks (variant four) can be taken apart")
    stored = load_file(str(checkpoint))  # the networks (a checkpoint's moving average where it keeps one)
    stored = {name: stored[k] for name, k in network_names(stored).items()}
    tensors = {k: v for k, v in stored.items() if not k.startswith("nets.") or k.split(".")[1] in own}
    networks = {m: {**r, "from": str(checkpoint)} for m, r in training_record(meta).items() if m in own}
    if fill_from is not None and set(own) == set(MAPS):
        fill_from = None  # nothing to fill: a run of another variant that trained all four networks may snapshot
    if fill_from is not None:
        fill_meta = _metadata(fill_from)
        fill_cfg = _config_of(fill_meta, fill_from)
        fill_net = net_config_of(fill_meta, fill_cfg)
        fill_maps = [m for m in fill_meta.get("maps", ",".join(fill_cfg.maps)).split(",") if m not in own]
        if cfg.variant != "four" or fill_cfg.variant != "four":
            raise input_error(fill_from, "only the four independent networks (variant four) can be combined")
        # photo_statistic shapes G_d's input only: other networks may come from a run with another
        if {**asdict(fill_net), "photo_statistic": ""} != {**asdict(net), "photo_statistic": ""} or (
            "diffuse" in fill_maps and fill_net.photo_statistic != net.photo_statistic
        ):
            raise input_error(fill_from, f"its networks ({fill_net}) do not fit those of {checkpoint} ({net})")
        fill = load_file(str(fill_from))
        for k, stored_name in network_names(fill).items():
            if k.startswith("nets.") and k.split(".")[1] in fill_maps:
                tensors[k] = fill[stored_name]
        # an assembled file keeps its networks' own records, except where a network's
        # record names its run's checkpoint and the fill is that run's own copy beside it
        # (the float16 weights.safetensors kept in git instead of the checkpoint)
        records = {}
        for m, r in training_record(fill_meta).items():
            origin = r.get("from", str(fill_from))
            if Path(origin).parent == Path(fill_from).parent:
                origin = str(fill_from)
            records[m] = {**r, "from": origin}
        networks.update({m: records[m] for m in fill_maps})
    maps = [m for m in MAPS if m in networks]
    info = {
        "format": "matscan-weights/1",
        "train_config": json.dumps(asdict(cfg)),
        "net_config": json.dumps(asdict(net)),
        "maps": ",".join(maps),
        "networks": json.dumps({m: networks[m] for m in maps}),
        "step": meta["step"],
        "elapsed_seconds": meta.get("elapsed_seconds", "0"),
        **{k: meta[k] for k in INIT_KEYS if k in meta},
    }
    info.update(extra or {})
    tensors = {k: v.to(dtype) if v.is_floating_point() else v for k, v in tensors.items()}
    with atomic_file(out) as tmp:
        save_file(tensors, str(tmp), metadata=info)
    return out


# --- evaluation ----------------------------------------------------------------------


#: Batch entries read as numbers (crop places, sample indices): they stay on the CPU.
HOST_KEYS = ("offset", "full_size", "index")


def batch_to(samples: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    return {k: torch.stack([s[k] for s in samples]) for k in samples[0]}


def to_device(batch: dict[str, Tensor], device: torch.device) -> dict[str, Tensor]:
    """The batch's photos and maps on ``device`` (asynchronously from pinned memory);
    :data:`HOST_KEYS` stay where they are."""
    return {k: v if k in HOST_KEYS else v.to(device, non_blocking=True) for k, v in batch.items()}


@torch.no_grad()
def validate(nets: MapNets, samples: list[dict[str, Tensor]], rig: Rig, batch: int = 8) -> dict[str, float]:
    """RMSE per map (normals: RMSE of the vectors, and mean angular error in degrees),
    computed on the networks' device."""
    was = nets.training
    nets.eval()
    device = next(nets.parameters()).device
    sq = {m: 0.0 for m in nets.maps}
    count = {m: 0 for m in nets.maps}
    angle, pixels = 0.0, 0
    for i in range(0, len(samples), batch):
        b = to_device(batch_to(samples[i : i + batch]), device)
        out = nets(network_input(b["inputs"], b["present"], b["offset"], b["full_size"], rig))
        for m in nets.maps:
            sq[m] += float(((out[m] - b[m]) ** 2).sum())
            count[m] += b[m].numel()
        if "normal" in out:
            cos = (out["normal"] * b["normal"]).sum(1).clamp(-1, 1)
            angle += float(torch.rad2deg(torch.acos(cos)).sum())
            pixels += cos.numel()
    nets.train(was)
    res = {f"rmse_{m}": math.sqrt(sq[m] / count[m]) for m in nets.maps}
    if pixels:
        res["normal_degrees"] = angle / pixels
    return res


# --- the loop ------------------------------------------------------------------------


def loss_lights(
    b: dict[str, Tensor], cfg: TrainConfig, rig: Rig, device: torch.device
) -> tuple[LightSet, Tensor, Tensor] | None:
    """The novel lights, surface points and ground-truth rendering of a batch's rendering
    loss, on ``device`` (None where the config has no rendering term). They depend on the
    samples alone, so every network's term shares them, and so do networks trained side
    by side on one batch."""
    if not (cfg.lambda_render > 0 and cfg.render_lights > 0):
        return None
    lights = lights_to(sample_lights(b["index"], cfg, rig), device)
    points = torch.stack(
        [
            surface_points(rig.field_mm, (cfg.crop, cfg.crop), tuple(o.tolist()), tuple(f.tolist()))
            for o, f in zip(b["offset"], b["full_size"], strict=True)
        ]
    ).to(device)
    return lights, points, truth_rendering({m: b[m] for m in MAPS}, lights, points)


def step_loss(
    out: dict[str, Tensor],
    b: dict[str, Tensor],
    cfg: TrainConfig,
    rig: Rig,
    render: tuple[LightSet, Tensor, Tensor] | None,
) -> tuple[Tensor, dict[str, float]]:
    """One step's loss for the networks' outputs ``out`` on batch ``b``: each trained map's
    own loss, with its own rendering term or one joint term for all (``cfg.render_with``),
    under ``render`` (:func:`loss_lights`). Returns the total and its terms, for the log."""
    truth = {m: b[m] for m in MAPS}
    lights, points, target = render if render is not None else (None, None, None)
    total: Tensor | float = 0.0
    terms: dict[str, float] = {}
    joint = cfg.render_with == "joint"
    for m in cfg.maps:
        own = None if joint else lights  # joint: no per-network rendering term
        loss, parts = map_loss(m, out, truth, own, points, cfg.lambda_map, cfg.lambda_render, target)
        total = total + loss
        terms[f"{m}"] = float(loss.detach())
        terms.update({f"{m}_{k}": v for k, v in parts.items()})
    if joint and lights is not None:
        r = rendering_loss(out, truth, tuple(cfg.maps), lights, points, target)
        total = total + cfg.lambda_render * r
        terms["joint_render"] = float(r.detach())
    return total, terms  # type: ignore[return-value]


def _dist_info() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    return rank, world


def train(
    cfg: TrainConfig,
    run: str | Path,
    max_steps: int | None = None,
    max_minutes: float | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Train (or resume) the run in folder ``run`` until ``cfg.steps``, ``max_steps``
    more steps, or ``max_minutes`` of wall time, whichever comes first.

    Returns a summary: steps done, seconds, last losses, last validation.
    """
    from tqdm import tqdm

    from matscan.outputs import check_run_folder

    run = Path(run)
    check_values(cfg)
    check_run_folder(run, cfg.library, (CHECKPOINT, "log.csv", "val.csv", SNAPSHOTS))
    saved = read_run_config(run)
    rank, world = _dist_info()
    device = resolve_device(cfg.device, int(os.environ.get("LOCAL_RANK", "0")))
    if device.type == "cuda":
        torch.cuda.set_device(device)
        torch.backends.cudnn.benchmark = True  # one input shape for the whole run: pick the fastest convs
    if cfg.workers < 0 or (cfg.workers > 0 and cfg.prefetch < 1):
        raise MatscanError(f"workers {cfg.workers}, prefetch {cfg.prefetch}: need workers ≥ 0 and prefetch ≥ 1")
    data_cfg = data_config(cfg)
    if cfg.snapshot_every < 0:
        raise MatscanError(f"snapshot_every: {cfg.snapshot_every} must be 0 (none) or a number of steps")
    if not 0 <= cfg.ema < 1:
        raise MatscanError(f"ema: {cfg.ema!r} must be a decay per step in [0, 1) (0: no moving average)")
    if cfg.render_with not in RENDER_WITH:
        raise MatscanError(f"render_with: {cfg.render_with!r} is not one of {', '.join(RENDER_WITH)}")
    if world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    torch.manual_seed(cfg.seed)
    config_path = run / "config.json"
    ckpt = run / CHECKPOINT
    init = Path(cfg.init) if cfg.init else None
    if init is not None and not ckpt.is_file():
        if not init.is_file():
            raise input_error(init, "no such weights file to start the run from (init)")
        _config_of(_metadata(init), init)  # a damaged or foreign file: refused before the run folder is made
    # a resumed run keeps the network config it started with
    start_meta = _metadata(ckpt) if ckpt.is_file() else {}
    nets = build_nets(cfg, net_config_of(start_meta, cfg) if start_meta else None).to(device)  # init on the CPU
    opt = torch.optim.Adam(nets.parameters(), lr=cfg.lr)
    step, elapsed = 0, 0.0
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
        if saved is not None:
            diff = [
                f.name
                for f in fields(cfg)
                if f.name not in RUNTIME_FIELDS and getattr(saved, f.name) != getattr(cfg, f.name)
            ]
            if diff:
                raise input_error(
                    run,
                    f"holds a run with another config (differs in {', '.join(diff)}); "
                    "use another folder, or the same settings to resume",
                )
    if world > 1:
        torch.distributed.barrier()
    init_record: dict[str, str] = {}
    if ckpt.is_file():
        step, elapsed, meta = load_checkpoint(ckpt, nets, opt)
        init_record = {k: meta[k] for k in INIT_KEYS if k in meta}
    elif init is not None:
        init_meta = _metadata(init)
        init_cfg = _config_of(init_meta, init)
        load_checkpoint(init, nets, None, subset=True, averaged=True)  # weights only: Adam starts afresh
        before, seconds = _trained(init_meta)  # the training behind the init weights, their own init included
        init_record = {
            "init": str(cfg.init),
            "init_step": str(before),
            "init_elapsed_seconds": f"{seconds:.1f}",
            "init_photo_statistic": net_config_of(init_meta, init_cfg).photo_statistic,
            "init_networks": json.dumps({m: r for m, r in training_record(init_meta).items() if m in cfg.maps}),
        }
    if rank == 0 and not config_path.is_file():  # written once the weights it names have loaded
        write_text(config_path, json.dumps(asdict(cfg), indent=2) + "\n")
    sample_offset = int(init_record.get("init_step", 0))  # the samples the init weights saw are skipped
    ema = None
    if cfg.ema and rank == 0:  # from the checkpoint's own average, else from the weights now
        kept = (
            {k.removeprefix(EMA): v for k, v in load_file(str(ckpt)).items() if k.startswith(EMA)}
            if ckpt.is_file()
            else {}
        )
        ema = {k: kept.get(k, v).detach().to(v.device, copy=True) for k, v in nets.state_dict().items()}

    model: torch.nn.Module = nets
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            nets, device_ids=[device.index] if device.type == "cuda" else None
        )

    rig = resolve_rig(cfg.rig)
    data = SvbrdfDataset(data_cfg)
    # spawned (not forked) workers: a fork after this process has run OpenMP or compiled
    # kernels can deadlock; each worker builds its own kernels
    loader = DataLoader(
        data,
        batch_sampler=StepSampler(sample_offset + step, cfg.batch, rank, world),
        num_workers=cfg.workers,
        persistent_workers=cfg.workers > 0,
        prefetch_factor=cfg.prefetch if cfg.workers > 0 else None,
        multiprocessing_context="spawn" if cfg.workers > 0 else None,
        pin_memory=device.type == "cuda",
    )
    val_samples = fixed_validation_set(cfg.val_count, cfg.crop, cfg.rig) if rank == 0 and cfg.val_every else []

    end = cfg.steps if max_steps is None else min(cfg.steps, step + max_steps)
    deadline = time.monotonic() + max_minutes * 60 if max_minutes is not None else math.inf
    stop = {"now": False}

    def on_signal(signum, frame):  # finish the step, write the checkpoint, leave
        stop["now"] = True

    old_handlers = {}
    if rank == 0:
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                old_handlers[sig] = signal.signal(sig, on_signal)
            except ValueError:  # not the main thread
                pass
    log_path, val_path = run / "log.csv", run / "val.csv"
    last_ckpt = time.monotonic()
    t_start = time.monotonic()
    last_terms: dict[str, float] = {}
    last_val: dict[str, float] = {}
    bar = tqdm(total=end - step, desc="train", unit="step", disable=not progress or rank != 0)
    batches = iter(loader)

    def keep_going() -> bool:
        go = step < end and not stop["now"] and time.monotonic() < deadline
        if world > 1:  # every process stops at the same step, or DDP would wait forever
            flag = torch.tensor([0 if go else 1], device=device)
            torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
            go = int(flag) == 0
        return go

    try:
        while keep_going():
            b = to_device(next(batches), device)
            x = network_input(b["inputs"], b["present"], b["offset"], b["full_size"], rig)
            total, terms = step_loss(model(x), b, cfg, rig, loss_lights(b, cfg, rig, device))
            opt.zero_grad(set_to_none=True)
            total.backward()
            for params in _groups(nets).values():
                torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
            opt.step()
            if ema is not None:
                with torch.no_grad():
                    for k, v in nets.state_dict().items():
                        ema[k].lerp_(v, 1 - cfg.ema)
            step += 1
            bar.update(1)
            last_terms = terms
            if rank == 0:
                if step % cfg.log_every == 0 or step == end:
                    _append_csv(
                        log_path,
                        {
                            "step": step,
                            "seconds": round(elapsed + time.monotonic() - t_start, 1),
                            **{k: round(v, 6) for k, v in terms.items()},
                        },
                    )
                    bar.set_postfix({m: f"{terms[m]:.3f}" for m in cfg.maps})
                if cfg.val_every and step % cfg.val_every == 0:
                    last_val = validate(nets, val_samples, rig)
                    _append_csv(val_path, {"step": step, **{k: round(v, 6) for k, v in last_val.items()}})
                snap = cfg.snapshot_every and step % cfg.snapshot_every == 0
                if snap or time.monotonic() - last_ckpt > cfg.checkpoint_minutes * 60:
                    save_checkpoint(ckpt, nets, opt, step, cfg, elapsed + time.monotonic() - t_start, init_record, ema)
                    last_ckpt = time.monotonic()
                if snap:
                    snapshot(run, step, cfg)
    finally:
        bar.close()
        if rank == 0:
            save_checkpoint(ckpt, nets, opt, step, cfg, elapsed + time.monotonic() - t_start, init_record, ema)
            for sig, handler in old_handlers.items():
                signal.signal(sig, handler)
        if world > 1:
            torch.distributed.barrier()
    return {"step": step, "seconds": elapsed + time.monotonic() - t_start, "losses": last_terms, "validation": last_val}


SNAPSHOTS = "snapshots"


def snapshot(run: Path, step: int, cfg: TrainConfig) -> Path:
    """The run's weights now (its checkpoint, just written) as a float16 weights file
    ``RUN/snapshots/step-NNNNNN.safetensors``, the networks it does not train filled from
    ``init``: a complete set that ``matscan evaluate --methods nets:FILE`` and
    ``tools/nets_unlike.py`` take as it is, so a run can be scored at every snapshot,
    not only where it stopped."""
    fill = Path(cfg.init) if cfg.init else None
    out = run / SNAPSHOTS / f"step-{step:06d}.safetensors"
    out.parent.mkdir(exist_ok=True)
    return export_weights(run / CHECKPOINT, out, dtype=torch.float16, fill_from=fill)


def snapshots(run: Path) -> list[Path]:
    """A run's snapshots in step order."""
    return sorted((Path(run) / SNAPSHOTS).glob("step-*.safetensors"))


def _append_csv(path: Path, row: dict[str, Any]) -> None:
    new = not path.is_file()
    with path.open("a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        if new:
            w.writeheader()
        w.writerow(row)
