"""Saturated values in the ``lm`` solver: dropped (as before) or censored ("at least the
clip", ``SolverConfig.censored``); runs/lm-censored/README.md has the rule.

Each map set is photographed by dome24 at exposure E (8-bit sRGB, read noise 0.002:
``runs/lm_noise.py``'s camera) and divided by E again; E = 1 is the study's photographs
(highlights clip), E = 4 a capture exposed four times longer, whose highlights clip four
times lower. ``reconstruct_capture`` as the command runs it (networks, then the solver),
with censoring off and on, scored against the truth: per-map RMSE, mean normal error,
the novel-light RMSE of the study (16 lights the rig does not have), and the share of
saturated values. ``python runs/lm_censored.py [--size=128] [--lights=24,6,3]
[--exposures=1,4] [--set=selection:N|unlike|gold] [--model=none]`` from the repository
root. ``gold``: one uniform gold (F0 (1, 0.78, 0.34), diffuse 0, roughness 0.3, flat), the
audit's case, with its mean F0 and roughness printed too. ``--time=SIZE``: instead, the
wall time of ``reconstruct_capture`` on the built-in sample at SIZE² × 24 (8-bit, E = 1),
each way three times, alternating, in one process; ``--time=FOLDER``: the same for a
capture folder (``matscan import-rti tests/data/rti-icon --out /tmp/icon``, say).
"""

import time

import torch
from lm_noise import capture, option, small

from matscan.calibrate import apply_calibration
from matscan.capture import load_capture
from matscan.evaluate import evaluation_lights, map_scores, rendering_scores
from matscan.mapset import MapSet, read_mapset
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.materials.photos import photo_material
from matscan.materials.procedural import random_material
from matscan.reconstruct import ReconstructConfig, lm, reconstruct_capture
from matscan.rig import builtin_rig
from matscan.weights import load_model


def main() -> None:
    torch.set_num_threads(2)
    size = int(option("size", "128"))
    subsets = option("lights", "24,6,3").split(",")
    exposures = [float(e) for e in option("exposures", "1,4").split(",")]
    rig = builtin_rig("dome24")
    nets = None if option("model", "default") == "none" else load_model(option("model", "default"))[0]
    which = option("set", "selection:24")
    if option("time", ""):
        timed(option("time", ""), rig, nets)
        return
    if which == "gold":
        f0 = torch.tensor([1.0, 0.78, 0.34])[:, None, None].expand(3, size, size)
        flat = torch.tensor([0.0, 0.0, 1.0])[:, None, None].expand(3, size, size)
        gold = MapSet(torch.zeros(3, size, size), f0.clone(), torch.full((1, size, size), 0.3), flat.clone())
        materials = [("gold", gold)]
    elif which.startswith("selection"):  # procedural prior v4, seeds 2^42 + i (tools/solver_priors.py)
        count = int(which.partition(":")[2] or 24)
        materials = [
            (f"v4-{i:02d}-{f}", m) for i in range(count) for f, m in [random_material(size, 2**42 + i, prior="v4")]
        ]
    else:
        materials = [(n, artist_material(n, size)) for n in ARTIST_NAMES]
        materials += [(f"photo-{n}", photo_material(n, size)) for n in ("brick", "grass", "gravel")]
        materials += [("sample", small(read_mapset("@sample"), size))]
    novel = evaluation_lights(rig)
    keys = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "normal_degrees", "novel_rmse")
    print(
        f"{which}, {size}², 8-bit sRGB, read noise 0.002, model {option('model', 'default')}; "
        f"mean over {len(materials)} map sets: " + ", ".join(keys) + ", saturated share"
    )
    for subset in subsets:
        for exposure in exposures:
            caps = [capture(t, rig, subset, exposure, 8, seed=i) for i, (_, t) in enumerate(materials)]
            share = sum(float(c.saturated.float().mean()) for c in caps) / len(caps)
            for censored in (False, True):
                cfg = ReconstructConfig(lm=lm.SolverConfig(censored=censored))
                t0 = time.perf_counter()
                rows = []
                for (name, truth), cap in zip(materials, caps, strict=True):
                    res = reconstruct_capture(cap, cfg, nets)
                    row = map_scores(res.maps, truth)
                    row.update(rendering_scores(res.maps, truth, novel, rig.field_mm, "novel", flip=False))
                    rows.append(row)
                    if which == "gold":
                        f0 = ", ".join(f"{float(v):.3f}" for v in res.maps.specular.mean((1, 2)))
                        print(f"  F0 ({f0}), roughness {float(res.maps.roughness.mean()):.3f}")
                    print(
                        f"  {subset:>2} lights E={exposure:g} censored {censored:d} {name:24s} "
                        + " ".join(f"{row[k]:.4f}" for k in keys)
                        + f" {float(cap.saturated.float().mean()):.4f}",
                        flush=True,
                    )
                mean = {k: sum(row[k] for row in rows) / len(rows) for k in keys}
                print(
                    f"{subset:>2} lights E={exposure:<4g} censored {censored:d}: "
                    + " ".join(f"{mean[k]:.4f}" for k in keys)
                    + f" {share:.4f}  ({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )


def timed(what: str, rig, nets) -> None:
    if what.isdigit():
        cap = capture(small(read_mapset("@sample"), int(what)), rig, "24", 1.0, 8, seed=0)
        what = f"sample {what}² × 24, 8-bit"
    else:
        cap = apply_calibration(load_capture(what))
    print(f"{what}: saturated share {float(cap.saturated.float().mean()):.4f}")
    seconds: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(3):
        for censored in (False, True):
            t0 = time.perf_counter()
            reconstruct_capture(cap, ReconstructConfig(lm=lm.SolverConfig(censored=censored)), nets)
            seconds[censored].append(time.perf_counter() - t0)
    off, on = min(seconds[False]), min(seconds[True])
    print(f"fastest of 3: off {off:.2f} s, on {on:.2f} s, on/off {on / off:.3f}")


if __name__ == "__main__":
    main()
