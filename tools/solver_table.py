"""Markdown table comparing methods across results.json files of `matscan evaluate`.

    tools/solver_table.py ENCODING LABEL=FILE:METHOD [LABEL=FILE:METHOD ...]

Each column group is one method's rows from one results.json (e.g. the first-order
refinement from docs/results/current and the second-order one from docs/results/lm),
averaged over materials for each light count, for one capture encoding (srgb8).
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict

METRICS = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "normal_degrees", "novel_rmse")


def main() -> None:
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    encoding = sys.argv[1]
    print("| method | lights | " + " | ".join(METRICS) + " |")
    print("|---|---:|" + "---:|" * len(METRICS))
    for spec in sys.argv[2:]:
        label, rest = spec.split("=", 1)
        path, method = rest.rsplit(":", 1)
        rows = json.load(open(path))["rows"]
        groups: dict[str, list[dict]] = defaultdict(list)
        for r in rows:
            if r["method"] == method and r["encoding"] == encoding:
                groups[r["lights"]].append(r)
        for lights in sorted(groups, key=int):
            g = groups[lights]
            # a method without maps (hsh) has re-rendering scores only
            means = [sum(r[m] for r in g) / len(g) if m in g[0] else None for m in METRICS]
            cells = " | ".join("–" if v is None else f"{v:.4f}" for v in means)
            print(f"| {label} | {lights} | {cells} |")


if __name__ == "__main__":
    main()
