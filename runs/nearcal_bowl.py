"""Whether the fitted maps' bowl measures the dome's scale: for bench/nearcal.py's
materials of one draw (its domes, ±5 mm and ±20% with their gradient, its photos), the
``lm`` solver's maps fitted at the true lights (true gains) moved radially by d mm (each
light along its direction from the sample's centre: the dome's scale), and their bowl: the
normals' slopes (median removed) regressed on the pixel's place, x·sx + y·sy over x² + y²,
in mm of dome radius (× 112.5²; a dome d mm too large bends the light directions as a
bowl of d would); ``trimmed``, the same over pixels whose slopes lie within their 90th
percentile; and the maps' novel-light PSNR. A flat sample's truth has no bowl, so if the
fitted maps' bowl at d = 0 were the truth's, holding it there would fix the scale.
``python runs/nearcal_bowl.py DRAW [main|held-out|others …] [--shifts=-1,0,1]`` from the
repository root (a second a fit at 128² on 2 cores)."""

import sys
from pathlib import Path

import torch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "bench"))
from nearcal import led_gains, listed, moved, novel_psnr  # noqa: E402

from matscan.capture import Capture  # noqa: E402
from matscan.capture.virtual import CameraModel, simulate_images  # noqa: E402
from matscan.mapset import MapSet  # noqa: E402
from matscan.reconstruct import ReconstructConfig, lightpos, reconstruct_capture  # noqa: E402
from matscan.reconstruct.selfcal import with_gains  # noqa: E402
from matscan.render import surface_points  # noqa: E402
from matscan.rig import builtin_rig  # noqa: E402

SIZE = 128
RADIUS_MM = 112.5  # dome24's


def bowl(maps: MapSet, pts: torch.Tensor, trim: float | None = None) -> float:
    """The maps' slopes regressed on the pixel's place (x, y; mm), in mm of dome radius."""
    n = maps.normal.reshape(3, -1).double()
    sx, sy = n[0] / n[2], n[1] / n[2]
    sx, sy = sx - sx.median(), sy - sy.median()
    keep = torch.ones_like(sx, dtype=torch.bool)
    if trim is not None:
        limit = torch.quantile(torch.cat([sx.abs(), sy.abs()]), trim)
        keep = (sx.abs() <= limit) & (sy.abs() <= limit)
    x, y = pts[:, 0], pts[:, 1]
    return float((x * sx + y * sy)[keep].sum() / (x * x + y * y)[keep].sum()) * RADIUS_MM**2


def main() -> None:
    torch.set_num_threads(2)
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    shifts = [-1.0, 0.0, 1.0]
    for a in sys.argv[1:]:
        if a.startswith("--shifts="):
            shifts = [float(v) for v in a.removeprefix("--shifts=").split(",")]
    draw, lists = 1000 * int(args[0]), args[1:] or ["main", "held-out", "others"]
    rig = builtin_rig("dome24")
    nominal = rig.light_set()
    cfg = ReconstructConfig(model="none", refine="on", solver="lm")
    pts = surface_points(rig.field_mm, (SIZE, SIZE), dtype=torch.float64).reshape(-1, 3)
    files = tuple(f"led_{k:02d}.png" for k in range(24))
    print(f"draw {draw // 1000}: bowl (mm of dome radius), trimmed, novel-light PSNR (dB), at the true dome moved d mm")
    for lst in lists:
        for i, (name, make) in enumerate(listed(SIZE)[lst]):
            maps = make()
            gains = led_gains(100 + i + draw, gradient=True)  # as bench/nearcal.py --drawn-gradient
            delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + draw)) * 2 - 1) * 5
            true = moved(nominal, delta)
            lit = true.with_intensity(true.intensity * gains)
            photos = simulate_images(maps, lit, rig.field_mm, CameraModel(read_noise=0.002), seed=i + draw)
            saturated = (photos >= 1 - 0.5 / 255).any(1, keepdim=True)
            cap = Capture(rig, rig.field_mm, "srgb", photos, saturated, tuple(range(24)), nominal, files)
            out = true.position / true.position.norm(dim=1, keepdim=True)
            cells = []
            for d in shifts:
                fit = reconstruct_capture(with_gains(lightpos._lit_from(cap, true.position + d * out), gains), cfg)
                psnr = novel_psnr(fit.maps, fit.intensity_scale, maps, rig.field_mm)
                cells.append(f"{d:+.1f}: {bowl(fit.maps, pts):+.2f} {bowl(fit.maps, pts, 0.9):+.2f} {psnr:.2f}")
            truth = f"{bowl(maps, pts):+.2f} {bowl(maps, pts, 0.9):+.2f}"
            print(f"{name:24s} truth {truth}  |  " + "  |  ".join(cells), flush=True)


if __name__ == "__main__":
    main()
