"""Each material's distance below its ideal dome, for lights drawn at the Cramér–Rao bound
(``bench/nearcal.py --at-bound=8``, logs in nearcal-bound/) beside the joint fit's
(``bench/nearcal.py --joint … --level-by=agreed,base --record``, logs in nearcal-base/; its
"by base" line, the fit as the defaults now turn it), per draw, and how many of the 25
each brings within 0.5 dB: which shortfalls the photos leave (the bound's own) and
which are the estimator's.
``python runs/nearcal_bound.py 1 2 0`` (the draws)."""

import re
import sys
from pathlib import Path

HERE = Path(__file__).parent
NUMBER = r"(-?\d+\.\d+)"


def at_bound(draw: int) -> dict[str, float]:
    """Each material's mean distance below its ideal over the draws of lights at the bound."""
    rows = {}
    for line in open(HERE / "nearcal-bound" / f"s128-d{draw}.log"):
        m = re.match(rf"^(\S.*?)\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}\s+\d+ of \d+\s+{NUMBER}\s+{NUMBER}\s*$", line)
        if m:
            ideal, mean = float(m.group(2)), float(m.group(3))
            rows[m.group(1).strip()] = ideal - mean
    return rows


def fitted(draw: int) -> dict[str, float]:
    """Each material's distance below its ideal for the joint fit turned level by the base plane
    (the first line where the material was not turned: its lights were not fitted)."""
    rows, cur = {}, None
    six = r"\s+".join([NUMBER] * 6)
    for path in sorted((HERE / "nearcal-base").glob(f"s128-d{draw}-*.log")):
        for line in open(path):
            m = re.match(rf"^(\S.*?)\s+{six}\s*$", line)
            if m:
                cur = m.group(1).strip().rstrip(" *")
                rows[cur] = float(m.group(4)) - float(m.group(7))
            elif line.startswith("    by base ") and cur:
                v = [float(x) for x in line.split()[2:]]
                rows[cur] = v[2] - v[5]
    return rows


draws = [int(a) for a in sys.argv[1:]] or [1, 2, 0]
bound = {d: at_bound(d) for d in draws}
fit = {d: fitted(d) for d in draws}
names = list(bound[draws[0]])
print("dB below the ideal dome, draws " + ", ".join(map(str, draws)) + ": at the bound (mean of its draws) | the fit")
for name in names:
    b = "  ".join(f"{bound[d][name]:5.2f}" for d in draws)
    f = "  ".join(f"{fit[d][name]:5.2f}" for d in draws)
    flag = " <" if any(fit[d][name] > 0.5 >= bound[d][name] for d in draws) else ""
    print(f"{name:24s} {b}  |  {f}{flag}")
for d in draws:
    nb = sum(v <= 0.5 for v in bound[d].values())
    nf = sum(fit[d][n] <= 0.5 for n in names)
    print(f"draw {d}: within 0.5 dB at the bound {nb} of {len(names)}, the fit {nf}")
print("<: the fit more than 0.5 dB below its ideal where lights at the bound were not, on average")
