"""Whether the photos alone tell a capture's own light places from a merged calibration's:
for bench/nearcal.py's materials named (``main:1`` the brick, ``others:4`` the gravel; the
list and index, as the bench's lists share domes by index), the photos' re-rendering RMSE
(against the raw photos, each fit's gains multiplied into its lights) and the novel-light
PSNR below the ideal dome of the ideal dome's fit, the capture's own
``--self-calibrate-positions`` from the rig file, the four's merged calibration held
(``reconstruct --calibration``) and fitted from there (with ``--self-calibrate-positions``).
The calibrations are those in nearcal-calibrated/calibrations-s128.json; ``--from=NAMES``
merges those of the named ones (default paper,brick,leather,plastic).
``python runs/nearcal_misfit.py [--from=NAMES] DRAW main:1 others:4`` from the repository
root (about 2 minutes a material on 2 cores)."""

import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "bench"))
from nearcal import led_gains, moved, novel_psnr  # noqa: E402

from matscan.calibrate import apply_calibration, merge_calibrations  # noqa: E402
from matscan.capture import Capture  # noqa: E402
from matscan.capture.folder import Correction  # noqa: E402
from matscan.capture.virtual import CameraModel, simulate_images  # noqa: E402
from matscan.materials.photos import photo_material  # noqa: E402
from matscan.materials.procedural import generate  # noqa: E402
from matscan.reconstruct import ReconstructConfig, reconstruct_capture  # noqa: E402
from matscan.reconstruct.selfcal import with_gains  # noqa: E402
from matscan.reconstruct.solver import rerender_error  # noqa: E402
from matscan.rig import builtin_rig  # noqa: E402

SIZE = 128


def materials() -> dict:
    main = [("paper", generate("paper", SIZE, 1)), ("brick (photo)", photo_material("brick", SIZE))]
    main += [("leather", generate("leather", SIZE, 1)), ("plastic", generate("plastic", SIZE, 1))]
    others = [(f, generate(f, SIZE, 1)) for f in ("woven_plain", "knit", "painted", "metal_brushed")]
    return {"main": main, "others": [*others, ("gravel (photo)", photo_material("gravel", SIZE))]}


def raw_rmse(result, capture: Capture, lights, gains) -> float:
    """The photos' re-rendering RMSE with every gain in the lights, no correction."""
    c = replace(capture, lights=lights) if lights is not None else capture
    c = with_gains(c, gains) if gains is not None else c
    g = c.correction.gain if c.correction is not None else torch.ones(24, 3)
    raw = replace(c, lights=c.lights.with_intensity(c.lights.intensity * g), correction=None)
    return rerender_error(result.maps, raw, list(range(24)), result.intensity_scale)


def main() -> None:
    torch.set_num_threads(2)
    args = sys.argv[1:]
    names = ("paper", "brick", "leather", "plastic")
    if args and args[0].startswith("--from="):
        names = tuple(args.pop(0).removeprefix("--from=").split(","))
    draw, specs = int(args[0]), args[1:]
    cal = json.loads((HERE / "nearcal-calibrated" / "calibrations-s128.json").read_text())
    rig, lists = builtin_rig("dome24"), materials()
    nominal = rig.light_set()
    cfg = ReconstructConfig(model="none", refine="on", solver="lm")
    selfc = replace(cfg, self_calibrate=True, self_calibrate_positions=True)
    for spec in specs:
        which, i = spec.split(":")
        name, maps = lists[which][int(i)]
        i, seed = int(i), 1000 * draw
        gains = led_gains(100 + i + seed, gradient=True)
        delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + seed)) * 2 - 1) * 5
        true = moved(nominal, delta)
        lit = true.with_intensity(true.intensity * gains)
        photos = simulate_images(maps, lit, rig.field_mm, CameraModel(read_noise=0.002), seed=i + seed)
        sat = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
        files = tuple(f"led_{k:02d}.png" for k in range(24))
        cap = Capture(rig, rig.field_mm, "srgb", photos, sat, tuple(range(24)), nominal, files)
        got = [cal[f"{k}-{SIZE}-seed{draw}-{i}"] for k in names]
        docs = [
            {
                "format": "matscan-calibration/1",
                "light_scales": {str(k): c["light_gains"][k] for k in range(24)},
                "light_positions_mm": {str(k): c["light_positions_mm"][k] for k in range(24)},
            }
            for c in got
            if c["read"]
        ]
        merged = merge_calibrations(docs, [f"calibration {k}" for k in range(len(docs))])
        given = apply_calibration(replace(cap, calibration=merged.document))
        ideal = reconstruct_capture(replace(cap, lights=true, correction=Correction(None, gains, (None,) * 24)), cfg)
        own, held = reconstruct_capture(cap, selfc), reconstruct_capture(given, cfg)
        fitted = reconstruct_capture(given, selfc)
        top = novel_psnr(ideal.maps, ideal.intensity_scale, maps, rig.field_mm)
        out = [f"{name:16s}"]
        for tag, r, c, lights, g in (
            ("ideal", ideal, replace(cap, lights=true), None, gains),
            ("own", own, cap, own.lights, own.light_gains),
            ("merged", held, given, None, None),
            ("fitted from it", fitted, given, fitted.lights, fitted.light_gains),
        ):
            below = top - novel_psnr(r.maps, r.intensity_scale, maps, rig.field_mm)
            mm = float(((lights if lights is not None else c.lights).position - true.position).norm(dim=1).mean())
            out.append(f"{tag} {below:+.2f} dB {mm:.2f} mm RMSE {raw_rmse(r, c, lights, g) * 1e3:.4f}e-3")
        print("  ".join(out), flush=True)


if __name__ == "__main__":
    main()
