"""Self-calibration on a dome whose LEDs are not what the rig file says.

Each material is photographed through dome24 (24 LEDs, 8-bit sRGB, read noise 0.002)
with every LED's brightness off by up to ±20% (uniform) and its colour by up to ±3% per
channel, then the gains' gradient across the dome removed and their geometric mean made
1 per channel (``without_tilt``: a gradient across the dome cannot be told from a tilted
sample without a flat target, and the overall scale stays the rig file's). Three
reconstructions (the solver alone, no networks) are compared:

* ideal: the photos divided by the true gains (a perfectly calibrated dome);
* nominal: the rig file's intensities, as a lab without calibration would run it;
* self-calibrated: ``--self-calibrate``, the gains estimated from the photos alone;
* calibrated + self-cal: ``--self-calibrate`` on the ideal capture, as when a dome
  already calibrated with a grey card is also self-calibrated (the gains it estimates
  multiply the calibration's scales).

Printed per material: the largest and mean relative error of the estimated gains, and
the PSNR (dB, sRGB, clipped) of re-renderings under 16 novel lights against the true
maps, for each reconstruction; then the means.

With ``--held-out`` the materials are 13 others, on which the estimator's constants were
not chosen: ten procedural families the list above lacks (seed 2), the photo-built grass
and the artist-style embossed coins and worn metal. ``--estimator=HOLD,SHARE`` sets
:data:`matscan.reconstruct.selfcal.ROUGHNESS_HOLD` and ``MIN_PHOTO_SHARE`` (``1,0`` is the
estimator before either existed). ``--held=off|unread|always`` sets
:data:`matscan.reconstruct.selfcal.HELD_GAINS` (whether the intensities are fitted with
the maps, every light held; runs/selfcal-held/README.md). Each row ends with the path the
self-calibration took: ``read`` (the estimate kept), ``refused`` or ``unread`` (the rig
file's intensities kept), and ``+held`` where the joint fit with the lights held gave the
gains.

Run by hand: .venv/bin/python bench/selfcal.py [SIZE] [--held-out] [--estimator=HOLD,SHARE] [--held=MODE]
(default 128)
"""

from __future__ import annotations

import math
import sys
import time

import torch

from matscan.capture import Capture
from matscan.capture.folder import Correction
from matscan.capture.virtual import CameraModel, simulate_images
from matscan.color import linear_to_srgb
from matscan.evaluate import evaluation_lights
from matscan.materials.artist import artist_material
from matscan.materials.photos import photo_material
from matscan.materials.procedural import generate
from matscan.reconstruct import ReconstructConfig, reconstruct_capture
from matscan.reconstruct import selfcal as estimator
from matscan.reconstruct.selfcal import without_tilt
from matscan.render import render_maps
from matscan.rig import builtin_rig


def led_gains(seed: int, gradient: bool = False) -> torch.Tensor:
    """±20% brightness, ±3% colour, with no gradient across the dome (without_tilt), or
    with the one the draw has (``gradient``); either way divided by their geometric mean
    per channel, the overall factor that no self-calibration can read (the albedo takes
    it), which would otherwise count against every estimate's relighting."""
    g = torch.Generator().manual_seed(seed)
    gains = (0.8 + 0.4 * torch.rand(24, 1, generator=g)) * (0.97 + 0.06 * torch.rand(24, 3, generator=g))
    if gradient:
        return gains / gains.log().mean(0).exp()
    return without_tilt(gains, builtin_rig("dome24").light_set())


def dome_capture(maps, gains: torch.Tensor, seed: int) -> Capture:
    rig = builtin_rig("dome24")
    lights = rig.light_set()
    photos = simulate_images(
        maps, lights.with_intensity(lights.intensity * gains), rig.field_mm, CameraModel(read_noise=0.002), seed=seed
    )
    top = 1 - 0.5 / 255
    return Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        (photos >= top).any(1, keepdim=True),
        tuple(range(24)),
        lights,
        tuple(f"led_{k:02d}.png" for k in range(24)),
    )


def novel_psnr(pred, scale: float, truth, field_mm) -> float:
    lights = evaluation_lights(builtin_rig("dome24"))
    with torch.no_grad():
        a = linear_to_srgb((render_maps(pred, lights, field_mm) * scale).clamp(0, 1))
        b = linear_to_srgb(render_maps(truth, lights, field_mm).clamp(0, 1))
    return 10 * math.log10(1 / float((a - b).square().mean()))


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    torch.set_num_threads(2)
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    for a in sys.argv[1:]:
        if a.startswith("--estimator="):
            hold, share = a.split("=", 1)[1].split(",")
            estimator.ROUGHNESS_HOLD, estimator.MIN_PHOTO_SHARE = float(hold), float(share)
        if a.startswith("--held="):
            estimator.HELD_GAINS = a.split("=", 1)[1]
    size = int(args[0]) if args else 128
    if "--held-out" in sys.argv:
        families = ("woven_twill", "woven_satin", "leather_embossed", "weave_heavy", "corrugated")
        families += ("metallic_print", "worn", "varnished_wood", "dark_glossy", "glossy_coat")
        materials = [(f, generate(f, size, 2)) for f in families]
        materials += [("grass (photo)", photo_material("grass", size))]
        materials += [(f"{n} (artist)", artist_material(n, size)) for n in ("embossed-coins", "worn-metal")]
    else:
        families = ("leather", "plastic", "paper", "woven_plain", "knit", "painted")
        materials = [(f, generate(f, size, 1)) for f in families]
        materials += [(f"{f} (metal)", generate(f, size, 1)) for f in ("metal_brushed",)]
        materials += [(f"{n} (photo)", photo_material(n, size)) for n in ("brick", "gravel")]
        materials += [(f"{n} (artist)", artist_material(n, size)) for n in ("foil-print", "black-leather", "lacquer")]
    print(
        f"estimator: ROUGHNESS_HOLD {estimator.ROUGHNESS_HOLD}, MIN_PHOTO_SHARE {estimator.MIN_PHOTO_SHARE}, "
        f"HELD_GAINS {estimator.HELD_GAINS}"
    )
    cfg = ReconstructConfig(model="none", refine="on")
    rows = []
    t0 = time.perf_counter()
    print(f"{'material':24s} {'gain err max':>12s} {'mean':>7s}   PSNR ideal  nominal  self-cal  cal+self-cal (dB)")
    for i, (name, maps) in enumerate(materials):
        gains = led_gains(100 + i)
        cap = dome_capture(maps, gains, seed=i)
        ideal_cap = Capture(**{**cap.__dict__, "correction": Correction(None, gains, (None,) * 24)})
        ideal = reconstruct_capture(ideal_cap, cfg)
        nominal = reconstruct_capture(cap, cfg)
        self_cfg = ReconstructConfig(model="none", refine="on", self_calibrate=True)
        selfcal = reconstruct_capture(cap, self_cfg)
        both = reconstruct_capture(ideal_cap, self_cfg)
        est = selfcal.light_gains
        rec = selfcal.self_calibration
        path = "read" if rec["updated"] else "refused" if "rejected" in rec else "unread"
        path += "+held" if "held_gains" in rec else ""
        err = (est / gains - 1).abs()
        psnr = [novel_psnr(r.maps, r.intensity_scale, maps, cap.field_mm) for r in (ideal, nominal, selfcal, both)]
        rows.append((float(err.max()), float(err.mean()), *psnr))
        print(
            f"{name:24s} {rows[-1][0]:12.4f} {rows[-1][1]:7.4f}   {psnr[0]:9.2f} {psnr[1]:8.2f} {psnr[2]:9.2f}"
            f" {psnr[3]:11.2f}  {path}"
        )
    means = [sum(r[j] for r in rows) / len(rows) for j in range(6)]
    print(
        f"{'mean':24s} {means[0]:12.4f} {means[1]:7.4f}   {means[2]:9.2f} {means[3]:8.2f} {means[4]:9.2f}"
        f" {means[5]:11.2f}"
    )
    print(f"self-calibrated − ideal: {means[4] - means[2]:+.2f} dB; nominal − ideal: {means[3] - means[2]:+.2f} dB")
    print(f"calibrated + self-cal − ideal: {means[5] - means[2]:+.2f} dB")
    print(f"{len(rows)} materials at {size}² in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
