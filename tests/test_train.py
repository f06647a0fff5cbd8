"""Training: a resumed run equals an uninterrupted one; two DDP processes equal one process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from matscan.errors import MatscanError
from matscan.train import TrainConfig, export_weights, load_weights, train

CFG = TrainConfig(
    preset="tiny", crop=32, batch=2, val_every=4, val_count=2, workers=0, render_lights=2, steps=6, log_every=1
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
