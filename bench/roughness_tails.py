"""What dome24 can tell of a flat glossy surface's roughness.

dome24's highest ring is at 67.5° elevation, so at the field's centre a flat sample's
half vectors lie 11° or more from the normal, in the tail of a glossy GGX lobe, where
D ≈ α²/(π tan⁴θ_h) once tan²θ_h ≫ α² and a rougher surface with a lower F0 photographs
nearly alike. Whether 8-bit photos can still tell them apart (the half vectors run from
about 1°, toward the field's edge below a 67.5° LED, to over 40°) is what this measures.

For a flat dark glossy material (ρ 0.03, F0 0.04, roughness r0) and each other
roughness r, each pixel's F0 that best matches its 24 photos (least squares: the
rendering is linear in F0 for fixed roughness) is found, and printed are:

* the share of the field where some photo still differs by more than one 8-bit sRGB
  code value from the true material's (elsewhere the photos cannot tell r from r0,
  whatever the method), and the largest difference;
* the RMS difference of renderings under the evaluation's 16 novel lights (linear
  radiance, clipped to [0, 1]), which the study scores.

Run by hand: .venv/bin/python bench/roughness_tails.py [R0 ...]   (default 0.22 0.30)
"""

from __future__ import annotations

import sys

import torch

from matscan.color import linear_to_srgb
from matscan.evaluate import evaluation_lights
from matscan.render import render, surface_points
from matscan.rig import builtin_rig

SIZE = 48  # pixels across the 120 mm field: enough to sample every light's angles


def photos(rig, lights, rho: float, f0, r: float) -> torch.Tensor:
    """Renderings (L, 3, SIZE, SIZE) of the flat material; ``f0`` a number or a (SIZE, SIZE) map."""
    shape = (1, 1, SIZE, SIZE)
    flat = torch.zeros(1, 3, SIZE, SIZE)
    flat[:, 2] = 1
    points = surface_points(rig.field_mm, (SIZE, SIZE))
    return render(
        torch.full((1, 3, SIZE, SIZE), rho),
        torch.as_tensor(f0, dtype=torch.float32).expand(1, 3, SIZE, SIZE),
        torch.full(shape, r),
        flat,
        lights,
        points,
    )[0]


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    r0s = [float(a) for a in sys.argv[1:]] or [0.22, 0.30]
    dome = builtin_rig("dome24")
    rig_lights, novel = dome.light_set(), evaluation_lights(dome)
    rho, f0 = 0.03, 0.04
    print("r0    r     mean best F0  field telling them apart  largest difference (codes)  novel-light RMS")
    for r0 in r0s:
        truth = photos(dome, rig_lights, rho, f0, r0)
        truth_novel = photos(dome, novel, rho, f0, r0).clamp(0, 1)
        for r in (0.15, 0.22, 0.30, 0.35, 0.41, 0.50, 0.60):
            # rendering = diffuse part + F0-linear specular part: two renderings fix it
            a = photos(dome, rig_lights, rho, 0.0, r)
            b = photos(dome, rig_lights, rho, 1.0, r) - a
            best = (((truth - a) * b).sum(dim=(0, 1)) / (b * b).sum(dim=(0, 1))).clamp(0, 1)
            fit = a + best * b
            codes = 255 * (linear_to_srgb(fit.clamp(0, 1)) - linear_to_srgb(truth.clamp(0, 1))).abs()
            told = float((codes.amax(dim=(0, 1)) > 1).float().mean())
            nov = photos(dome, novel, rho, best, r).clamp(0, 1)
            rms = float((nov - truth_novel).square().mean().sqrt())
            print(
                f"{r0:.2f}  {r:.2f}  {float(best.mean()):.4f}        {100 * told:5.1f}%{'':20s}"
                f"{float(codes.max()):6.1f}{'':20s}{rms:.4f}"
            )


if __name__ == "__main__":
    main()
