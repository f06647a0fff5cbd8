"""A dome calibrated once, then each capture fitted from there (``reconstruct --calibration
dome.json --self-calibrate-positions``), on bench/nearcal.py's materials, from the logs in
nearcal-calibrated/: ``recipe-s128-dD-*.log`` (``--calibrated-on=paper,brick,leather,plastic
--then-fit``), a material's line in ``recipe-kept-s128-dD-*.log`` (run again once a
calibration's refused scales were kept) replacing its line there. Prints, per draw, how far below the ideal
dome the four's merged calibration alone leaves the materials, how far the fit from there
does, and how far their own fits as shipped do (runs/nearcal_shipped.py): mean and how many
within 0.5 dB; then each material. ``python runs/nearcal_calibrated.py [1 2]``."""

import re
import statistics
import sys
from pathlib import Path

from nearcal_shipped import shipped

HERE = Path(__file__).parent
NUMBER = r"(-?\d+\.\d+)"
ROW = re.compile(
    r"^(\S.*?)\s+" + r"\s+".join([NUMBER] * 5) + r"\s+then fitted\s+" + NUMBER + r" mm\s+" + NUMBER + r"\s+"
    r"(-?\d+\.\d+)( \((?:held|kept)\))?( refused)?"
)


def recipe(draw: str) -> dict:
    """{material: {"merged", "fitted", "mm", "how"}} (dB below the ideal; the fit's light error)."""
    out = {}
    logs = [sorted(HERE.glob(f"nearcal-calibrated/{k}-s128-d{draw}-*.log")) for k in ("recipe", "recipe-kept")]
    for p in logs[0] + logs[1]:
        for line in open(p):
            if m := ROW.match(line):
                how = ((m.group(10) or " fitted").strip(" ()") + (m.group(11) or "")).strip()
                r = dict(merged=float(m.group(6)), fitted=float(m.group(9)), mm=float(m.group(7)), how=how)
                out[m.group(1).strip()] = r
    return out


def main() -> None:
    for draw in sys.argv[1:] or ["1", "2"]:
        got, own = recipe(draw), shipped(draw)
        if not got:
            continue
        ship = {k: own[k]["ideal"] - own[k]["final"] for k in got}
        cols = {"merged alone": [r["merged"] for r in got.values()], "then fitted": [r["fitted"] for r in got.values()]}
        cols["own fit, shipped"] = list(ship.values())
        print(f"draw {draw}: {len(got)} materials, dB below the ideal dome (mean; within 0.5 dB):")
        for k, v in cols.items():
            print(f"   {k:18s} {statistics.mean(v):6.2f}   {sum(x <= 0.5 for x in v)} of {len(v)}")
        for k, r in got.items():
            print(
                f"   {k:24s} merged {r['merged']:5.2f}  fitted {r['fitted']:5.2f} ({r['how']}, {r['mm']:.2f} mm)  "
                f"own {ship[k]:5.2f}"
            )


if __name__ == "__main__":
    main()
