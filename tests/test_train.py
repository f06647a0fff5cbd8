"""Training: a resumed run equals an uninterrupted one; two DDP processes equal one process."""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
import shutil
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from matscan.errors import MatscanError
from matscan.nets import MAPS, PRESETS, NetConfig, preset
from matscan.train import (
    CHECKPOINT,
    TrainConfig,
    _metadata,
    build_nets,
    export_weights,
    load_weights,
    resolve_device,
    save_checkpoint,
    snapshots,
    train,
    training_record,
)

ROOT = Path(__file__).resolve().parent.parent

CFG = TrainConfig(
    preset="tiny",
    crop=32,
    batch=2,
    val_every=4,
    val_count=2,
    workers=0,
    render_lights=2,
    steps=6,
    log_every=1,
    device="cpu",  # exact comparisons: a CUDA machine would run "auto" there, where resumes differ in the last bits
)


def _params(path: Path) -> list[torch.Tensor]:
    nets, _ = load_weights(path)
    return [p.detach().clone() for p in nets.parameters()]


def test_resume_continues_the_same_run(tmp_path):
    train(CFG, tmp_path / "a", progress=False)
    train(CFG, tmp_path / "b", max_steps=2, progress=False)  # interrupted after 2 steps
    res = train(CFG, tmp_path / "b", progress=False)  # resumed from the checkpoint
    assert res["step"] == 6
    for pa, pb in zip(
        _params(tmp_path / "a" / "checkpoint.safetensors"),
        _params(tmp_path / "b" / "checkpoint.safetensors"),
        strict=True,
    ):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)
    assert (tmp_path / "a" / "val.csv").read_text().count("\n") == 2  # header + step 4
    rows = (tmp_path / "b" / "log.csv").read_text().strip().splitlines()
    assert rows[0].startswith("step,seconds,diffuse") and len(rows) == 7


def test_a_resume_with_another_config_is_refused(tmp_path):
    train(CFG, tmp_path / "a", max_steps=1, progress=False)
    other = TrainConfig(**{**CFG.__dict__, "lr": 1e-3})
    with pytest.raises(MatscanError, match="differs in lr"):
        train(other, tmp_path / "a", progress=False)


def test_a_joint_rendering_loss_of_one_network_is_its_own(tmp_path):
    # with one network trained, the joint rendering term is that network's own: same weights
    one = {**CFG.__dict__, "maps": ("roughness",), "val_every": 0, "steps": 3}
    train(TrainConfig(**one), tmp_path / "own", progress=False)
    train(TrainConfig(**{**one, "render_with": "joint"}), tmp_path / "joint", progress=False)
    for pa, pb in zip(_params(tmp_path / "own" / CHECKPOINT), _params(tmp_path / "joint" / CHECKPOINT), strict=True):
        torch.testing.assert_close(pa, pb, rtol=1e-5, atol=1e-7)
    own = next(csv.DictReader((tmp_path / "own" / "log.csv").open()))
    joint = next(csv.DictReader((tmp_path / "joint" / "log.csv").open()))
    assert float(joint["joint_render"]) == pytest.approx(float(own["roughness_render"]), rel=1e-5)
    assert "roughness_render" not in joint


def test_a_joint_rendering_loss_trains_the_networks_together(tmp_path):
    cfg = TrainConfig(**{**CFG.__dict__, "maps": ("specular", "normal"), "render_with": "joint", "val_every": 0})
    train(cfg, tmp_path / "a", max_steps=2, progress=False)
    rows = list(csv.DictReader((tmp_path / "a" / "log.csv").open()))
    assert len(rows) == 2 and float(rows[-1]["joint_render"]) > 0
    assert not any(k.endswith("_render") and k != "joint_render" for k in rows[0])
    with pytest.raises(MatscanError, match="render_with: 'both'"):
        train(TrainConfig(**{**cfg.__dict__, "render_with": "both"}), tmp_path / "b", progress=False)


def test_export_and_load_weights(tmp_path):
    train(CFG, tmp_path / "a", max_steps=1, progress=False)
    out = export_weights(tmp_path / "a" / "checkpoint.safetensors", tmp_path / "w.safetensors", {"note": "x"})
    nets, meta = load_weights(out)
    assert meta["step"] == "1" and meta["note"] == "x" and not nets.training
    assert out.stat().st_size < (tmp_path / "a" / "checkpoint.safetensors").stat().st_size
    # float16 storage: half the bytes, and the same parameters to float16 precision
    half = export_weights(tmp_path / "a" / "checkpoint.safetensors", tmp_path / "h.safetensors", dtype=torch.float16)
    nets16, _ = load_weights(half)
    assert half.stat().st_size < 0.55 * out.stat().st_size
    for (k, a), (_, b) in zip(nets.state_dict().items(), nets16.state_dict().items(), strict=True):
        assert b.dtype == a.dtype, k
        torch.testing.assert_close(b, a.half().float(), rtol=0, atol=0)


def test_two_ddp_processes_equal_one_process(tmp_path):
    # DDP averages gradients over ranks: 2 processes × batch 1 take the same steps as 1 process × batch 2
    one = TrainConfig(**{**CFG.__dict__, "batch": 2, "steps": 3, "val_every": 0})
    two = TrainConfig(**{**CFG.__dict__, "batch": 1, "steps": 3, "val_every": 0})
    train(one, tmp_path / "single", progress=False)
    script = tmp_path / "ddp.py"
    script.write_text(
        "import sys\nfrom matscan.train import TrainConfig, train\n"
        f"train(TrainConfig(**{two.__dict__!r}), sys.argv[1], progress=False)\n"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--nproc_per_node",
            "2",
            "--master_port",
            "29533",
            str(script),
            str(tmp_path / "ddp"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    for pa, pb in zip(
        _params(tmp_path / "single" / "checkpoint.safetensors"),
        _params(tmp_path / "ddp" / "checkpoint.safetensors"),
        strict=True,
    ):
        torch.testing.assert_close(pa, pb, rtol=1e-5, atol=1e-6)


def _log(run: Path) -> list[dict[str, str]]:
    rows = list(csv.DictReader((run / "log.csv").open()))
    for r in rows:
        r.pop("seconds")
    return rows


def test_init_starts_from_weights_with_the_samples_after_theirs(tmp_path):
    a = TrainConfig(**{**CFG.__dict__, "steps": 4, "val_every": 0})
    train(a, tmp_path / "a", progress=False)
    train(a, tmp_path / "b", max_steps=3, progress=False)
    init = tmp_path / "b" / CHECKPOINT
    # step 4 of A uses the weights after 3 steps and samples 6, 7: a run started from B's weights logs,
    # at its first step, exactly A's step-4 losses (Adam's state does not enter a forward pass)
    c = TrainConfig(**{**a.__dict__, "init": str(init)})
    train(c, tmp_path / "c", max_steps=1, progress=False)
    step4 = _log(tmp_path / "a")[3]
    assert _log(tmp_path / "c")[0] == {**step4, "step": "1"}
    meta = _metadata(tmp_path / "c" / CHECKPOINT)
    assert (meta["init"], meta["init_step"], meta["init_photo_statistic"]) == (str(init), "3", "median")
    # one network alone, started from all four: the same losses for it
    d = TrainConfig(**{**c.__dict__, "maps": ("diffuse",)})
    train(d, tmp_path / "d", max_steps=1, progress=False)
    assert _log(tmp_path / "d")[0] == {k: v for k, v in step4.items() if k.startswith("diffuse")} | {"step": "1"}


def test_a_missing_init_file_is_refused_naming_it(tmp_path):
    cfg = TrainConfig(**{**CFG.__dict__, "init": str(tmp_path / "nope.safetensors")})
    with pytest.raises(MatscanError, match="nope.safetensors: no such weights file"):
        train(cfg, tmp_path / "a", progress=False)


def test_export_fills_the_networks_a_run_did_not_train(tmp_path):
    full = TrainConfig(**{**CFG.__dict__, "val_every": 0})
    train(full, tmp_path / "b", max_steps=3, progress=False)
    init = tmp_path / "b" / CHECKPOINT
    d = TrainConfig(**{**full.__dict__, "maps": ("diffuse",), "init": str(init)})
    train(d, tmp_path / "d", max_steps=1, progress=False)
    alone, _ = load_weights(export_weights(tmp_path / "d" / CHECKPOINT, tmp_path / "g.safetensors"))
    assert alone.maps == ("diffuse",)  # without the fill the file has G_d only
    out = export_weights(tmp_path / "d" / CHECKPOINT, tmp_path / "w.safetensors", fill_from=init)
    nets, meta = load_weights(out)
    assert nets.maps == MAPS and meta["maps"] == ",".join(MAPS)
    b_nets, _ = load_weights(init)
    d_nets, _ = load_weights(tmp_path / "d" / CHECKPOINT)
    for name in MAPS:
        source = d_nets if name == "diffuse" else b_nets
        for pa, pb in zip(nets.nets[name].parameters(), source.nets[name].parameters(), strict=True):
            torch.testing.assert_close(pa, pb, rtol=0, atol=0)
    record = training_record(meta)
    assert record["diffuse"]["steps"] == 4 and record["normal"]["steps"] == 3
    assert record["normal"]["from"] == str(init)
    # a run's own checkpoint counts the steps of the weights it started from
    own = training_record(_metadata(tmp_path / "d" / CHECKPOINT))
    assert own == {"diffuse": {"steps": 4, "elapsed_seconds": record["diffuse"]["elapsed_seconds"]}}
    # filling from an assembled file keeps the records of the networks taken from it
    train(d, tmp_path / "d", max_steps=1, progress=False)
    again = export_weights(tmp_path / "d" / CHECKPOINT, tmp_path / "w2.safetensors", fill_from=out)
    record = json.loads(load_weights(again)[1]["networks"])
    assert record["diffuse"]["steps"] == 5 and record["normal"] == {**record["normal"], "steps": 3, "from": str(init)}
    # a run started from an assembled file adds its steps to each network's own (normal had 3, diffuse 5)
    e = TrainConfig(**{**full.__dict__, "maps": ("diffuse", "normal"), "init": str(again)})
    train(e, tmp_path / "e", max_steps=2, progress=False)
    own = training_record(_metadata(tmp_path / "e" / CHECKPOINT))
    assert (own["diffuse"]["steps"], own["normal"]["steps"]) == (7, 5)
    # and its seconds to each network's own (exact sums, whatever the machine's speed)
    run = float(_metadata(tmp_path / "e" / CHECKPOINT)["elapsed_seconds"])
    for name in ("diffuse", "normal"):
        assert own[name]["elapsed_seconds"] == round(run + record[name]["elapsed_seconds"], 1)


def test_snapshots_keep_the_weights_along_the_run_filled_from_init(tmp_path):
    full = TrainConfig(**{**CFG.__dict__, "val_every": 0})
    train(full, tmp_path / "b", max_steps=2, progress=False)
    init = tmp_path / "b" / CHECKPOINT
    cfg = TrainConfig(**{**full.__dict__, "maps": ("roughness",), "init": str(init), "snapshot_every": 2})
    train(cfg, tmp_path / "r", max_steps=3, progress=False)
    assert [p.name for p in snapshots(tmp_path / "r")] == ["step-000002.safetensors"]
    train(cfg, tmp_path / "r", max_steps=1, progress=False)  # resumed: step 4 is a snapshot too
    paths = snapshots(tmp_path / "r")
    assert [p.name for p in paths] == ["step-000002.safetensors", "step-000004.safetensors"]
    last, meta = load_weights(paths[-1])
    assert meta["step"] == "4" and last.maps == MAPS
    ckpt, _ = load_weights(tmp_path / "r" / CHECKPOINT)
    start, _ = load_weights(init)
    for name in MAPS:
        source = ckpt if name == "roughness" else start  # the trained network, the others from init
        for pa, pb in zip(last.nets[name].parameters(), source.nets[name].parameters(), strict=True):
            torch.testing.assert_close(pa, pb.half().float(), rtol=0, atol=0)
    first, _ = load_weights(paths[0])
    pairs = zip(first.nets["roughness"].parameters(), last.nets["roughness"].parameters(), strict=True)
    assert max(float((a - b).detach().abs().max()) for a, b in pairs) > 0  # the network trained between them
    with pytest.raises(MatscanError, match="snapshot_every: -1"):
        train(TrainConfig(**{**full.__dict__, "snapshot_every": -1}), tmp_path / "n", progress=False)


def test_a_variant_run_from_init_keeps_snapshots(tmp_path):
    # the ablation variants train all four networks; their snapshots need nothing filled from init
    # (an export that tried to combine them stopped such a run at its first snapshot)
    cfg = TrainConfig(**{**CFG.__dict__, "val_every": 0, "variant": "no_global_skip"})
    train(cfg, tmp_path / "a", max_steps=1, progress=False)
    init = tmp_path / "a" / CHECKPOINT
    cont = TrainConfig(**{**cfg.__dict__, "init": str(init), "snapshot_every": 1})
    train(cont, tmp_path / "b", max_steps=2, progress=False)
    paths = snapshots(tmp_path / "b")
    assert [p.name for p in paths] == ["step-000001.safetensors", "step-000002.safetensors"]
    last, meta = load_weights(paths[-1])
    assert json.loads(meta["train_config"])["variant"] == "no_global_skip"
    ckpt, _ = load_weights(tmp_path / "b" / CHECKPOINT)
    for pa, pb in zip(last.parameters(), ckpt.parameters(), strict=True):
        torch.testing.assert_close(pa, pb.half().float(), rtol=0, atol=0)


def test_export_takes_some_of_a_runs_networks_and_fills_the_others(tmp_path):
    full = TrainConfig(**{**CFG.__dict__, "val_every": 0})
    train(full, tmp_path / "b", max_steps=2, progress=False)
    init = tmp_path / "b" / CHECKPOINT
    train(TrainConfig(**{**full.__dict__, "init": str(init)}), tmp_path / "c", max_steps=1, progress=False)
    run = tmp_path / "c" / CHECKPOINT
    out = export_weights(run, tmp_path / "w.safetensors", fill_from=init, take=("diffuse", "normal"))
    nets, meta = load_weights(out)
    assert nets.maps == MAPS
    b_nets, _ = load_weights(init)
    c_nets, _ = load_weights(run)
    for name in MAPS:
        source = c_nets if name in ("diffuse", "normal") else b_nets
        other = b_nets if source is c_nets else c_nets
        for pa, pb in zip(nets.nets[name].parameters(), source.nets[name].parameters(), strict=True):
            torch.testing.assert_close(pa, pb, rtol=0, atol=0)
        # the run moved every network, so taking the wrong one would show
        pairs = zip(nets.nets[name].parameters(), other.nets[name].parameters(), strict=True)
        assert any(not torch.equal(pa, po) for pa, po in pairs)
    record = training_record(meta)
    assert (record["diffuse"]["steps"], record["normal"]["steps"]) == (3, 3)
    assert (record["specular"]["steps"], record["roughness"]["steps"]) == (2, 2)
    assert record["diffuse"]["from"] == str(run) and record["specular"]["from"] == str(init)
    # without a fill the file has the networks taken, and nothing else
    alone, _ = load_weights(export_weights(run, tmp_path / "t.safetensors", take=("normal",)))
    assert alone.maps == ("normal",)
    with pytest.raises(MatscanError, match="take: gloss is not among the networks it trained"):
        export_weights(run, tmp_path / "x.safetensors", take=("gloss",))
    # a run's exported float16 weights (kept in git instead of its checkpoint) export again
    half = export_weights(run, tmp_path / "h.safetensors", dtype=torch.float16)
    again = export_weights(half, tmp_path / "h2.safetensors", fill_from=init, take=("diffuse", "normal"))
    a, b = load_file(str(half)), load_file(str(again))
    for k, v in a.items():
        if k.split(".")[1] in ("diffuse", "normal"):
            torch.testing.assert_close(b[k].half(), v, rtol=0, atol=0)
    assert training_record(load_weights(again)[1])["specular"]["from"] == str(init)
    # filled from a run's float16 copy, its networks name that copy, not the checkpoint beside it
    beside = tmp_path / "b" / "weights.safetensors"
    export_weights(init, beside, dtype=torch.float16)
    filled = export_weights(run, tmp_path / "f.safetensors", fill_from=beside, take=("diffuse", "normal"))
    record = training_record(load_weights(filled)[1])
    assert record["specular"]["from"] == str(beside) and record["diffuse"]["from"] == str(run)


def test_files_without_a_net_config_load_with_the_median(tmp_path):
    cfg = TrainConfig(preset="cpu")
    nets = build_nets(cfg)
    assert nets.cfg.photo_statistic == "lower_third"
    path = tmp_path / "c.safetensors"
    save_checkpoint(path, nets, torch.optim.Adam(nets.parameters()), 0, cfg, 0.0)
    assert load_weights(path)[0].cfg.photo_statistic == "lower_third"
    tensors = load_file(str(path))
    meta = _metadata(path)
    del meta["net_config"]  # as every file written before the field existed
    save_file(tensors, str(path), metadata=meta)
    old, _ = load_weights(path)
    assert old.cfg == NetConfig(**{**asdict(preset("cpu")), "photo_statistic": "median"})
    for pa, pb in zip(old.parameters(), nets.parameters(), strict=True):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)


def test_a_resumed_run_keeps_the_net_config_it_started_with(tmp_path, monkeypatch):
    train(CFG, tmp_path / "a", max_steps=1, progress=False)
    monkeypatch.setitem(PRESETS, "tiny", NetConfig(**{**asdict(PRESETS["tiny"]), "photo_statistic": "lower_third"}))
    train(CFG, tmp_path / "a", max_steps=1, progress=False)
    meta = _metadata(tmp_path / "a" / CHECKPOINT)
    assert meta["step"] == "2" and json.loads(meta["net_config"])["photo_statistic"] == "median"


# --- material prior, device, run folders of earlier versions ---------------------------------


def test_a_run_folder_from_before_prior_and_device_resumes(tmp_path):
    train(CFG, tmp_path / "a", max_steps=1, progress=False)
    config = tmp_path / "a" / "config.json"
    old = {k: v for k, v in json.loads(config.read_text()).items() if k not in ("prior", "device", "prefetch")}
    config.write_text(json.dumps(old, indent=2) + "\n")  # as written before those fields existed
    res = train(CFG, tmp_path / "a", max_steps=1, progress=False)
    assert res["step"] == 2 and json.loads(config.read_text()) == old  # the run's record stays as it was


def test_where_a_run_executes_may_change_on_resume_but_not_its_prior(tmp_path):
    train(CFG, tmp_path / "a", max_steps=1, progress=False)
    moved = TrainConfig(**{**CFG.__dict__, "device": "cpu", "prefetch": 2, "workers": 0})
    assert train(moved, tmp_path / "a", max_steps=1, progress=False)["step"] == 2
    with pytest.raises(MatscanError, match="differs in prior"):
        train(TrainConfig(**{**CFG.__dict__, "prior": "v2"}), tmp_path / "a", progress=False)


def test_prior_v2_trains_and_is_recorded(tmp_path):
    cfg = TrainConfig(**{**CFG.__dict__, "prior": "v2", "val_every": 0})
    res = train(cfg, tmp_path / "a", max_steps=2, progress=False)
    assert res["step"] == 2 and all(math.isfinite(v) for v in res["losses"].values())
    assert json.loads((tmp_path / "a" / "config.json").read_text())["prior"] == "v2"
    assert json.loads(_metadata(tmp_path / "a" / CHECKPOINT)["config"])["prior"] == "v2"
    with pytest.raises(MatscanError, match="prior: 'v7' is not one of"):
        train(TrainConfig(**{**CFG.__dict__, "prior": "v7"}), tmp_path / "b", progress=False)
    assert not (tmp_path / "b").exists()  # refused before the run folder was made


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    for bad in ("gpu", "cuda:x", ""):
        with pytest.raises(MatscanError, match="is not one of auto, cpu, cuda, cuda:N"):
            resolve_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(MatscanError, match="sees no CUDA device"):
            resolve_device("cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_run_on_cuda_matches_the_cpu_and_resumes_there(tmp_path):
    cfg = TrainConfig(**{**CFG.__dict__, "val_every": 2})
    train(TrainConfig(**{**cfg.__dict__, "device": "cpu"}), tmp_path / "cpu", max_steps=2, progress=False)
    train(TrainConfig(**{**cfg.__dict__, "device": "cuda"}), tmp_path / "gpu", max_steps=2, progress=False)
    tensors = load_file(str(tmp_path / "gpu" / CHECKPOINT))
    assert all(t.device.type == "cpu" for t in tensors.values())
    for a, b in zip(_log(tmp_path / "cpu"), _log(tmp_path / "gpu"), strict=True):
        for k in a:
            assert float(b[k]) == pytest.approx(float(a[k]), rel=2e-3, abs=1e-4), k
    # the GPU run goes on on the CPU
    res = train(TrainConfig(**{**cfg.__dict__, "device": "cpu"}), tmp_path / "gpu", max_steps=1, progress=False)
    assert res["step"] == 3


def test_variants_trained_side_by_side_equal_their_own_runs(tmp_path):
    # tools/train_ablation.py shares batches between the variants of a seed: each run's
    # weights, Adam state and moving average (ema) must still be what train() gives for
    # its config alone, and the export is the average (a decay not 0.5, so that the
    # average's two weights cannot be swapped unseen)
    spec = importlib.util.spec_from_file_location("train_ablation", ROOT / "tools" / "train_ablation.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    base = TrainConfig(**{**CFG.__dict__, "steps": 3, "val_every": 2, "log_every": 1, "ema": 0.75})
    configs = [
        TrainConfig(**{**base.__dict__, "variant": "four", "seed": 0}),
        TrainConfig(**{**base.__dict__, "variant": "no_global_skip", "seed": 0}),
        TrainConfig(**{**base.__dict__, "variant": "four", "seed": 1}),
    ]
    last = tool.train_together(configs, tmp_path / "together", minutes=10, progress=False)
    assert sorted(last) == ["four-s0", "four-s1", "no_global_skip-s0"]
    for cfg in (configs[0], configs[2]):
        alone = tmp_path / f"alone-{cfg.seed}"
        train(cfg, alone, progress=False)
        together = tmp_path / "together" / f"four-s{cfg.seed}"
        stored_alone, stored_together = load_file(str(alone / CHECKPOINT)), load_file(str(together / CHECKPOINT))
        assert stored_alone.keys() == stored_together.keys() and any(k.startswith("ema.") for k in stored_alone)
        for k, v in stored_alone.items():
            torch.testing.assert_close(stored_together[k], v, rtol=0, atol=0, msg=k)
        exported = load_file(str(tmp_path / "together" / f"four-s{cfg.seed}.safetensors"))
        for k, v in stored_together.items():
            if k.startswith("ema."):  # the float16 export is the average, not the last weights
                assert torch.equal(exported[k.removeprefix("ema.")], v.half()), k
        weights = {k: v for k, v in stored_together.items() if k.startswith("model.")}
        assert any(not torch.equal(v, stored_together["ema." + k.removeprefix("model.")]) for k, v in weights.items())
        # train() validates every val_every steps; the tool also at its last step
        assert (together / "val.csv").read_text().startswith((alone / "val.csv").read_text())
    four0, four1 = (_params(tmp_path / "together" / f"four-s{s}" / CHECKPOINT) for s in (0, 1))
    assert any(not torch.equal(a, b) for a, b in zip(four0, four1, strict=True))  # seeds differ
    weights, meta = load_weights(tmp_path / "together" / "no_global_skip-s0.safetensors")
    assert meta["step"] == "3" and weights.variant == "no_global_skip"


def test_variants_side_by_side_resume_from_their_float16_weights(tmp_path):
    """``tools/train_ablation.py --resume``: the runs go on from an earlier call's float16
    exports at their step (a GPU lease brings back only those), log from the next step
    and move their weights; a missing file, or files of different steps, are refused in
    one line."""
    spec = importlib.util.spec_from_file_location("train_ablation", ROOT / "tools" / "train_ablation.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    base = TrainConfig(**{**CFG.__dict__, "steps": 3, "val_every": 0, "log_every": 1})
    configs = [TrainConfig(**{**base.__dict__, "variant": v, "seed": 0}) for v in ("four", "no_global_skip")]
    tool.train_together(configs, tmp_path / "first", minutes=10, progress=False)
    longer = [TrainConfig(**{**c.__dict__, "steps": 5}) for c in configs]
    tool.train_together(longer, tmp_path / "second", minutes=10, progress=False, resume=tmp_path / "first")
    summary = json.loads((tmp_path / "second" / "summary.json").read_text())
    assert summary["steps"] == 5 and summary["resumed_from"]["step"] == 3
    for name in ("four-s0", "no_global_skip-s0"):
        assert [r["step"] for r in _log(tmp_path / "second" / name)] == ["4", "5"]
        before, _ = load_weights(tmp_path / "first" / f"{name}.safetensors")
        after, meta = load_weights(tmp_path / "second" / f"{name}.safetensors")
        assert meta["step"] == "5"
        assert any(not torch.equal(a, b) for a, b in zip(before.parameters(), after.parameters(), strict=True))
    with pytest.raises(SystemExit, match="no such weights file to resume four-s1"):
        seed1 = [TrainConfig(**{**base.__dict__, "seed": 1})]
        tool.train_together(seed1, tmp_path / "x", minutes=10, progress=False, resume=tmp_path / "first")
    shutil.copy(tmp_path / "second" / "four-s0.safetensors", tmp_path / "first" / "four-s0.safetensors")
    with pytest.raises(SystemExit, match="stopped at different steps"):
        tool.train_together(longer, tmp_path / "y", minutes=10, progress=False, resume=tmp_path / "first")


def test_a_moving_average_of_the_weights_is_kept_exported_and_resumed(tmp_path):
    """With ``ema`` d the checkpoint keeps w̄ ← d·w̄ + (1 − d)·w after every step, from the
    weights it starts with: after one step w̄ = d·w0 + (1 − d)·w1 exactly (w0 from a run
    stopped at step 0's twin). Exports, snapshots and loading take the average; a resume
    carries it on and equals the uninterrupted run."""
    d = 0.5
    base = {**CFG.__dict__, "val_every": 0, "steps": 3}
    train(TrainConfig(**{**base, "steps": 1}), tmp_path / "plain", max_steps=0, progress=False)  # w0, untrained
    w0 = load_file(str(tmp_path / "plain" / CHECKPOINT))
    cfg = TrainConfig(**{**base, "ema": d, "snapshot_every": 1})
    train(cfg, tmp_path / "a", max_steps=1, progress=False)
    w1 = load_file(str(tmp_path / "a" / CHECKPOINT))
    names = [k for k in w1 if k.startswith("model.")]
    assert names and all("ema." + k.removeprefix("model.") in w1 for k in names)
    moved = 0
    for k in names:
        want = d * w0[k] + (1 - d) * w1[k]
        torch.testing.assert_close(w1["ema." + k.removeprefix("model.")], want, rtol=0, atol=1e-6)
        moved += int(not torch.equal(w0[k], w1[k]))
    assert moved > 0
    loaded, _ = load_weights(tmp_path / "a" / CHECKPOINT)
    exported, _ = load_weights(export_weights(tmp_path / "a" / CHECKPOINT, tmp_path / "w.safetensors"))
    snap, _ = load_weights(snapshots(tmp_path / "a")[0])
    for k, v in loaded.state_dict().items():
        torch.testing.assert_close(v, w1["ema." + k], rtol=0, atol=0)
        torch.testing.assert_close(exported.state_dict()[k], v, rtol=0, atol=0)
        torch.testing.assert_close(snap.state_dict()[k], v.half().float(), rtol=0, atol=0)
    train(cfg, tmp_path / "a", progress=False)  # resumed to step 3
    train(cfg, tmp_path / "b", progress=False)  # uninterrupted
    a, b = load_file(str(tmp_path / "a" / CHECKPOINT)), load_file(str(tmp_path / "b" / CHECKPOINT))
    for k in (k for k in a if k.startswith("ema.")):
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    with pytest.raises(MatscanError, match="differs in ema"):  # a resume without it would drop the average
        train(TrainConfig(**base), tmp_path / "a", progress=False)
    with pytest.raises(MatscanError, match="ema: 1"):
        train(TrainConfig(**{**base, "ema": 1.0}), tmp_path / "c", progress=False)


def test_the_cli_averages_a_new_run_and_resumes_a_run_as_it_began(tmp_path):
    from matscan.cli import main

    small = ["--preset", "tiny", "--crop", "32", "--batch", "2", "--val-every", "0", "--render-lights", "2"]
    small += ["--workers", "0", "--max-steps", "1"]

    def kept(run: Path) -> bool:
        return any(k.startswith("ema.") for k in load_file(str(run / CHECKPOINT)))

    assert main(["train", "--out", str(tmp_path / "new"), *small]) == 0
    assert json.loads((tmp_path / "new" / "config.json").read_text())["ema"] == 0.999 and kept(tmp_path / "new")
    assert main(["train", "--out", str(tmp_path / "new"), *small]) == 0  # resumed: keeps its average
    assert _metadata(tmp_path / "new" / CHECKPOINT)["step"] == "2" and kept(tmp_path / "new")
    assert main(["train", "--out", str(tmp_path / "none"), "--ema", "0", *small]) == 0
    assert not kept(tmp_path / "none")
    # a run folder from before the average (no "ema" in its config) resumes without one
    config = json.loads((tmp_path / "none" / "config.json").read_text())
    del config["ema"]
    (tmp_path / "none" / "config.json").write_text(json.dumps(config))
    assert main(["train", "--out", str(tmp_path / "none"), *small]) == 0
    assert _metadata(tmp_path / "none" / CHECKPOINT)["step"] == "2" and not kept(tmp_path / "none")
    # and such a config given to a new folder remakes that run as it was: no average
    again = ["train", "--out", str(tmp_path / "again"), "--config", str(tmp_path / "none" / "config.json")]
    assert main([*again, "--max-steps", "1"]) == 0
    assert json.loads((tmp_path / "again" / "config.json").read_text())["ema"] == 0 and not kept(tmp_path / "again")
