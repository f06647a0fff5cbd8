"""Reconstruction cost: seconds and peak memory for 512², 1024² and 3072² with 2, 6
and 24 lights, networks only and networks + refinement.

Each case runs in a fresh process on a capture simulated in memory from the
built-in sample's maps (resampled), with the `cpu` preset networks (random
weights when no shipped weights are installed: the cost is the same). Refinement
runs REFINE_STEPS steps per tile (default 150, as `matscan reconstruct`); pass a
smaller number to keep a 3072² run short, e.g. `bench/reconstruct.py 20`.

Run by hand: .venv/bin/python bench/reconstruct.py [refine_steps]
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time

import torch

SIZES = (512, 1024, 3072)
LIGHTS = ("2", "6", "24")


def case(size: int, lights: str, refine: bool, steps: int) -> dict:
    from matscan.capture import Capture
    from matscan.capture.virtual import CameraModel, resize_maps, simulate_images
    from matscan.mapset import read_mapset
    from matscan.nets import MapNets, preset
    from matscan.reconstruct import ReconstructConfig, reconstruct_capture
    from matscan.rig import builtin_rig
    from matscan.samples import sample_maps_path

    torch.set_num_threads(2)
    rig = builtin_rig("dome24")
    indices = list(rig.subset(lights))
    maps = resize_maps(read_mapset(sample_maps_path()), size)
    ls = rig.light_set(indices)
    photos = simulate_images(maps, ls, rig.field_mm, CameraModel(read_noise=0.002))
    del maps
    capture = Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        photos.amax(1, keepdim=True) >= 1.0,
        tuple(indices),
        ls,
        tuple(f"led_{k:02d}.png" for k in indices),
    )
    try:
        from matscan.weights import load_model

        nets, _ = load_model("default")
    except Exception:
        nets = MapNets(24, preset("cpu")).eval()
    cfg = ReconstructConfig(refine="on" if refine else "off", refine_steps=steps)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    t0 = time.perf_counter()
    res = reconstruct_capture(capture, cfg, nets)
    seconds = time.perf_counter() - t0
    return {
        "seconds": seconds,
        "peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "before_gib": base,
        "timings": res.timings,
    }


def main() -> None:
    if len(sys.argv) == 5:
        print(json.dumps(case(int(sys.argv[1]), sys.argv[2], sys.argv[3] == "1", int(sys.argv[4]))))
        return
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 150
    print(f"refinement: {steps} steps per tile; peak = the process's peak resident memory (GiB)")
    print(f"{'size':>6} {'lights':>6} {'refine':>6} {'seconds':>8} {'networks s':>10} {'refine s':>9} {'peak GiB':>9}")
    for size in SIZES:
        for lights in LIGHTS:
            for refine in (False, True):
                out = subprocess.run(
                    [sys.executable, __file__, str(size), lights, "1" if refine else "0", str(steps)],
                    capture_output=True,
                    text=True,
                )
                if out.returncode:
                    print(f"{size:>6} {lights:>6} {refine!s:>6} failed: {out.stderr.strip().splitlines()[-1]}")
                    continue
                r = json.loads(out.stdout)
                t = r["timings"]
                print(
                    f"{size:>6} {lights:>6} {refine!s:>6} {r['seconds']:>8.1f} {t.get('networks_s', 0):>10.1f} "
                    f"{t.get('refine_s', 0):>9.1f} {r['peak_gib']:>9.2f}"
                )


if __name__ == "__main__":
    main()
