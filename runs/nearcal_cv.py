"""Whether photos left out tell a capture's own light places from a merged calibration's
where the photos' misfit cannot (nearcal_misfit.py). For bench/nearcal.py's materials
named (``main:1`` the brick, ``held-out:0`` the twill, ``others:4`` the gravel: the list
and index, as the bench's lists share domes by index), each candidate's lights and gains
are held while the maps are fitted again ``FOLDS`` times, each time without a
``FOLDS``-th of the photos (light k in fold k mod ``FOLDS``). The candidates: the ideal
dome's, the capture's own ``--self-calibrate-positions`` from the rig file, the shipped
recipe (the four's merged calibration, fitted from there) and the same with a confirmed
calibration's places moved together (``lightpos.CALIBRATED_COMMON`` "confirmed"). Printed
per candidate: the novel-light dB below the ideal dome's fit, the lights' mean error,
the photos' misfit (``fit``), the RMSE of re-rendering the photos left out (``cv``; raw
photos, each fit's gains multiplied into its lights) and the same with each left-out
light's place and RGB gain fitted to its photo first (``refit``), all RMSE ×10⁻³. The
calibrations are those in nearcal-calibrated/calibrations-s128.json. ``python
runs/nearcal_cv.py DRAW main:1 held-out:0`` from the repository root (about 10 minutes a
material on 2 cores)."""

import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "bench"))
from nearcal import led_gains, listed, moved, novel_psnr  # noqa: E402

from matscan.calibrate import apply_calibration, merge_calibrations  # noqa: E402
from matscan.capture import Capture  # noqa: E402
from matscan.capture.folder import Correction  # noqa: E402
from matscan.capture.virtual import CameraModel, simulate_images  # noqa: E402
from matscan.mapset import MapSet  # noqa: E402
from matscan.reconstruct import ReconstructConfig, lightpos, reconstruct_capture  # noqa: E402
from matscan.reconstruct.selfcal import with_gains  # noqa: E402
from matscan.reconstruct.solver import rerender_error  # noqa: E402
from matscan.render import render, surface_points  # noqa: E402
from matscan.rig import builtin_rig  # noqa: E402

SIZE = 128
FOLDS = 4


def raw(capture: Capture, lights, gains) -> Capture:
    """The capture lit by ``lights`` (None: its own) with ``gains`` (None: its
    correction's) multiplied into their intensities and no correction."""
    c = replace(capture, lights=lights) if lights is not None else capture
    c = with_gains(c, gains) if gains is not None else c
    g = c.correction.gain if c.correction is not None else torch.ones(len(c.files), 3)
    return replace(c, lights=c.lights.with_intensity(c.lights.intensity * g), correction=None)


def refit_rmse(maps: MapSet, capture: Capture, k: int, scale: float) -> float:
    """Photo ``k``'s re-rendering RMSE once its light's position and RGB gain are fitted
    to it with ``maps`` held (L-BFGS; the LED still aimed where the rig file aims it)."""
    one = capture.lights.select([k])
    aim = torch.tensor(capture.rig.lights[capture.light_indices[k]].aim_mm, dtype=one.position.dtype)
    y, valid = capture.linear([k])[0], ~capture.saturation([k])[0]
    pts = surface_points(capture.field_mm, capture.size)
    dp = torch.zeros(1, 3, requires_grad=True)  # hundreds of mm: 0.01 moves about 1% of the light
    lg = torch.zeros(1, 3, requires_grad=True)

    def misfit() -> torch.Tensor:
        pos = one.position + 100 * dp
        axis = (aim - pos) / (aim - pos).norm(dim=1, keepdim=True)
        lit = replace(one, position=pos, axis=axis, intensity=one.intensity * lg.exp())
        img = render(maps.diffuse, maps.specular, maps.roughness, maps.normal, lit, pts, compile=False)[0] * scale
        return (img - y).square().mul(valid).sum()

    opt = torch.optim.LBFGS([dp, lg], lr=1, max_iter=40, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = misfit()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        return float(misfit() / (valid.sum() * 3)) ** 0.5


def left_out_rmse(capture: Capture, cfg: ReconstructConfig) -> tuple[float, float]:
    """Root mean square, over the folds, of each fold's left-out re-rendering RMSE: with
    the lights as the capture has them, and with each left-out light fitted to its photo
    (:func:`refit_rmse`)."""
    n, total, refit = len(capture.files), 0.0, 0.0
    for f in range(FOLDS):
        left = [k for k in range(n) if k % FOLDS == f]
        res = reconstruct_capture(capture.select([k for k in range(n) if k % FOLDS != f]), cfg)
        total += rerender_error(res.maps, capture, left, res.intensity_scale) ** 2 / FOLDS
        refit += sum(refit_rmse(res.maps, capture, k, res.intensity_scale) ** 2 for k in left) / n
    return total**0.5, refit**0.5


def main() -> None:
    torch.set_num_threads(2)
    draw, specs = int(sys.argv[1]), sys.argv[2:]
    cal = json.loads((HERE / "nearcal-calibrated" / "calibrations-s128.json").read_text())
    rig, lists = builtin_rig("dome24"), listed(SIZE)
    nominal = rig.light_set()
    cfg = ReconstructConfig(model="none", refine="on", solver="lm")
    selfc = replace(cfg, self_calibrate=True, self_calibrate_positions=True)
    for spec in specs:
        which, i = spec.split(":")
        name, make = lists[which][int(i)]
        maps = make()
        i, seed = int(i), 1000 * draw
        gains = led_gains(100 + i + seed, gradient=True)
        delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + seed)) * 2 - 1) * 5
        true = moved(nominal, delta)
        lit = true.with_intensity(true.intensity * gains)
        photos = simulate_images(maps, lit, rig.field_mm, CameraModel(read_noise=0.002), seed=i + seed)
        sat = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
        files = tuple(f"led_{k:02d}.png" for k in range(24))
        cap = Capture(rig, rig.field_mm, "srgb", photos, sat, tuple(range(24)), nominal, files)
        got = [cal[f"{k}-{SIZE}-seed{draw}-{i}"] for k in ("paper", "brick", "leather", "plastic")]
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
        own, fitted = reconstruct_capture(cap, selfc), reconstruct_capture(given, selfc)
        lightpos.CALIBRATED_COMMON = "confirmed"
        together = reconstruct_capture(given, selfc)
        lightpos.CALIBRATED_COMMON = "off"
        top = novel_psnr(ideal.maps, ideal.intensity_scale, maps, rig.field_mm)
        out = [f"{name:18s}"]
        for tag, r, c, lights, g in (
            ("ideal", ideal, replace(cap, lights=true), None, gains),
            ("own", own, cap, own.lights, own.light_gains),
            ("recipe", fitted, given, fitted.lights, fitted.light_gains),
            ("together", together, given, together.lights, together.light_gains),
        ):
            below = top - novel_psnr(r.maps, r.intensity_scale, maps, rig.field_mm)
            mm = float(((lights if lights is not None else c.lights).position - true.position).norm(dim=1).mean())
            lit_by = raw(c, lights, g)
            fit = rerender_error(r.maps, lit_by, list(range(24)), r.intensity_scale)
            cv, refit = left_out_rmse(lit_by, cfg)
            scores = f"fit {fit * 1e3:.4f} cv {cv * 1e3:.4f} refit {refit * 1e3:.4f}"
            out.append(f"{tag} {below:+.2f} dB {mm:.2f} mm {scores}")
        print("  ".join(out), flush=True)


if __name__ == "__main__":
    main()
