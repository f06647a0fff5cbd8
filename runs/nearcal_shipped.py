"""What ``reconstruct --self-calibrate-positions`` gives as shipped on bench/nearcal.py's 25
materials, per draw, from the logs already made: each read material's line "by base" in
nearcal-base/ (the defaults' fit, turned level by the base plane), and for the three whose
intensities are unread the line "held gains" in nearcal-held/ (the gains fitted with the
lights held at the rig file's places). Prints the mean novel-light PSNR of the ideal dome,
the rig file, the self-calibrated intensities alone and the shipped fit, how far the
shipped fit is below the ideal (mean, median), how many come within 0.5 dB, the read
materials' mean light error, and each material short by more than 0.5 dB.
``python runs/nearcal_shipped.py [0 1 2]``."""

import re
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).parent
ROW = re.compile(r"^(\S.*?)\s+" + r"\s+".join([r"(-?\d+\.\d+)"] * 6) + r"\s*$")


def rows(paths, by):
    """{material: {"mm", "ideal", "nominal", "gains", "final"}} of the logs, the lines ``by`` replacing the first."""
    out, cur = {}, None
    for p in paths:
        for line in open(p):
            m = ROW.match(line)
            if m and not line.startswith(" "):
                name = m.group(1).strip()
                cur = name.rstrip(" *")
                v = [float(x) for x in m.groups()[1:]]
                out[cur] = dict(mm=v[0], ideal=v[2], nominal=v[3], gains=v[4], final=v[5], read=not name.endswith("*"))
            elif cur and line.startswith(f"    {by} "):
                v = [float(x) for x in line[len(by) + 4 :].split()]
                out[cur].update(mm=v[0], final=v[5])
    return out


def shipped(draw: str) -> dict:
    """{material: row} as shipped on this draw: ``rows`` of nearcal-base/, the unread three's
    "final" from nearcal-held/'s held gains."""
    base = rows(sorted(HERE.glob(f"nearcal-base/s128-d{draw}-*.log")), "by base")
    held = rows(sorted(HERE.glob(f"nearcal-held/s128-d{draw}-*.log")), "held gains")
    for k, r in base.items():
        if not r["read"]:  # the unread three: as shipped, the held gains
            r["final"] = held[k]["final"]
    return base


def main() -> None:
    for draw in sys.argv[1:] or ["1", "2", "0"]:
        base = shipped(draw)
        mean = {k: statistics.mean(r[k] for r in base.values()) for k in ("ideal", "nominal", "gains", "final")}
        below = {k: r["ideal"] - r["final"] for k, r in base.items()}
        read = [r["mm"] for r in base.values() if r["read"]]
        print(
            f"draw {draw}: {len(base)} materials, mean PSNR ideal {mean['ideal']:.2f}, rig file {mean['nominal']:.2f}, "
            f"intensities alone {mean['gains']:.2f}, shipped {mean['final']:.2f} dB; below the ideal "
            f"{statistics.mean(below.values()):.2f} mean, {statistics.median(below.values()):.2f} median; "
            f"{sum(v <= 0.5 for v in below.values())} within 0.5 dB; {len(read)} read, lights "
            f"{statistics.mean(read):.2f} mm off on average"
        )
        for k, v in sorted(below.items(), key=lambda kv: -kv[1]):
            if v > 0.5:
                print(f"   {k:24s} {v:.2f} dB below{'' if base[k]['read'] else ' (intensities unread)'}")


if __name__ == "__main__":
    main()
