"""Grey-card calibration of a dome whose LEDs are not where, nor as bright as, the rig
file says: what the scales, the flat fields and the fitted positions
(``matscan calibrate --grey --flat-fields --positions``) each bring back.

A simulated dome24 whose LEDs are ±5 mm off their rig-file places (uniform per axis,
each still aimed at the centre), ±20% in brightness and ±3% in colour, with a lens
whose vignetting darkens the field's edge (V = 1 − v ρ², ρ = distance from the centre
over half the field's width; corners at 1 − 2v), photographs an 18% grey card and a
material (8-bit sRGB, read noise 0.002). The grey card's photos are calibrated as
``matscan calibrate`` does (:func:`matscan.calibrate.light_scales`,
:func:`matscan.calibrate.fit_light_positions`), the material reconstructed by the
solver alone (no networks) with

* ideal: the true positions, and the photos divided by the true gains and vignetting;
* nominal: the rig file, uncalibrated;
* scales: the grey card's per-light scales;
* + flats: and its flat fields;
* + colour: the scales per channel (RGB), with the flat fields;
* + positions: the lights at their fitted positions, the RGB scales and flat fields
  measured against them (``calibrate --positions``).

Printed per material: the fitted positions' mean and largest error (mm; the same card
for every material, a new dome each), and the PSNR (dB, sRGB, clipped) of re-renderings
under 16 novel lights against the true maps; then the means.

Run by hand: .venv/bin/python bench/greycal.py [--vignetting=V] [SIZE]   (defaults 0.2, 128)
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import torch

from matscan.calibrate import fit_light_positions, light_scales, with_light_positions
from matscan.capture import Capture
from matscan.capture.folder import Correction
from matscan.capture.virtual import CameraModel, apply_camera
from matscan.mapset import MapSet
from matscan.materials.artist import artist_material
from matscan.materials.photos import photo_material
from matscan.materials.procedural import generate
from matscan.reconstruct import ReconstructConfig, reconstruct_capture
from matscan.render import render_maps, surface_points
from matscan.rig import builtin_rig

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from nearcal import moved  # noqa: E402
from selfcal import novel_psnr  # noqa: E402


def photographs(maps: MapSet, lights, field_mm, vignetting: torch.Tensor, seed: int) -> Capture:
    """The dome's photos of ``maps`` (vignetted, 8-bit sRGB), as a capture on the rig file."""
    rig = builtin_rig("dome24")
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        photos = torch.stack(
            [
                apply_camera(
                    render_maps(maps, lights.select([k]), field_mm)[0] * vignetting, CameraModel(read_noise=0.002), gen
                )
                for k in range(24)
            ]
        )
    top = 1 - 0.5 / 255
    names = tuple(f"led_{k:02d}.png" for k in range(24))
    return Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        (photos >= top).any(1, keepdim=True),
        tuple(range(24)),
        rig.light_set(),
        names,
    )


def calibrated(cap: Capture, scales: dict, flats: dict[str, torch.Tensor]) -> Capture:
    gain = torch.tensor([scales[str(k)] for k in range(24)]).view(24, -1).expand(24, 3).contiguous()
    return replace(
        cap, correction=Correction(None, gain, tuple(flats[str(k)].half() if flats else None for k in range(24)))
    )


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    torch.set_num_threads(2)
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    opts = dict(a[2:].split("=", 1) for a in sys.argv[1:] if a.startswith("--"))
    size = int(args[0]) if args else 128
    v = float(opts.get("vignetting", 0.2))
    rig = builtin_rig("dome24")
    pts = surface_points(rig.field_mm, (size, size))
    vignetting = 1 - v * (pts[..., 0] ** 2 + pts[..., 1] ** 2) / (rig.field_mm[0] / 2) ** 2  # (H, W)
    card = MapSet(
        diffuse=torch.full((3, size, size), 0.18),
        specular=torch.zeros(3, size, size),
        roughness=torch.ones(1, size, size),
        normal=torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, size, size).contiguous(),
    )
    materials = [(f, generate(f, size, 1)) for f in ("leather", "plastic", "paper", "woven_plain", "painted")]
    materials += [(f"{n} (photo)", photo_material(n, size)) for n in ("brick", "gravel")]
    materials += [(f"{n} (artist)", artist_material(n, size)) for n in ("black-leather",)]
    cfg = ReconstructConfig(model="none", refine="on")
    columns = ("ideal", "nominal", "scales", "+ flats", "+ colour", "+ positions")
    rows = []
    t0 = time.perf_counter()
    print(f"{'material':22s} {'pos err mean':>12s} {'max':>6s}   " + " ".join(f"{c:>11s}" for c in columns) + "  (dB)")
    for i, (name, maps) in enumerate(materials):
        g = torch.Generator().manual_seed(200 + i)
        delta = (torch.rand(24, 3, generator=g) * 2 - 1) * 5
        gains = (0.8 + 0.4 * torch.rand(24, 1, generator=g)) * (0.97 + 0.06 * torch.rand(24, 3, generator=g))
        nominal_lights = rig.light_set()
        true_lights = moved(nominal_lights, delta)
        true_lights = true_lights.with_intensity(true_lights.intensity * gains)
        grey = photographs(card, true_lights, rig.field_mm, vignetting, seed=1000 + i)
        cap = photographs(maps, true_lights, rig.field_mm, vignetting, seed=i)

        fit = fit_light_positions(grey)
        fitted = torch.tensor([fit.positions[str(k)] for k in range(24)])
        err = (fitted - true_lights.position).norm(dim=-1)
        placed = {k: fit.positions[str(k)] for k in range(24)}
        scales, _ = light_scales(grey)
        scales_f, flats = light_scales(grey, flat_fields=True)
        scales_c, flats_c = light_scales(grey, flat_fields=True, colour=True)
        scales_p, flats_p = light_scales(with_light_positions(grey, placed), flat_fields=True, colour=True)

        truth_geometry = replace(
            cap, lights=replace(nominal_lights, position=true_lights.position, axis=true_lights.axis)
        )
        ideal = replace(truth_geometry, correction=Correction(None, gains, (vignetting[None].half(),) * 24))
        runs = [
            ideal,
            cap,
            calibrated(cap, scales, {}),
            calibrated(cap, scales_f, flats),
            calibrated(cap, scales_c, flats_c),
            calibrated(with_light_positions(cap, placed), scales_p, flats_p),
        ]
        psnr = []
        for run in runs:
            res = reconstruct_capture(run, cfg)
            psnr.append(novel_psnr(res.maps, res.intensity_scale, maps, cap.field_mm))
        rows.append((float(err.mean()), float(err.max()), *psnr))
        print(
            f"{name:22s} {rows[-1][0]:12.2f} {rows[-1][1]:6.2f}   " + " ".join(f"{p:11.2f}" for p in psnr), flush=True
        )
    means = [sum(r[j] for r in rows) / len(rows) for j in range(2 + len(columns))]
    print(f"{'mean':22s} {means[0]:12.2f} {means[1]:6.2f}   " + " ".join(f"{p:11.2f}" for p in means[2:]))
    print(", ".join(f"{c} − ideal {means[2 + j] - means[2]:+.2f} dB" for j, c in enumerate(columns) if j))
    print(f"{len(rows)} materials at {size}², vignetting {v:g}, in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
