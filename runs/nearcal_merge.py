"""How far off the four's calibrations put each simulated dome's lights, alone and merged:
``calibrate --merge``'s mean (with its astray rule) and, for comparison, each light's
median of the four. From nearcal-calibrated/calibrations-s128.json (each calibration the
bench's ``--calibration-cache`` kept, by material, draw and dome index: its places, gains
and whether its intensities were read) and the domes' true places, drawn as
bench/nearcal.py draws them. ``python runs/nearcal_merge.py`` from the repository root."""

import json
import statistics
import sys
from pathlib import Path

import torch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "bench"))
from nearcal import moved  # noqa: E402

from matscan.calibrate import merge_calibrations  # noqa: E402
from matscan.rig import builtin_rig  # noqa: E402

FOUR = ("paper", "brick", "leather", "plastic")


def error(places: torch.Tensor, true: torch.Tensor) -> float:
    """The lights' mean distance from their true places (mm)."""
    return float((places.to(true.dtype) - true).norm(dim=1).mean())


def main() -> None:
    cal = json.loads((HERE / "nearcal-calibrated" / "calibrations-s128.json").read_text())
    nominal = builtin_rig("dome24").light_set()
    means, medians = [], []
    print("draw dome  each of the four's mean error (mm; - unread)  merged mean  median")
    for draw in (1, 2, 0):
        for i in range(13):
            got = [cal.get(f"{k}-128-seed{draw}-{i}") for k in FOUR]
            if None in got:
                continue
            delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + 1000 * draw)) * 2 - 1) * 5
            true = moved(nominal, delta).position

            read = [torch.tensor(c["light_positions_mm"], dtype=true.dtype) for c in got if c["read"]]
            docs = [
                {"format": "matscan-calibration/1", "light_positions_mm": {str(k): p[k].tolist() for k in range(24)}}
                for p in read
            ]
            merged = merge_calibrations(docs, [f"calibration {k}" for k in range(len(docs))]).document
            mean = torch.tensor([merged["light_positions_mm"][str(k)] for k in range(24)], dtype=true.dtype)
            median = torch.stack(read).quantile(0.5, dim=0)  # the middle two's mean where four
            each = [f"{error(torch.tensor(c['light_positions_mm']), true):5.2f}" if c["read"] else "    -" for c in got]
            means.append(error(mean, true))
            medians.append(error(median, true))
            print(f"{draw:4d} {i:4d}  {' '.join(each)}{'':22s}{means[-1]:5.2f}  {medians[-1]:6.2f}")
    print(
        f"{len(means)} domes: merged mean {statistics.mean(means):.2f} mm on average "
        f"({min(means):.2f}-{max(means):.2f}), median {statistics.mean(medians):.2f} "
        f"({min(medians):.2f}-{max(medians):.2f})"
    )


if __name__ == "__main__":
    main()
