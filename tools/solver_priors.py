"""How strongly the ``lm`` solver should hold F0 and roughness to their start: a sweep on a selection set.

The solver's prior (``matscan.reconstruct.lm.SolverConfig``: ``prior_specular``,
``prior_roughness``) decides wherever the photos say little. A smooth dielectric away
from every highlight is such a place: its photos are explained as well by a broad lobe
with a small F0 as by a narrow one with F0 0.04, so a weak hold on F0 lets it fall and a
strong hold on a wrong starting roughness (the networks read glossy plastic and varnish
as satin) keeps the roughness. This tool reconstructs every material of a selection set
under each light count with ``--refine auto`` (the networks, the evidence choice at 2
and 3 photos, the solver) for each pair of strengths, and prints the mean novel-light
RMSE and the roughness and specular RMSE per count and pair.

The selection set: procedural materials ``random_material(SIZE, 2**42 + i, prior)``
(default prior v4, which holds glossy plastics, varnish, dark glossy and metal
families). Training draws seeds below 2**40 and the published studies 2**41 + i, so
choosing the strengths here keeps the unlike sets and the studies' procedural half for
evaluation.

Run: .venv/bin/python tools/solver_priors.py [--count 24] [--size 128] [--lights 2,3,6,10,16,24]
[--specular 0.2,1,5] [--roughness 0.5,0.1,0.02] [--json OUT]
(24 materials × 6 counts × 9 pairs: about 25 minutes on 2 cores.)
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import torch

from matscan.evaluate import evaluation_lights, map_scores, rendering_scores, study_capture
from matscan.materials.procedural import PRIORS, random_material
from matscan.reconstruct import ReconstructConfig, reconstruct_capture
from matscan.reconstruct.lm import SolverConfig
from matscan.rig import resolve_rig
from matscan.weights import load_model

#: The first seed of the selection set (module doc).
SELECTION_SEED = 2**42


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", default="default")
    parser.add_argument("--count", type=int, default=24, help="materials of the selection set")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--prior", default="v4", choices=sorted(PRIORS))
    parser.add_argument("--lights", default="2,3,6,10,16,24", help="dome24 Table 4 counts")
    parser.add_argument("--specular", type=_floats, default=[0.2, 1.0, 5.0], help="prior_specular values")
    parser.add_argument("--roughness", type=_floats, default=[0.5, 0.1, 0.02], help="prior_roughness values")
    parser.add_argument("--json", type=Path, help="write every record here")
    args = parser.parse_args()
    torch.set_num_threads(2)
    rig = resolve_rig("dome24")
    novel = evaluation_lights(rig)
    nets = load_model(args.weights)[0]
    pairs = list(itertools.product(args.specular, args.roughness))
    mats = [random_material(args.size, SELECTION_SEED + i, prior=args.prior) for i in range(args.count)]
    records = []
    t0 = time.perf_counter()
    for subset in args.lights.split(","):
        for i, (family, truth) in enumerate(mats):
            name = f"selection-{i:03d}-{family}"
            capture = study_capture(name, truth, "srgb8", subset, "dome24", 0.002)
            for spec, rough in pairs:
                cfg = ReconstructConfig(lm=SolverConfig(prior_specular=spec, prior_roughness=rough))
                res = reconstruct_capture(capture, cfg, nets)
                row = {"material": name, "family": family, "lights": subset, "specular": spec, "roughness": rough}
                row.update(map_scores(res.maps, truth))
                row.update(rendering_scores(res.maps, truth, novel, rig.field_mm, "novel"))
                records.append(row)
        print(f"{subset} lights done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    if args.json:
        args.json.write_text(json.dumps(records, indent=1))
    counts = args.lights.split(",")
    for key, label in (("novel_rmse", "novel-light RMSE"), ("rmse_roughness", "roughness"), ("rmse_specular", "F0")):
        print(
            f"\n{label}, mean over {args.count} materials\nprior_specular prior_roughness "
            + " ".join(f"{c:>7s}" for c in counts)
            + "    mean"
        )
        for spec, rough in pairs:
            means = []
            for c in counts:
                vals = [
                    r[key] for r in records if r["lights"] == c and r["specular"] == spec and r["roughness"] == rough
                ]
                means.append(sum(vals) / len(vals))
            print(
                f"{spec:14g} {rough:15g} " + " ".join(f"{m:7.4f}" for m in means) + f" {sum(means) / len(means):7.4f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
