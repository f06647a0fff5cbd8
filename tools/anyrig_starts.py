"""Which of an any-rig network's maps costs on the real capture rti-icon.

From 3 and 6 of its photos (spread over the 54 not held out, as bench/anyrig.py takes
them), the ``lm`` solver is started from hybrids of the network's maps and flat maps
(``flat_start``) and held near the start with the flat start's strength, as
``reconstruct --anyrig`` does. Printed: the held-out PSNR of the start and of the solved
maps (18 photos, as displayed), SSIM, and the solved specular and roughness means.

Run by hand: .venv/bin/python tools/anyrig_starts.py WEIGHTS (about 2 minutes)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import torch

from matscan.anyrig import load, predict_capture
from matscan.capture import load_capture
from matscan.capture.rti import import_rti
from matscan.mapset import MapSet
from matscan.reconstruct import ReconstructConfig
from matscan.reconstruct.job import FLAT_START_PRIOR, display, held_out_positions, photo_scores
from matscan.reconstruct.solver import flat_start, solve_maps
from matscan.render import render_maps

MAPS = ("diffuse", "specular", "roughness", "normal")
HYBRIDS = {
    "flat": (),
    "network": MAPS,
    "net normal": ("normal",),
    "net diffuse": ("diffuse",),
    "net spec+rough": ("specular", "roughness"),
    "net diffuse+normal": ("diffuse", "normal"),
}


def held_out_psnr(cap, left, maps: MapSet, scale: float) -> dict[str, float]:
    return photo_scores(cap, left, lambda i: display(render_maps(maps, cap.lights.select([i]), cap.field_mm, scale)))


def main() -> None:
    torch.set_num_threads(2)
    net = load(sys.argv[1])
    with tempfile.TemporaryDirectory() as tmp:
        import_rti(Path(__file__).parents[1] / "tests" / "data" / "rti-icon", Path(tmp) / "icon")
        cap = load_capture(Path(tmp) / "icon")
    n = len(cap.files)
    left = held_out_positions(n, 18)
    rest = [i for i in range(n) if i not in left]
    for count in (3, 6):
        sub = cap.select([rest[round((j + 0.5) * len(rest) / count - 0.5)] for j in range(count)])
        flat, netm = flat_start(sub), MapSet(**predict_capture(net, sub))
        for name, keys in HYBRIDS.items():
            start = MapSet(**{k: getattr(netm if k in keys else flat, k) for k in MAPS})
            maps, _, scale = solve_maps(start, sub, ReconstructConfig().lm, FLAT_START_PRIOR)
            before, after = held_out_psnr(cap, left, start, 1.0), held_out_psnr(cap, left, maps, scale)
            print(
                f"{count} photos  {name:20s} start {before['psnr_left_out']:.2f}  "
                f"solved {after['psnr_left_out']:.2f} dB / {after['ssim_left_out']:.3f}  "
                f"specular {float(maps.specular.mean()):.3f}  roughness {float(maps.roughness.mean()):.3f}",
                flush=True,
            )
        tilt = float(torch.rad2deg(torch.acos(netm.normal[2].clamp(-1, 1))).mean())
        print(
            f"  the network's start: specular {float(netm.specular.mean()):.3f}, roughness "
            f"{float(netm.roughness.mean()):.3f}, diffuse {float(netm.diffuse.mean()):.3f} (flat maps' "
            f"{float(flat.diffuse.mean()):.3f}), normals {tilt:.2f}° "
            "from the vertical on average"
        )


if __name__ == "__main__":
    main()
