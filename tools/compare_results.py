"""Compare two `matscan evaluate` results.json files row by row: did a re-run reproduce them?

Rows are matched by (material, encoding, lights, method). Prints, for every score, the
largest absolute and relative difference over the matched rows (time is left out), and
the rows only one file has. Exit status 1 when a score differs by more than --tolerance
(relative; differences under 1e-6 count as equal; default 1e-3), so this can gate a re-run.

Run: .venv/bin/python tools/compare_results.py docs/results/current/results.json /tmp/rerun/results.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

KEYS = ("material", "encoding", "lights", "method")


def load(path: Path) -> dict[tuple, dict]:
    try:
        rows = json.loads(path.read_text())["rows"]
        return {tuple(r[k] for k in KEYS): r for r in rows}
    except FileNotFoundError:
        raise SystemExit(f"{path}: no such file") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"{path}: not a matscan evaluate results.json ({type(e).__name__}: {e})") from None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--tolerance", type=float, default=1e-3)
    args = parser.parse_args()
    a, b = load(args.a), load(args.b)
    common = sorted(set(a) & set(b))
    worst: dict[str, tuple[float, float]] = {}
    for key in common:
        for score, va in a[key].items():
            vb = b[key].get(score)
            if score == "seconds" or not isinstance(va, float) or not isinstance(vb, float):
                continue
            if math.isnan(va) and math.isnan(vb):
                continue
            d = abs(va - vb)
            r = d / max(abs(va), abs(vb)) if d > 1e-6 else 0.0  # near-zero scores: absolute
            old = worst.get(score, (0.0, 0.0))
            worst[score] = (max(old[0], d), max(old[1], r))
    print(
        f"{len(common)} rows in both; {len(set(a) - set(b))} only in {args.a}; {len(set(b) - set(a))} only in {args.b}"
    )
    print("| score | largest absolute difference | largest relative difference |")
    print("|---|---:|---:|")
    for score, (d, r) in worst.items():
        print(f"| {score} | {d:.2e} | {r:.2e} |")
    bad = [s for s, (_, r) in worst.items() if r > args.tolerance]
    if bad or not common:
        print(f"differ by more than {args.tolerance:g}: {', '.join(bad) or 'no rows in common'}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
