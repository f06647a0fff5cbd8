"""Why the joint fit misplaces the lights of the unread materials: the experiments of docs/rti-record.md's
"The unread three's bias: what it is not" (run from the repository's root, at the commit that
added this file, whose lightpos.py has the flags ADJUSTED, CENSORED and PLACE_SPREAD_MM).

    python runs/nearcal-unread/unread.py clamp NAME INDEX FAMILY MODES   # from the truth, float photos
    python runs/nearcal-unread/unread.py truth NAME INDEX FAMILY [adjusted]  # from the truth, 8-bit photos
    python runs/nearcal-unread/unread.py basins NAME INDEX FAMILY        # the far end and the truth, one noise model
    python runs/nearcal-unread/unread.py prior NAME INDEX FAMILY S,S...  # placed from the rig file, held gains

NAME, INDEX, FAMILY as bench/nearcal.py lists and generates it (knit 1 1, metal_brushed 3 1,
paper 0 1, woven_twill 0 2), on draw 1 (``--seed=1``). MODES: clamped, unclamped, censored
(comma-separated): the camera's noise on float photos, clipped at 0 or not, and clipped with
the clipped values censored in the fit (``lightpos.CENSORED``).
"""

import sys
from dataclasses import replace
from pathlib import Path

import torch

what, name, index, family = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
extra = sys.argv[5] if len(sys.argv) > 5 else ""
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
sys.argv = sys.argv[:1] + ["--drawn-gradient"]  # what bench/nearcal.py reads on import
import nearcal as nc  # noqa: E402

from matscan.capture import Capture  # noqa: E402
from matscan.capture.virtual import CameraModel, simulate_images  # noqa: E402
from matscan.materials.procedural import generate  # noqa: E402
from matscan.reconstruct import ReconstructConfig, lightpos, reconstruct_capture  # noqa: E402
from matscan.reconstruct.selfcal import estimate_gains, with_gains  # noqa: E402
from matscan.render import render_maps  # noqa: E402

if not hasattr(lightpos, "CENSORED"):  # removed after these runs: set here, the flags would do nothing
    raise SystemExit("unread.py: run it at 87a45d7, whose lightpos.py has ADJUSTED and CENSORED (README.md)")
torch.set_num_threads(2)
RIG = nc.builtin_rig("dome24")
NOMINAL = RIG.light_set()
FILES = tuple(f"led_{k:02d}.png" for k in range(24))
DRAW = 1000  # draw 1
maps = generate(name, 128, family)
gains = nc.led_gains(100 + index + DRAW, gradient=True)
delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + index + DRAW)) * 2 - 1) * 5
true = nc.moved(NOMINAL, delta)
lit = true.with_intensity(true.intensity * gains)
cfg = ReconstructConfig(model="none", refine="on", solver="lm")


def camera_photos(lights):
    """bench/nearcal.py's photos (8-bit sRGB, the camera's noise) in a capture of ``lights``."""
    photos = simulate_images(maps, lit, RIG.field_mm, CameraModel(read_noise=0.002), seed=index + DRAW)
    saturated = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
    return Capture(RIG, RIG.field_mm, "srgb", photos, saturated, tuple(range(24)), lights, FILES)


def from_truth(cap: Capture, label: str) -> None:
    """The joint fit started at the true lights, gains and maps, 30 steps, as --from-truth runs it."""
    pos, _, rec = lightpos.fit_positions(cap, maps, gains, iterations=30, bias_pairs=0)
    err = (pos - true.position).norm(dim=1)
    print(f"{name} {label}: {float(err.mean()):.2f} mm mean, {float(err.max()):.2f} max", flush=True)


if what == "clamp":
    x = render_maps(maps, lit, RIG.field_mm)
    z = torch.randn(x.shape, generator=torch.Generator().manual_seed(index + DRAW))
    noisy = x + torch.sqrt(x.clamp_min(0) / 20000.0 + 0.002**2) * z  # the camera's noise, as CameraModel's
    print(f"{name}: {float((x < 0.004).double().mean()):.3f} of the values within 2 read-noise deviations of 0")
    for mode in extra.split(","):
        lightpos.CENSORED = mode == "censored"
        photos = noisy.clamp(max=1) if mode == "unclamped" else noisy.clamp(0, 1)
        saturated = (photos >= 1).any(1, keepdim=True)
        from_truth(Capture(RIG, RIG.field_mm, "linear", photos, saturated, tuple(range(24)), true, FILES), mode)
elif what == "truth":
    for on in (False, True) if extra == "adjusted" else (False,):
        lightpos.ADJUSTED = on
        from_truth(camera_photos(true), "adjusted" if on else "as it is")
elif what == "basins":
    cap = camera_photos(NOMINAL)
    g1, record = estimate_gains(cap, cfg)
    level = record["convention"] == "level sample"
    solve, calls = lightpos._solve, []

    def watched(*args, **kwargs):
        calls.append((args, solve(*args, **kwargs)))
        return calls[-1][1]

    lightpos._solve = watched
    lightpos.estimate_positions(lightpos._lit_from(cap, true.position), gains, cfg, level=level)
    lightpos._solve = solve
    (photos, th_start, lg), first = calls[0][0][:3], calls[0][1]
    end = min((s for _, s in calls), key=lambda s: s.cost)
    off = float((end.pos - true.position.double()).norm(dim=1).mean())
    print(f"{name}: the joint fit from the true places (the solver's maps, true gains) ends {off:.2f} mm off")
    held = replace(photos, near=torch.zeros_like(photos.near))
    th_end = th_start.clone()
    th_end[:, first.used] = end.th
    starts = {
        "the truth, from the solver's maps": (true.position.double(), th_start, lg),
        "the truth, from the true maps": (true.position.double(), lightpos._numbers(maps), gains.double().log()),
        "its end, from the solver's maps": (end.pos, th_start, end.lg),
        "its end, from its own maps": (end.pos, th_end, end.lg),
    }
    for label, (pos, th, lg0) in starts.items():
        placed = replace(held, lights=replace(held.lights, position=pos))
        s = solve(placed, th, lg0, 30, fixed=(first.noise, first.used), shared_f0=lightpos.SHARED_F0)
        print(f"{name}: lights held at {label}: misfit {s.first:.6f} -> {s.cost:.6f} per value", flush=True)
elif what == "prior":
    cap = camera_photos(NOMINAL)
    g1, record = estimate_gains(cap, cfg)
    level = record["convention"] == "level sample"
    held, _ = lightpos.estimate_held_gains(cap, g1, cfg, level=level)
    fit = reconstruct_capture(with_gains(cap, held), cfg)
    print(f"{name}: places held, relit {nc.novel_psnr(fit.maps, fit.intensity_scale, maps, RIG.field_mm):.2f} dB")
    for spread in (float(v) for v in extra.split(",")):
        lightpos.PLACE_SPREAD_MM = spread
        lights, g2, _, _ = lightpos.estimate_positions(cap, held, cfg, level=level)
        fit = reconstruct_capture(with_gains(replace(cap, lights=lights), g2), cfg)
        err = (lights.position - true.position).norm(dim=1)
        psnr = nc.novel_psnr(fit.maps, fit.intensity_scale, maps, RIG.field_mm)
        print(f"{name}: placed, prior {spread} mm: {float(err.mean()):.2f} mm mean, relit {psnr:.2f} dB", flush=True)
