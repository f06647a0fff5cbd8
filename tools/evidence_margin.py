"""How large a lead the solver alone needs before ``--refine auto`` trusts the evidence.

With 2 and 3 photos ``--refine auto`` reconstructs without some photos and compares how
well the networks + solver and the solver alone predict them
(``matscan.reconstruct.job.choose_by_evidence``); the solver alone is used only where it
is better by ``EVIDENCE_MARGIN``. This tool measures what each margin would give: for
each weights file, each procedural material of the selection set and each light count
(dome24 Table 4 subsets, 8-bit sRGB, the study's captures:
``matscan.evaluate.study_capture``) it records both candidates' left-out RMSE and the
novel-light RMSE of both candidates' maps from all the photos, then prints the mean
novel-light RMSE that each margin's choice gives, with both candidates and the better of
the two per capture (what a perfect choice would give).

The selection set: procedural materials ``random_material(SIZE, 2**42 + i)``. Training
draws seeds below 2**40 and the published studies (``procedural:N`` in ``matscan
evaluate``) 2**41 + i, so neither has seen these materials; choosing the margin here
keeps the unlike sets and the studies' procedural half for evaluation.

Run: .venv/bin/python tools/evidence_margin.py WEIGHTS [...] [--count 16] [--lights 2,3]
[--margins 0,0.025,0.05,0.075,0.1,0.15,0.2] [--json OUT]
(WEIGHTS "default" is the shipped file; 16 materials × 2 counts, about 4 minutes a
weights file on 2 cores.)
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import torch

from matscan.evaluate import evaluation_lights, rendering_scores, study_capture
from matscan.materials.procedural import random_material
from matscan.reconstruct import ReconstructConfig, reconstruct_capture
from matscan.reconstruct.job import CANDIDATES, choose_by_evidence, evidence_winner
from matscan.rig import resolve_rig
from matscan.weights import load_model

#: The first seed of the selection set (module doc).
SELECTION_SEED = 2**42


def measure(weights: str, count: int, lights: list[str], size: int) -> list[dict]:
    """One record per (light count, material): the candidates' left-out and novel RMSE."""
    rig = resolve_rig("dome24")
    novel = evaluation_lights(rig)
    nets = load_model(weights)[0]
    cfg = ReconstructConfig()
    records = []
    for subset in lights:
        for i in range(count):
            family, truth = random_material(size, SELECTION_SEED + i)
            name = f"selection-{i:03d}-{family}"
            capture = study_capture(name, truth, "srgb8", subset, "dome24", 0.002)
            _, choice = choose_by_evidence(capture, cfg, nets)
            record = {"weights": weights, "material": name, "lights": subset, "left_out": choice["rmse_left_out"]}
            record["novel"] = {}
            for candidate, (use_nets, refine) in CANDIDATES.items():
                res = reconstruct_capture(capture, replace(cfg, refine=refine), nets if use_nets else None)
                scores = rendering_scores(res.maps, truth, novel, rig.field_mm, "novel", flip=False)
                record["novel"][candidate] = scores["novel_rmse"]
            records.append(record)
            print(
                f"{weights} {subset} {name}: left out "
                + ", ".join(f"{k} {v:.4f}" for k, v in record["left_out"].items())
                + "; novel "
                + ", ".join(f"{k} {v:.4f}" for k, v in record["novel"].items()),
                flush=True,
            )
    return records


def mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)


def table(records: list[dict], margins: list[float]) -> str:
    """Mean novel-light RMSE of each margin's choice, by weights and light count, and over all."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((r["weights"], r["lights"]), []).append(r)
    groups[("all", "all")] = records
    head = "| weights | lights | " + " | ".join(CANDIDATES) + " | " + " | ".join(f"{m:g}" for m in margins)
    lines = [head + " | better of the two |", "|---|---:|" + "---:|" * (len(CANDIDATES) + len(margins) + 1)]
    for (w, lights), rs in groups.items():
        cells = [f"{mean(r['novel'][c] for r in rs):.4f}" for c in CANDIDATES]
        cells += [f"{mean(r['novel'][evidence_winner(r['left_out'], m)] for r in rs):.4f}" for m in margins]
        cells.append(f"{mean(min(r['novel'].values()) for r in rs):.4f}")
        lines.append(f"| {w} | {lights} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("weights", nargs="+", help="weights files (or 'default', the shipped one)")
    parser.add_argument("--count", type=int, default=16, help="selection materials (default 16)")
    parser.add_argument("--lights", default="2,3", help="Table 4 subsets (default 2,3: where auto chooses)")
    parser.add_argument("--margins", default="0,0.025,0.05,0.075,0.1,0.15,0.2", help="margins to compare")
    parser.add_argument("--size", type=int, default=256, help="material size in pixels (default 256, the study's)")
    parser.add_argument("--json", default=None, help="also write the records here")
    args = parser.parse_args()
    torch.set_num_threads(2)
    lights = [s.strip() for s in args.lights.split(",")]
    margins = [float(m) for m in args.margins.split(",")]
    records = [r for w in args.weights for r in measure(w, args.count, lights, args.size)]
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)
    print()
    print("Mean novel-light RMSE over the selection set: each candidate always, each margin's choice,")
    print("and the better of the two per capture.")
    print()
    print(table(records, margins))


if __name__ == "__main__":
    main()
