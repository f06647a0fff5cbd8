"""The any-rig network against the dome24 networks on dome24, and against the solver alone
on a rig it never saw.

Materials: the 8 non-procedural evaluation sets (5 artist-style, 3 built from texture
photos; never trained on), SIZE² px over the 120 mm field, 8-bit sRGB with read noise 0.002.

* dome24, the paper's Table 4 subsets of 1, 2, 3 and 6 LEDs: the shipped dome24 networks
  and the any-rig network, each alone (no refinement);
* the 49-light RTI dome of bench/rti_dome.py (directional lights, orthographic camera; no
  such rig is in the any-rig training), 3, 6 and 12 of its lights spread evenly: the
  any-rig network alone, and the solver alone from flat maps.

Printed per rig and light count: novel-light RMSE (linear, clipped; 16 lights for dome24,
the 20 test lights for the RTI dome) against the true maps, and the normals' mean error
in degrees, averaged over the materials.

Run by hand: .venv/bin/python bench/anyrig.py WEIGHTS [SIZE]   (default size 128)
"""

from __future__ import annotations

import sys
import time

import torch

from matscan.anyrig import load, predict_capture
from matscan.capture import Capture
from matscan.capture.virtual import CameraModel, simulate_images
from matscan.evaluate import evaluation_lights
from matscan.mapset import MapSet
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.materials.photos import TINTS, photo_material
from matscan.reconstruct import ReconstructConfig, reconstruct_capture
from matscan.reconstruct.networks import predict_maps
from matscan.render import render_maps
from matscan.rig import builtin_rig
from matscan.weights import load_model

sys.path.insert(0, "bench")
from rti_dome import TEST, TRAIN, rti_rig  # noqa: E402


def capture_of(maps, rig, indices, seed) -> Capture:
    lights = rig.light_set(indices)
    photos = simulate_images(maps, lights, rig.field_mm, CameraModel(read_noise=0.002), seed=seed)
    return Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        (photos >= 1 - 0.5 / 255).any(1, keepdim=True),
        tuple(indices),
        lights,
        tuple(f"{k:02d}.png" for k in indices),
    )


def scores(pred: MapSet, truth: MapSet, lights, field) -> tuple[float, float]:
    with torch.no_grad():
        a = render_maps(pred, lights, field).clamp(0, 1)
        b = render_maps(truth, lights, field).clamp(0, 1)
    cos = (pred.normal * truth.normal).sum(0).clamp(-1, 1)
    return float((a - b).square().mean().sqrt()), float(torch.rad2deg(torch.acos(cos)).mean())


def spread(n: int, count: int) -> list[int]:
    return sorted({round((i + 0.5) * n / count - 0.5) for i in range(count)})


def main() -> None:
    torch.set_num_threads(2)
    weights = sys.argv[1]
    size = int(sys.argv[2]) if len(sys.argv) > 2 else 128
    anyrig = load(weights)
    nets, _ = load_model("default")
    materials = [artist_material(n, size) for n in ARTIST_NAMES] + [photo_material(n, size) for n in TINTS]
    dome = builtin_rig("dome24")
    rti, test = rti_rig(TRAIN), rti_rig(TEST)
    rows: dict[tuple, list[tuple[float, float]]] = {}
    t0 = time.perf_counter()
    for i, maps in enumerate(materials):
        for count in ("1", "2", "3", "6"):
            cap = capture_of(maps, dome, dome.subset(count), seed=i)
            lights = evaluation_lights(dome)
            rows.setdefault(("dome24", count, "dome24 networks"), []).append(
                scores(predict_maps(nets, cap), maps, lights, dome.field_mm)
            )
            rows.setdefault(("dome24", count, "any-rig network"), []).append(
                scores(MapSet(**predict_capture(anyrig, cap)), maps, lights, dome.field_mm)
            )
        for count in (3, 6, 12):
            cap = capture_of(maps, rti, spread(len(TRAIN), count), seed=i)
            lights = test.light_set()
            rows.setdefault(("RTI dome (unseen)", str(count), "any-rig network"), []).append(
                scores(MapSet(**predict_capture(anyrig, cap)), maps, lights, rti.field_mm)
            )
            res = reconstruct_capture(cap, ReconstructConfig(model="none", refine="on"))
            rows.setdefault(("RTI dome (unseen)", str(count), "solver alone"), []).append(
                scores(res.maps, maps, lights, rti.field_mm)
            )
    print(f"{'rig':20s} {'lights':>6s} {'method':18s} {'novel RMSE':>10s} {'normal °':>9s}")
    for (rig, count, method), vals in rows.items():
        rmse = sum(v[0] for v in vals) / len(vals)
        deg = sum(v[1] for v in vals) / len(vals)
        print(f"{rig:20s} {count:>6s} {method:18s} {rmse:10.4f} {deg:9.2f}")
    print(f"{len(materials)} materials at {size}², {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
