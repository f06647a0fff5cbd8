"""The ``lm`` solver's full-resolution level: a fixed two steps (as before) or two and then
up to ``SolverConfig.more_iterations`` more on the pixels still converging;
runs/lm-converge/README.md has the rule.

``python runs/lm_converge.py [--size=128] [--lights=24,6,3] [--exposures=1,4]
[--set=selection:N] [--model=none] [--more=8]`` from the repository root: each map set
photographed by dome24 at exposure E (``runs/lm_censored.py``'s captures) and
reconstructed as the command does (networks, then the solver) with ``more_iterations`` 0
and ``--more``; per-map RMSE, mean normal error and the novel-light RMSE (the study's 16
lights), mean over the map sets, per cell. ``--time=SIZE`` or ``--time=FOLDER``: instead,
the wall time of ``reconstruct_capture`` each way, three times alternating in one process.
``--compare BEFORE.json AFTER.json``: the mean novel-light RMSE per set, method and light
count of two ``matscan evaluate`` results, and their ratio.
"""

import json
import sys
import time
from collections import defaultdict

import torch
from lm_noise import capture, option, small

from matscan.calibrate import apply_calibration
from matscan.capture import load_capture
from matscan.evaluate import evaluation_lights, map_scores, rendering_scores
from matscan.mapset import read_mapset
from matscan.materials.procedural import random_material
from matscan.reconstruct import ReconstructConfig, lm, reconstruct_capture
from matscan.rig import builtin_rig
from matscan.weights import load_model

KEYS = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "normal_degrees", "novel_rmse")


def main() -> None:
    if "--compare" in sys.argv:
        i = sys.argv.index("--compare")
        compare(sys.argv[i + 1], sys.argv[i + 2])
        return
    torch.set_num_threads(2)
    size = int(option("size", "128"))
    more = int(option("more", "8"))
    rig = builtin_rig("dome24")
    nets = None if option("model", "default") == "none" else load_model(option("model", "default"))[0]
    if option("time", ""):
        timed(option("time", ""), rig, nets, more)
        return
    count = int(option("set", "selection:24").partition(":")[2] or 24)
    # procedural prior v4, seeds 2^42 + i: neither training nor the studies draw them
    materials = [
        (f"v4-{i:02d}-{f}", m) for i in range(count) for f, m in [random_material(size, 2**42 + i, prior="v4")]
    ]
    novel = evaluation_lights(rig)
    print(
        f"selection:{count}, {size}², 8-bit sRGB, read noise 0.002, model {option('model', 'default')}; "
        f"mean over {len(materials)} map sets: " + ", ".join(KEYS)
    )
    for subset in option("lights", "24,6,3").split(","):
        for exposure in [float(e) for e in option("exposures", "1,4").split(",")]:
            caps = [capture(t, rig, subset, exposure, 8, seed=i) for i, (_, t) in enumerate(materials)]
            for steps in (0, more):
                cfg = ReconstructConfig(lm=lm.SolverConfig(more_iterations=steps))
                t0 = time.perf_counter()
                rows = []
                for (name, truth), cap in zip(materials, caps, strict=True):
                    res = reconstruct_capture(cap, cfg, nets)
                    row = map_scores(res.maps, truth)
                    row.update(rendering_scores(res.maps, truth, novel, rig.field_mm, "novel", flip=False))
                    rows.append(row)
                    print(
                        f"  {subset:>2} lights E={exposure:g} more {steps} {name:24s} "
                        + " ".join(f"{row[k]:.4f}" for k in KEYS)
                    )
                mean = {k: sum(row[k] for row in rows) / len(rows) for k in KEYS}
                print(
                    f"{subset:>2} lights E={exposure:<4g} more {steps}: "
                    + " ".join(f"{mean[k]:.4f}" for k in KEYS)
                    + f"  ({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )


def timed(what: str, rig, nets, more: int) -> None:
    if what.isdigit():
        cap = capture(small(read_mapset("@sample"), int(what)), rig, "24", 1.0, 8, seed=0)
        what = f"sample {what}² × 24, 8-bit"
    else:
        cap = apply_calibration(load_capture(what))
    seconds: dict[int, list[float]] = {0: [], more: []}
    for _ in range(3):
        for steps in (0, more):
            t0 = time.perf_counter()
            reconstruct_capture(cap, ReconstructConfig(lm=lm.SolverConfig(more_iterations=steps)), nets)
            seconds[steps].append(time.perf_counter() - t0)
    off, on = min(seconds[0]), min(seconds[more])
    print(f"{what}: fastest of 3: more 0 {off:.2f} s, more {more} {on:.2f} s, ratio {on / off:.3f}")


def _means(path: str) -> dict[tuple[str, str, int], float]:
    """Mean novel-light RMSE per (set, method, lights): set "procedural" or "unlike"."""
    sums: dict[tuple[str, str, int], list[float]] = defaultdict(list)
    for r in json.loads(open(path).read())["rows"]:
        half = "procedural" if r["material"].startswith("procedural") else "unlike"
        sums[(half, r["method"], r["lights"])].append(r["novel_rmse"])
    return {k: sum(v) / len(v) for k, v in sums.items()}


def compare(before: str, after: str) -> None:
    a, b = _means(before), _means(after)
    print(f"{'set':11s} {'method':8s} {'lights':>6s} {'before':>8s} {'after':>8s} {'ratio':>6s}")
    for key in sorted(set(a) & set(b), key=lambda k: (k[0], k[1], int(k[2]))):
        print(f"{key[0]:11s} {key[1]:8s} {key[2]:>6} {a[key]:8.5f} {b[key]:8.5f} {b[key] / a[key]:6.3f}")


if __name__ == "__main__":
    main()
