"""Export the ablation runs' weights and tabulate their training and validation.

Each run folder (trained with `matscan train --out runs/ablation/VARIANT --variant VARIANT
--steps 2000`) gets its weights exported as float16 beside it
(runs/ablation/VARIANT.safetensors, about half the float32 size, small enough to commit), for
`matscan evaluate --methods nets:runs/ablation/VARIANT.safetensors`. Prints, as Markdown, the
parameter count, seconds per step and the validation RMSE at the last step every run
reached (the fixed procedural validation set, random light subsets), and, when given a
reference run of the same configuration (--reference runs/dome24-cpu-stage1, the first stage
of the shipped weights, whose G_d started from the median as the ablation runs' did), how far the
variant `four`'s validation is from the reference's at the same steps: training is seeded,
so only floating-point summation order (thread counts) separates them.

Run: .venv/bin/python tools/ablation.py runs/ablation/{four,one_encoder,global_track,no_global_skip}
     [--reference runs/dome24-cpu-stage1]

With ``--scores DIR`` it tabulates instead the scores that ``tools/nets_unlike.py`` wrote
for several seeds of each variant (``DIR/VARIANT-sSEED.unlike.txt`` and ``.procedural.txt``,
as ``runs/ablation-gpu/lease.sh score`` makes them): per set and variant, each score's mean
over the light counts, averaged over the seeds, with half the seeds' range beside it (the
noise a difference between variants must exceed). ``--paired A,B`` adds, per set and score,
each seed's difference B − A (both saw the same batches) and whether it is beyond the noise
(the rule of runs/ablation9-gpu/README.md: one sign in every seed, and a mean above the
largest half range over the seeds of either variant), and the paired Student's t of the
differences with its two-sided 5% verdict (that README's rule for six seeds).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
from pathlib import Path

import torch

from matscan.train import CHECKPOINT, export_weights, load_weights

COLUMNS = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "rmse_normal", "normal_degrees")


def read_csv(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open())) if path.is_file() else []


#: One line of ``tools/nets_unlike.py``'s output: a light count's means over the map sets.
SCORE_LINE = re.compile(
    r"(\d+) lights: novel ([\d.]+) diffuse ([\d.]+) specular ([\d.]+) roughness ([\d.]+) normal ([\d.]+)°"
)
SCORES = ("novel", "diffuse", "specular", "roughness", "normal °")


def seed_scores(folder: Path) -> dict[tuple[str, str], dict[str, list[float]]]:
    """Per (set, variant), per seed: each score's mean over the light counts of its score file."""
    found: dict[tuple[str, str], dict[str, list[float]]] = {}
    for path in sorted(folder.glob("*-s*.*.txt")):
        run, kind = path.name.split(".")[:2]
        variant, seed = run.rsplit("-s", 1)
        rows = [[float(v) for v in m.groups()[1:]] for m in map(SCORE_LINE.search, path.read_text().splitlines()) if m]
        if not rows:
            raise SystemExit(f"{path}: no scores in it")
        found.setdefault((kind, variant), {})[seed] = [sum(r[k] for r in rows) / len(rows) for k in range(len(SCORES))]
    if not found:
        raise SystemExit(f"{folder}: no VARIANT-sSEED.SET.txt score files")
    return found


def half_range(values: list[float]) -> float:
    return (max(values) - min(values)) / 2


#: Student's t two-sided 5% critical values by degrees of freedom (any statistics table).
T_CRITICAL = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228}


def paired_t(d: list[float]) -> float:
    """The paired t statistic of differences ``d``: mean / (sample sd / sqrt(n)), sd with n - 1;
    ±inf where every difference is the same nonzero number, 0 where all are zero."""
    n = len(d)
    mean = sum(d) / n
    sd = (sum((x - mean) ** 2 for x in d) / (n - 1)) ** 0.5
    if sd == 0:
        return 0.0 if mean == 0 else float("inf") if mean > 0 else float("-inf")
    return mean / (sd / n**0.5)


def seed_table(folder: Path) -> str:
    """Markdown: per set and variant, the scores' means over the counts, mean ± half range over seeds."""
    found = seed_scores(folder)
    lines = ["| set | variant | seeds | " + " | ".join(SCORES) + " |", "|---|---|---:|" + "---:|" * len(SCORES)]
    for (kind, variant), seeds in sorted(found.items(), key=lambda kv: (kv[0][0], VARIANT_ORDER.index(kv[0][1]))):
        cells = []
        for k in range(len(SCORES)):
            vals = [v[k] for v in seeds.values()]
            digits = 2 if SCORES[k].endswith("°") else 4
            cells.append(f"{sum(vals) / len(vals):.{digits}f} ± {half_range(vals):.{digits}f}")
        lines.append(f"| {kind} | {variant} | {len(seeds)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def paired(found: dict[tuple[str, str], dict[str, list[float]]], a: str, b: str) -> list[dict]:
    """Each set's and score's paired differences ``b - a`` over the seeds (both variants must
    have the same; every score is an error: positive means ``a`` is better), and whether it is
    beyond the noise: one sign in every seed, and a mean larger than the largest half range
    over the seeds of either variant's score (runs/ablation9-gpu/README.md's rule)."""
    out = []
    for kind in sorted({k for k, _ in found}):
        if (kind, a) not in found or (kind, b) not in found:
            continue
        seeds = sorted(found[kind, a], key=int)
        if seeds != sorted(found[kind, b], key=int):
            raise SystemExit(f"{kind}: {a} has seeds {seeds}, {b} {sorted(found[kind, b], key=int)}: not paired")
        if len(seeds) < 2:
            raise SystemExit(f"{kind}: {a} and {b} have fewer than two seeds; the noise needs two")
        for k, score in enumerate(SCORES):
            d = [found[kind, b][s][k] - found[kind, a][s][k] for s in seeds]
            mean = sum(d) / len(d)
            noise = max(half_range([found[kind, v][s][k] for s in seeds]) for v in (a, b))
            one_sign = all(x > 0 for x in d) or all(x < 0 for x in d)
            beyond = one_sign and abs(mean) > noise
            t = paired_t(d)
            critical = T_CRITICAL.get(len(d) - 1)
            out.append(
                {
                    "set": kind,
                    "score": score,
                    "seeds": seeds,
                    "differences": d,
                    "mean": mean,
                    "noise": noise,
                    "verdict": (f"{a} better" if mean > 0 else f"{b} better") if beyond else "inside the noise",
                    "t": t,
                    "t_verdict": "–"
                    if critical is None
                    else ((f"{a} better" if t > 0 else f"{b} better") if abs(t) > critical else "not significant"),
                }
            )
    if not out:
        variants = sorted({v for _, v in found})
        raise SystemExit(f"--paired {a},{b}: no set has scores of both (variants found: {', '.join(variants)})")
    return out


def paired_table(folder: Path, a: str, b: str) -> str:
    rows = paired(seed_scores(folder), a, b)
    lines = [
        f"| set | score | {b} − {a}, per seed | mean | noise | verdict | t | t, 5% |",
        "|---|---|---|---:|---:|---|---:|---|",
    ]
    for r in rows:
        digits = 2 if r["score"].endswith("°") else 4
        per = ", ".join(f"{x:+.{digits}f}" for x in r["differences"])
        mean, noise = f"{r['mean']:+.{digits}f}", f"{r['noise']:.{digits}f}"
        t = f"{r['t']:+.2f} | {r['t_verdict']}"
        lines.append(f"| {r['set']} | {r['score']} | {per} | {mean} | {noise} | {r['verdict']} | {t} |")
    return "\n".join(lines)


VARIANT_ORDER = ("four", "one_encoder", "global_track", "no_global_skip")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="*", type=Path)
    parser.add_argument("--reference", type=Path, help="a run of the same configuration to compare `four` with")
    parser.add_argument("--scores", type=Path, help="tabulate the seeds' score files in this folder instead")
    parser.add_argument(
        "--paired", metavar="A,B", help="with --scores: B - A per seed, and whether it is beyond the noise"
    )
    args = parser.parse_args()
    if args.scores is not None:
        print(seed_table(args.scores))
        if args.paired:
            a, _, b = args.paired.partition(",")
            if not a or not b or "," in b:
                parser.error(f"--paired: {args.paired!r} is not two variants joined by a comma")
            print()
            print(paired_table(args.scores, a, b))
        return 0
    if args.paired:
        parser.error("--paired needs --scores")
    if not args.runs:
        parser.error("give run folders, or --scores DIR")

    rows = []
    for run in args.runs:
        cfg = json.loads((run / "config.json").read_text())
        out = run.with_suffix(".safetensors")
        export_weights(run / CHECKPOINT, out, {"run": str(run)}, dtype=torch.float16)
        nets, meta = load_weights(out)
        val = read_csv(run / "val.csv")
        step = int(meta["step"])
        seconds = float(meta.get("elapsed_seconds", 0))
        rows.append((run, cfg, nets, step, seconds, val, out))

    print("| variant | parameters | steps | s/step | " + " | ".join(COLUMNS) + " | weights |")
    print("|---|---:|---:|---:|" + "---:|" * len(COLUMNS) + "---|")
    for _run, cfg, nets, step, seconds, val, out in rows:
        last = val[-1] if val else {}
        params = sum(p.numel() for p in nets.parameters())
        cells = " | ".join(f"{float(last[c]):.4f}" if c in last else "–" for c in COLUMNS)
        print(
            f"| {cfg['variant']} | {params:,} | {step} | {seconds / max(step, 1):.2f} | {cells} | "
            f"`{out}` ({out.stat().st_size / 2**20:.1f} MiB) |"
        )
    print(f"\n(validation at step {rows[0][5][-1]['step'] if rows[0][5] else '–'}; threads per run: see the logs)")

    if args.reference:
        ref = {r["step"]: r for r in read_csv(args.reference / "val.csv")}
        for run, cfg, _nets, _step, _s, val, _out in rows:
            if cfg["variant"] != "four":
                continue
            print(f"\n`{run}` against `{args.reference}` at the same steps (validation, this run / reference):")
            for r in val:
                if r["step"] in ref:
                    pairs = ", ".join(f"{c} {float(r[c]):.4f} / {float(ref[r['step']][c]):.4f}" for c in COLUMNS)
                    print(f"- step {r['step']}: {pairs}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
