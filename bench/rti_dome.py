"""A simulated RTI dome: matscan's solver against the field's HSH fit, on materials unlike
the training set.

The dome: 49 directional lights (12 on each ring at 10°, 30°, 50° and 70° elevation, one
at the zenith) and an orthographic camera, as RTI domes are described by their .lp
files; 20 test lights between them (5 on each ring at 20°, 40°, 60°, 80°, azimuths
offset). Each material (the artist-style sets and the sets built from texture photos:
``matscan evaluate`` "photos" and "artist") is photographed under the 49 lights (8-bit
sRGB, read noise 0.002) and reconstructed by the solver, from flat maps (the dome24
networks take dome24's slots) and from the shipped any-rig network's maps; HSH (order 2,
nine coefficients per pixel and channel) is fitted to the same photos. All three then
predict the 20 test photos, which none saw.

Printed per material: PSNR (dB) and SSIM of the test photos (sRGB, clipped) for HSH and
the solver, the solver's normal error (mean angle, degrees) and its map errors (RMSE of
diffuse, specular, roughness); then the same for the solver started from the shipped
any-rig network's maps (``reconstruct --anyrig default``); then the means. With
``--dropped`` the solver drops saturated values instead of reading them as "at least the
clip" (``SolverConfig.censored``, off), as it did before 2026-12-01.

Run by hand: .venv/bin/python bench/rti_dome.py [SIZE] [--dropped]   (default 128)
"""

from __future__ import annotations

import math
import sys
import time

import torch

from matscan.capture import Capture
from matscan.capture.virtual import CameraModel, simulate_images
from matscan.color import linear_to_srgb
from matscan.hsh import fit_hsh, relight_hsh
from matscan.losses import ssim
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.materials.photos import TINTS, photo_material
from matscan.reconstruct import ReconstructConfig, reconstruct_capture
from matscan.reconstruct.lm import SolverConfig
from matscan.render import render_maps
from matscan.rig import Camera, Light, Rig
from matscan.weights import load_anyrig


def ring(elevations, per_ring: int, offset_deg: float = 0.0) -> list[tuple[float, float, float]]:
    out = []
    for e in elevations:
        for k in range(per_ring):
            a = math.radians(offset_deg + 360.0 * k / per_ring)
            el = math.radians(e)
            out.append((math.cos(el) * math.cos(a), math.cos(el) * math.sin(a), math.sin(el)))
    return out


TRAIN = ring((10, 30, 50, 70), 12) + [(0.0, 0.0, 1.0)]
TEST = ring((20, 40, 60, 80), 5, offset_deg=17.0)


def rti_rig(directions) -> Rig:
    return Rig(
        "rti49",
        1000.0,
        Camera(direction=(0.0, 0.0, 1.0)),
        (120.0, 120.0),
        tuple(Light(direction=d) for d in directions),
    )


def photos_of(maps, rig: Rig, seed: int) -> torch.Tensor:
    return simulate_images(maps, rig.light_set(), rig.field_mm, CameraModel(read_noise=0.002), seed=seed)


def scores(pred: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    a, b = linear_to_srgb(pred.clamp(0, 1)), linear_to_srgb(truth.clamp(0, 1))
    return 10 * math.log10(1 / float((a - b).square().mean())), float(ssim(a, b))


def _line(name: str, r: list[float]) -> str:
    def solver(a: list[float]) -> str:
        return f"{a[0]:6.2f} {a[1]:6.3f} {a[2]:9.2f} {a[3]:8.4f} {a[4]:9.4f} {a[5]:6.3f}"

    return f"{name:24s} {r[0]:9.2f} {r[1]:6.3f} {solver(r[2:8])}   {solver(r[8:14])}"


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    torch.set_num_threads(2)
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    size = int(args[0]) if args else 128
    cfg = ReconstructConfig(model="none", refine="on", lm=SolverConfig(censored="--dropped" not in sys.argv))
    materials = [(f"{n} (artist)", artist_material(n, size)) for n in ARTIST_NAMES]
    materials += [(f"{n} (photo)", photo_material(n, size)) for n in TINTS]
    train, test = rti_rig(TRAIN), rti_rig(TEST)
    rows = []
    t0 = time.perf_counter()
    anyrig = load_anyrig("default")
    solver = f"{'PSNR':>6s} {'SSIM':>6s} {'normal °':>9s} {'diffuse':>8s} {'specular':>9s} {'rough':>6s}"
    print(f"{'':24s} {'HSH':>16s} {'solver from flat maps':>49s}   {'solver from the any-rig network':>49s}")
    print(f"{'material':24s} {'PSNR':>9s} {'SSIM':>6s} {solver}   {solver}")
    for i, (name, maps) in enumerate(materials):
        photos = photos_of(maps, train, seed=i)
        cap = Capture(
            train,
            train.field_mm,
            "srgb",
            photos,
            (photos >= 1 - 0.5 / 255).any(1, keepdim=True),
            tuple(range(len(TRAIN))),
            train.light_set(),
            tuple(f"{k:02d}.png" for k in range(len(TRAIN))),
        )
        truth = render_maps(maps, test.light_set(), test.field_mm)
        coef = fit_hsh(linear_to_srgb(photos.clamp(0, 1)), torch.tensor(TRAIN))
        hsh = relight_hsh(coef, torch.tensor(TEST))
        hsh_psnr = 10 * math.log10(1 / float((hsh - linear_to_srgb(truth.clamp(0, 1))).square().mean()))
        hsh_ssim = float(ssim(hsh, linear_to_srgb(truth.clamp(0, 1))))
        row: list[float] = [hsh_psnr, hsh_ssim]
        for start in (None, anyrig):
            res = reconstruct_capture(cap, cfg, anyrig=start)
            with torch.no_grad():
                pred = render_maps(res.maps, test.light_set(), test.field_mm) * res.intensity_scale
            psnr, s = scores(pred, truth)
            cos = (res.maps.normal * maps.normal).sum(0).clamp(-1, 1)
            normal_deg = float(torch.rad2deg(torch.acos(cos)).mean())
            errs = [
                float((getattr(res.maps, m) - getattr(maps, m)).square().mean().sqrt())
                for m in ("diffuse", "specular", "roughness")
            ]
            row += [psnr, s, normal_deg, *errs]
        rows.append(row)
        print(_line(name, row))
    print(_line("mean", [sum(r[j] for r in rows) / len(rows) for j in range(len(rows[0]))]))
    print(
        f"{len(rows)} materials at {size}², {len(TRAIN)} lights, {len(TEST)} test lights, "
        f"{time.perf_counter() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
