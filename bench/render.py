"""Rendering throughput: matscan's renderer against a straightforward NumPy implementation.

Renders 24 dome24 lights at 512² and 3072² and prints pixel-lights per second, peak
resident memory of each case (each runs in a fresh process), and the ratio to the
NumPy implementation of the same formulas timed in the same run (NumPy loops over
lights, vectorised over pixels, float32; at 3072² it renders 4 of the 24 lights to
keep the run short: throughput is per pixel-light either way). matscan's first call
in a process builds the compiled kernel (or loads it from torch's cache); that
warm-up is printed separately and not counted in the throughput.

Run by hand: .venv/bin/python bench/render.py
"""

from __future__ import annotations

import json
import math
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from matscan.render import render, surface_points
from matscan.rig import builtin_rig


def make_maps(size: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(3, size, size, generator=g) * 0.2
    n[2] = 1
    n = n / n.norm(dim=0, keepdim=True)
    return (
        torch.rand(3, size, size, generator=g),
        torch.rand(3, size, size, generator=g) * 0.3,
        torch.rand(1, size, size, generator=g) * 0.8 + 0.1,
        n,
    )


def numpy_render(diffuse, specular, roughness, normal, rig, indices):
    """design.md's image formation, one light at a time, in plain NumPy (float32)."""
    h, w = diffuse.shape[1:]
    p = surface_points(rig.field_mm, (h, w)).numpy().transpose(2, 0, 1)  # (3, H, W)
    c = np.array(rig.camera.position_mm, np.float32)[:, None, None]
    out = np.empty((len(indices), 3, h, w), np.float32)
    R = rig.reference_distance_mm
    for o, k in enumerate(indices):
        lt = rig.lights[k]
        lv = np.array(lt.position_mm, np.float32)[:, None, None] - p
        d = np.sqrt((lv * lv).sum(0))
        l = lv / d
        v = c - p
        v = v / np.sqrt((v * v).sum(0))
        hv = l + v
        hv = hv / np.sqrt((hv * hv).sum(0))
        nl = (normal * l).sum(0)
        nv = (normal * v).sum(0)
        nh = np.clip((normal * hv).sum(0), 0, None)
        vh = np.clip((v * hv).sum(0), 0, 1)
        alpha = np.maximum(roughness[0] ** 2, 1e-3)
        a2 = alpha * alpha
        D = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
        nlc, nvc = np.maximum(nl, 1e-7), np.maximum(nv, 1e-7)
        G = (2 * nlc / (nlc + np.sqrt(a2 + (1 - a2) * nlc * nlc))) * (
            2 * nvc / (nvc + np.sqrt(a2 + (1 - a2) * nvc * nvc))
        )
        F = specular + (1 - specular) * (1 - vh) ** 5
        fr = diffuse / math.pi + D * G * F / (4 * nlc * nvc) * ((nl > 0) & (nv > 0))
        lobe = np.maximum(-(np.array(lt.axis, np.float32)[:, None, None] * l).sum(0), 0) ** lt.exponent
        inten = np.array(lt.intensity, np.float32)[:, None, None]
        out[o] = math.pi * inten * (R / d) ** 2 * lobe * fr * np.maximum(nl, 0)
    return out


def case(which: str, size: int) -> dict:
    torch.set_num_threads(2)
    rig = builtin_rig("dome24")
    maps = make_maps(size)
    if which == "matscan":
        indices = list(range(24))
        pts = surface_points(rig.field_mm, (size, size))
        with torch.no_grad():
            t0 = time.perf_counter()  # first call: builds (or loads from cache) the compiled kernel
            render(*make_maps(64), rig.light_set(indices), surface_points(rig.field_mm, (64, 64)), compile=True)
            warmup = time.perf_counter() - t0
            t0 = time.perf_counter()
            out = render(*maps, rig.light_set(indices), pts)
            seconds = time.perf_counter() - t0
    else:
        warmup = 0.0
        indices = list(range(24)) if size <= 1024 else [0, 5, 10, 20]
        arrays = [m.numpy() for m in maps]
        t0 = time.perf_counter()
        out = numpy_render(*arrays, rig, indices)
        seconds = time.perf_counter() - t0
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return {
        "seconds": seconds,
        "warmup": warmup,
        "pixel_lights": size * size * len(indices),
        "peak_gib": peak_gib,
        "checksum": float(np.asarray(out[:1]).mean()),
    }


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    if len(sys.argv) == 3:
        print(json.dumps(case(sys.argv[1], int(sys.argv[2]))))
        return
    print(f"{'size':>6} {'impl':>8} {'Mpix·light/s':>13} {'seconds':>8} {'peak GiB':>9} {'warm-up s':>10}")
    for size in (512, 3072):
        res = {}
        for which in ("matscan", "numpy"):
            out = subprocess.run(
                [sys.executable, __file__, which, str(size)], capture_output=True, text=True, check=True
            )
            r = json.loads(out.stdout)
            res[which] = r
            rate = r["pixel_lights"] / r["seconds"] / 1e6
            print(f"{size:>6} {which:>8} {rate:>13.1f} {r['seconds']:>8.2f} {r['peak_gib']:>9.2f} {r['warmup']:>10.1f}")
        ratio = (res["matscan"]["pixel_lights"] / res["matscan"]["seconds"]) / (
            res["numpy"]["pixel_lights"] / res["numpy"]["seconds"]
        )
        print(f"{size:>6} {'ratio':>8} {ratio:>12.1f}×  (matscan / NumPy, same run)")


if __name__ == "__main__":
    main()
