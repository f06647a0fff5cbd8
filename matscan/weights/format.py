"""The weights file format: networks rebuilt from what a file stores, with no training code.

A weights file (``matscan-weights/1``) or a checkpoint (``matscan-checkpoint/1``) is a
safetensors file whose tensors are the networks' (``model.…``; a checkpoint also has
Adam's, ``opt.…``) and whose string metadata says what they are: the training config
(``train_config`` or ``config``, JSON; loading reads only the rig, preset, variant and
maps from it: :class:`NetSpec`), the network shape (``net_config``), the maps present,
and per network the training behind it (``networks``). Like nanoGPT's ``sample.py``,
loading imports only the networks' module: every field is checked, and a damaged or
foreign file is a one-line error naming it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import torch

from matscan.errors import MatscanError, input_error
from matscan.jsonfile import (
    check_bool,
    check_int,
    check_list,
    check_number,
    check_object,
    check_string,
    loads_text,
    short_repr,
)
from matscan.nets import MAPS, PHOTO_STATISTICS, PRESETS, VARIANTS, MapNets, NetConfig, preset
from matscan.rig import resolve_rig


@dataclass(frozen=True)
class NetSpec:
    """What rebuilding the networks needs from a file's training config."""

    rig: str = "dome24"
    preset: str = "cpu"
    variant: str = "four"
    maps: tuple[str, ...] = MAPS


def net_spec(meta: dict[str, str], path: Path) -> NetSpec:
    """The :class:`NetSpec` in a file's stored training config, its four fields checked
    (the others are training's own, and read by :mod:`matscan.train` when a run resumes)."""
    key = "train_config" if meta.get("train_config") else "config"
    if not meta.get(key):
        raise input_error(path, "not a matscan weights file (no training config in its metadata)")
    where = f"{path}: {key}"
    obj = check_object(loads_text(meta[key], where), where, None)
    values: dict[str, Any] = {}
    if "maps" in obj:
        values["maps"] = check_maps(obj["maps"], f"{where}.maps")
    for name, choices in (("preset", tuple(PRESETS)), ("variant", VARIANTS)):
        if name in obj:
            values[name] = check_string(obj[name], f"{where}.{name}", choices)
    if "rig" in obj:  # the networks' input width is its light count
        rig = check_string(obj["rig"], f"{where}.rig")
        try:
            resolve_rig(rig)
        except MatscanError as exc:
            raise MatscanError(f"{where}.rig: {exc}") from None
        values["rig"] = rig
    return NetSpec(**values)


def build(spec: NetSpec, net: NetConfig) -> MapNets:
    """The networks a :class:`NetSpec` and a network shape describe (untrained)."""
    return MapNets(len(resolve_rig(spec.rig).lights), net, spec.variant, spec.maps)


def net_config_of(meta: dict[str, str], preset_name: str = "cpu", where: str = "weights") -> NetConfig:
    """The network config a checkpoint or weights file was trained with: its stored
    ``net_config``, or, for files written before that was stored, the preset's with
    the median ``photo_statistic`` (the only statistic there was then).

    A stored config is checked field by field (``where`` names the file in errors).
    """
    if "net_config" in meta:
        return check_net_config(loads_text(meta["net_config"], f"{where}: net_config"), f"{where}: net_config")
    return NetConfig(**{**asdict(preset(preset_name)), "photo_statistic": "median"})


def metadata(path: Path) -> dict[str, str]:
    """The string metadata of a safetensors file; a damaged header is a one-line error."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return f.metadata() or {}
    except Exception as exc:  # safetensors raises its own error types for a damaged header
        detail = " ".join(str(exc).split())[:200]
        raise input_error(path, f"not a readable safetensors file ({detail})") from None


#: Bounds on a stored network shape: beyond every preset, small enough to build.
_NET_BOUNDS = {"base": (1, 1024), "growth": (0, 1024), "depth": (1, 12), "global_dim": (0, 65536)}
_WEIGHTS_FORMATS = ("matscan-weights/1", "matscan-checkpoint/1")
_RECORD_KEYS = {"steps": True, "elapsed_seconds": True, "from": False}


def check_net_config(data: Any, where: str) -> NetConfig:
    """A :class:`NetConfig` from its stored JSON object, every field checked."""
    obj = check_object(data, where, {f.name: False for f in fields(NetConfig)})
    values: dict[str, Any] = {}
    for f in fields(NetConfig):
        if f.name not in obj:
            continue
        w = f"{where}.{f.name}"
        if f.name in _NET_BOUNDS:
            values[f.name] = check_int(obj[f.name], w, *_NET_BOUNDS[f.name])
        elif isinstance(f.default, bool):
            values[f.name] = check_bool(obj[f.name], w)
        else:
            values[f.name] = check_string(obj[f.name], w, tuple(PHOTO_STATISTICS))
    net = NetConfig(**values)
    if max(net.channels()) > 1024:
        raise MatscanError(f"{where}: base + growth × depth = {max(net.channels())} channels; at most 1024")
    return net


def check_maps(value: Any, where: str) -> tuple[str, ...]:
    """A non-empty list of distinct map names."""
    maps = tuple(check_string(m, f"{where}[{i}]", MAPS) for i, m in enumerate(check_list(value, where, "map names")))
    if len(set(maps)) != len(maps):
        raise MatscanError(f"{where}: names a map twice")
    return maps


def check_records(value: Any, where: str, maps: tuple[str, ...]) -> None:
    """Per-network training records (``networks``, ``init_networks``): one for each of ``maps``."""
    records = check_object(value, where, dict.fromkeys(MAPS, False))
    for m in maps:
        if m not in records:
            raise MatscanError(f"{where}: no record of the {m} network")
    for m, record in records.items():
        rec = check_object(record, f"{where}.{m}", _RECORD_KEYS)
        check_int(rec["steps"], f"{where}.{m}.steps", 0)
        check_number(rec["elapsed_seconds"], f"{where}.{m}.elapsed_seconds", 0)
        if "from" in rec:
            check_string(rec["from"], f"{where}.{m}.from")


def check_metadata(meta: dict[str, str], path: Path, maps: tuple[str, ...]) -> tuple[str, ...]:
    """Check the metadata fields that loading and :func:`training_record` read; return the
    file's maps (its ``maps`` field, or the training config's)."""
    if "format" in meta and meta["format"] not in _WEIGHTS_FORMATS:
        raise input_error(path, f"format: {short_repr(meta['format'])} is not one of {', '.join(_WEIGHTS_FORMATS)}")
    own = maps
    if "maps" in meta:
        maps = check_maps(meta["maps"].split(","), f"{path}: maps")
    for key in ("step", "init_step", "elapsed_seconds", "init_elapsed_seconds"):
        if key in meta:
            value = loads_text(meta[key], f"{path}: {key}")
            (check_int if key.endswith("step") else check_number)(value, f"{path}: {key}", 0)
    if "networks" in meta:
        check_records(loads_text(meta["networks"], f"{path}: networks"), f"{path}: networks", maps)
        return maps
    key = "train_config" if meta.get("train_config") else "config"
    if "maps" not in loads_text(meta[key], f"{path}: {key}"):  # training_record reads them from there
        raise input_error(path, f"{key}: missing field 'maps'")
    if "init_networks" in meta:
        if "step" not in meta:
            raise input_error(path, "init_networks without step: the metadata is incomplete")
        where = f"{path}: init_networks"
        check_records(loads_text(meta["init_networks"], where), where, own)
    return maps


EMA = "ema."  # a checkpoint's moving average of the weights (TrainConfig.ema): ema. + the weights' name


def network_names(keys: Iterable[str], averaged: bool = True) -> dict[str, str]:
    """The networks' tensors among a weights file's or checkpoint's tensor names, as
    {network name: stored name}: ``model.…`` in a checkpoint (bare in an export), or
    with ``averaged`` the checkpoint's moving average ``ema.…`` where it keeps one; never
    Adam's state ``opt.…``."""
    keys = list(keys)
    if averaged and any(k.startswith(EMA) for k in keys):
        return {k.removeprefix(EMA): k for k in keys if k.startswith(EMA)}
    return {k.removeprefix("model."): k for k in keys if not k.startswith(("opt.", EMA))}


def check_fits(path: Path, nets: MapNets) -> None:
    """Refuse a file whose tensors are not exactly those of ``nets`` (names and shapes)."""
    from safetensors import safe_open

    want = {k: tuple(v.shape) for k, v in nets.state_dict().items()}
    with safe_open(str(path), framework="pt") as f:
        have = {name: tuple(f.get_slice(k).get_shape()) for name, k in network_names(f.keys()).items()}
    for k in sorted(set(want) | set(have)):
        if want.get(k) != have.get(k):
            shapes = f"{k}: file {have.get(k)}, network {want.get(k)}"
            raise input_error(path, f"weights do not fit the networks its metadata describes ({shapes})")


def training_record(meta: dict[str, str]) -> dict[str, dict[str, Any]]:
    """Per network of a weights file or checkpoint: the steps and seconds of training
    behind it and where it came from (an assembled file's ``networks``; otherwise the
    file's own run, with the training each network had in the weights it started from)."""
    if "networks" in meta:
        return json.loads(meta["networks"])
    cfg = json.loads(meta.get("train_config") or meta["config"])
    if "init_networks" not in meta:  # no init, or one written before per-network records
        steps, seconds = _trained(meta)
        return {m: {"steps": steps, "elapsed_seconds": round(seconds, 1)} for m in cfg["maps"]}
    before = json.loads(meta["init_networks"])
    step, seconds = int(meta["step"]), float(meta.get("elapsed_seconds", 0))
    return {
        m: {"steps": step + before[m]["steps"], "elapsed_seconds": round(seconds + before[m]["elapsed_seconds"], 1)}
        for m in cfg["maps"]
    }


def _trained(meta: dict[str, str]) -> tuple[int, float]:
    """Steps and seconds of a file's run, with those of the weights it started from."""
    steps = int(meta.get("step", 0)) + int(meta.get("init_step", 0))
    return steps, float(meta.get("elapsed_seconds", 0)) + float(meta.get("init_elapsed_seconds", 0))


def load_weights(path: str | Path) -> tuple[MapNets, dict[str, str]]:
    """Networks from an exported weights file (or a checkpoint), in eval mode, and the
    file's metadata."""
    path = Path(path)
    if not path.is_file():
        raise input_error(path, "no such weights file")
    meta = metadata(path)
    spec = net_spec(meta, path)
    # an export may hold networks of several runs (export_weights fill_from): its maps name them
    spec = NetSpec(spec.rig, spec.preset, spec.variant, check_metadata(meta, path, spec.maps))
    net = net_config_of(meta, spec.preset, str(path))
    with torch.device("meta"):  # shapes only: a file that does not fit allocates nothing
        check_fits(path, build(spec, net))
    nets = build(spec, net)
    load_state(path, nets)
    return nets.eval(), meta


def load_state(path: Path, nets: MapNets, subset: bool = False) -> None:
    """Load the networks' tensors of a weights file or checkpoint into ``nets`` (a
    checkpoint's moving average where it keeps one: :func:`network_names`); ``subset``:
    the file may hold more networks than ``nets``."""
    from safetensors.torch import load_file

    tensors = load_file(str(path))
    model = {name: tensors[k] for name, k in network_names(tensors).items()}
    if subset:
        own = nets.state_dict()
        model = {k: v for k, v in model.items() if k in own}
    try:
        nets.load_state_dict(model)
    except RuntimeError as exc:
        raise input_error(path, f"weights do not fit this network ({str(exc).splitlines()[0]})") from None
