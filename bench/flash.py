"""Phone-flash captures, leave one out: is any held-out photo predicted far worse than the rest?

For each material, 9 photos through the built-in `flash` rig (a 3 × 3 grid of phone
positions, flash beside the lens; 8-bit sRGB with noise, intensity unknown to the
reconstruction, as with a real phone). Each photo in turn is left out; the other 8 are
reconstructed (no networks: they are trained for the dome; the intensity scale is fitted
with the maps) and the left-out photo is re-rendered from the result. Printed per material
and solver: the RMSE of each held-out photo (sRGB, what a person sees), and the largest
over the median (the issue asks for at most 2).

Run by hand: .venv/bin/python bench/flash.py [SIZE] [SOLVERS]   (default 128 lm,adam)
"""

from __future__ import annotations

import sys
import time

import torch

from matscan.capture import Capture
from matscan.capture.virtual import CameraModel, default_flash_geometry, simulate_images
from matscan.color import linear_to_srgb
from matscan.materials.photos import photo_material
from matscan.materials.procedural import generate
from matscan.reconstruct import ReconstructConfig, reconstruct_capture, subset_capture
from matscan.render import render, surface_points
from matscan.rig import Light, LightSet, builtin_rig


def flash_capture(maps, size: int, seed: int) -> Capture:
    rig = builtin_rig("flash")
    template = rig.lights[0]
    geometry = default_flash_geometry()
    lights = LightSet.from_lights(
        [Light(tuple(g[0]), template.intensity, template.exponent, template.aim_mm) for g in geometry],
        [tuple(g[1]) for g in geometry],
        rig.reference_distance_mm,
    )
    photos = simulate_images(maps, lights, rig.field_mm, CameraModel(read_noise=0.002), seed=seed)
    top = 1 - 0.5 / 255
    return Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        (photos >= top).any(1, keepdim=True),
        (None,) * len(geometry),
        lights,
        tuple(f"{i:02d}.png" for i in range(len(geometry))),
    )


def held_out_errors(capture: Capture, solver: str) -> list[float]:
    n = len(capture.files)
    pts = surface_points(capture.field_mm, capture.size)
    errors = []
    for i in range(n):
        kept = [j for j in range(n) if j != i]
        res = reconstruct_capture(subset_capture(capture, kept), ReconstructConfig(model="none", solver=solver))
        m = res.maps
        with torch.no_grad():
            img = render(m.diffuse, m.specular, m.roughness, m.normal, capture.lights.select([i]), pts)[0]
        img = (img * res.intensity_scale).clamp(0, 1)
        errors.append(float((linear_to_srgb(img) - linear_to_srgb(capture.linear([i])[0])).square().mean().sqrt()))
    return errors


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    torch.set_num_threads(2)
    size = int(sys.argv[1]) if len(sys.argv) > 1 else 128
    solvers = sys.argv[2].split(",") if len(sys.argv) > 2 else ["lm", "adam"]
    materials = [
        ("brick (photo)", photo_material("brick", size)),
        ("leather_embossed", generate("leather_embossed", size, 3)),
        ("metallic_print", generate("metallic_print", size, 3)),
    ]
    for name, maps in materials:
        capture = flash_capture(maps, size, seed=len(name))
        for solver in solvers:
            t0 = time.perf_counter()
            errors = held_out_errors(capture, solver)
            median = sorted(errors)[len(errors) // 2]
            print(
                f"{name:18s} {solver:4s} held-out sRGB RMSE "
                + " ".join(f"{e:.3f}" for e in errors)
                + f"  max/median {max(errors) / median:.2f}  ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
