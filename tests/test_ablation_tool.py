"""tools/ablation.py --paired: the rule of runs/ablation9-gpu/README.md, on score files
whose per-seed numbers make each verdict by hand."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parent.parent / "tools" / "ablation.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("ablation_tool", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: per variant, per seed: novel, diffuse, specular, roughness, normal °
SCORES = {
    "four": [(0.050, 0.1, 0.10, 0.20, 5.0), (0.052, 0.1, 0.12, 0.20, 5.0), (0.054, 0.1, 0.14, 0.21, 5.0)],
    "no_global_skip": [
        (0.055, 0.2, 0.105, 0.18, 5.0),  # novel: +0.005, beyond the noise 0.0025 -> four better
        (0.056, 0.099, 0.125, 0.18, 5.0),  # diffuse: +0.1, -0.001, +0.1: mean 0.066 > 0.0505, but two signs
        (0.060, 0.2, 0.145, 0.19, 5.0),  # specular: +0.005 each, inside the noise 0.02; roughness -0.02 each
    ],
}


def write_scores(folder: Path, kind: str, scores=SCORES) -> None:
    for variant, seeds in scores.items():
        for seed, (novel, diffuse, specular, roughness, normal) in enumerate(seeds):
            # two light counts whose mean is the seed's score
            lines = [
                f"{variant}-s{seed}.safetensors {n} lights: novel {novel + e:.4f} diffuse {diffuse + e:.4f} "
                f"specular {specular + e:.4f} roughness {roughness + e:.4f} normal {normal + 10 * e:.2f}°"
                for n, e in ((1, 0.001), (24, -0.001))
            ]
            (folder / f"{variant}-s{seed}.{kind}.txt").write_text("\n".join(lines) + "\n")


def test_paired_verdicts_follow_the_rule(tmp_path):
    tool = load_tool()
    write_scores(tmp_path, "unlike")
    rows = {r["score"]: r for r in tool.paired(tool.seed_scores(tmp_path), "four", "no_global_skip")}
    assert rows["novel"]["differences"] == pytest.approx([0.005, 0.004, 0.006])
    assert rows["novel"]["noise"] == pytest.approx(0.0025)
    assert rows["novel"]["verdict"] == "four better"
    assert rows["diffuse"]["mean"] == pytest.approx((0.1 - 0.001 + 0.1) / 3)
    assert rows["diffuse"]["noise"] == pytest.approx(0.0505)
    assert rows["diffuse"]["verdict"] == "inside the noise"  # larger than the noise, but not in every seed
    assert rows["specular"]["verdict"] == "inside the noise"  # every seed, but under the noise
    assert rows["roughness"]["verdict"] == "no_global_skip better"
    assert rows["normal °"]["verdict"] == "inside the noise"  # no difference at all


def test_paired_needs_the_same_two_seeds_or_more(tmp_path):
    tool = load_tool()
    write_scores(tmp_path, "unlike")
    (tmp_path / "no_global_skip-s2.unlike.txt").unlink()
    with pytest.raises(SystemExit, match="not paired"):
        tool.paired(tool.seed_scores(tmp_path), "four", "no_global_skip")
    for name in ("four-s2", "four-s1", "no_global_skip-s1"):
        (tmp_path / f"{name}.unlike.txt").unlink()
    with pytest.raises(SystemExit, match="fewer than two seeds"):
        tool.paired(tool.seed_scores(tmp_path), "four", "no_global_skip")


def test_the_noise_is_the_larger_variants_half_range(tmp_path):
    """One sign in every seed, and a mean (0.0047) above ``four``'s half range (0.001) but
    below ``no_global_skip``'s (0.005): inside the noise. A variant's typo is refused."""
    tool = load_tool()
    scores = {
        "four": [(0.050, 0.1, 0.1, 0.2, 5.0), (0.051, 0.1, 0.1, 0.2, 5.0), (0.052, 0.1, 0.1, 0.2, 5.0)],
        "no_global_skip": [(0.053, 0.1, 0.1, 0.2, 5.0), (0.052, 0.1, 0.1, 0.2, 5.0), (0.062, 0.1, 0.1, 0.2, 5.0)],
    }
    write_scores(tmp_path, "unlike", scores)
    rows = {r["score"]: r for r in tool.paired(tool.seed_scores(tmp_path), "four", "no_global_skip")}
    assert rows["novel"]["differences"] == pytest.approx([0.003, 0.001, 0.010])
    assert rows["novel"]["noise"] == pytest.approx(0.005)
    assert rows["novel"]["mean"] == pytest.approx(0.014 / 3)
    assert rows["novel"]["verdict"] == "inside the noise"
    with pytest.raises(SystemExit, match="no set has scores of both"):
        tool.paired(tool.seed_scores(tmp_path), "four", "no_global_skp")


def test_paired_t_by_hand(tmp_path):
    """Differences 1, 2, 3: mean 2, sd 1, t = 2 * sqrt(3). The fixture's novel differences
    0.005, 0.004, 0.006 give t = 0.005 / (0.001 / sqrt(3)) = 8.66, above the 4.303 of two
    degrees of freedom: four better."""
    tool = load_tool()
    assert tool.paired_t([1.0, 2.0, 3.0]) == pytest.approx(2 * 3**0.5)
    assert tool.paired_t([-1.0, -2.0, -3.0]) == pytest.approx(-2 * 3**0.5)
    assert tool.paired_t([0.5, 0.5]) == float("inf")
    assert tool.paired_t([0.0, 0.0, 0.0]) == 0.0
    write_scores(tmp_path, "unlike")
    rows = {r["score"]: r for r in tool.paired(tool.seed_scores(tmp_path), "four", "no_global_skip")}
    assert rows["novel"]["t"] == pytest.approx(0.005 / (0.001 / 3**0.5))
    assert rows["novel"]["t_verdict"] == "four better"
    # diffuse +0.1, -0.001, +0.1: mean 0.066333, sd 0.058312, t = 1.9703 < 4.303
    assert rows["diffuse"]["t"] == pytest.approx(1.9703, abs=0.0005)
    assert rows["diffuse"]["t_verdict"] == "not significant"
    assert rows["roughness"]["t_verdict"] == "no_global_skip better"  # -0.02 in every seed: t = -inf
    assert tool.T_CRITICAL[5] == 2.571
