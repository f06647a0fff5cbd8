"""The third start's rules (docs/rti-record.md) read from bench/nearcal.py's logs in nearcal-weak/
and nearcal-same/: per run, the mean final PSNR (a), the count within 0.5 dB of the ideal
dome (c) and the fitted materials' mean light error (d) without → with the third start
(the "without weak" or "as default" line where another end was kept, else the first line), then each material
whose end changed, with the share by which its third end's misfit was lower; over two
runs or more, (b): each material's distance below its ideal averaged over the runs,
without → with, those more than 0.1 dB farther marked.
``python runs/nearcal_rule.py nearcal-same/s256-d1 [nearcal-same/s128-d1 ...] [--margin=M]``
(each run the logs whose names start so): with ``--margin`` the third end counts as kept
only where that share is above M (``lightpos.WEAK_MARGIN``). With ``--by=NAME`` (runs of
``--level-by=agreed,NAME``, nearcal-base/) "with" is each material's line "by NAME", the
same fit turned level so, and "without" its first line. With ``--versus=DIR`` (and
``--by=NAME``) "without" is instead each material's line "by NAME" in DIR's logs of the same
draw (nearcal-base/: the default as it stood) and "with" the run's first line:
``python runs/nearcal_rule.py --versus=nearcal-base --by=base nearcal-mean/s128-d1``."""

import glob
import json
import re
import sys
from pathlib import Path

HERE = Path(__file__).parent


def parse(paths, by=None):
    rows = {}
    cur = None
    for p in paths:
        for line in open(p):
            m = re.match(
                r"^(\S.*?)\s+(-?\d+\.\d+)\s+(-?\d+\.\d+)\s+(-?\d+\.\d+)\s+(-?\d+\.\d+)\s+(-?\d+\.\d+)\s+(-?\d+\.\d+)\s*$",
                line,
            )
            if m and not line.startswith(" "):
                name = m.group(1).strip()
                mean, mx, ideal, nom, gains, fin = map(float, m.groups()[1:])
                cur = name
                rows[name] = dict(mm=mean, ideal=ideal, final=fin, wmm=mean, wfinal=fin, fitted=not name.endswith("*"))
            elif line.lstrip().startswith("{") and cur:
                rec = json.loads(line.strip().split("}; the positions")[0] + "}")
                ends = rec["misfit_per_value"].get("ends", {})
                others = [v for k, v in ends.items() if k != "weak"]
                if "weak" in ends:
                    rows[cur]["margin"] = (min(others) - ends["weak"]) / min(others)
                    rows[cur]["share"] = rec.get("shared_f0", {}).get("share")
            elif line.startswith(("    without weak", "    as default")) and cur:
                v = [float(x) for x in line.split()[2:]]
                rows[cur]["wmm"], rows[cur]["wfinal"] = v[0], v[5]
            elif by and line.startswith(f"    by {by} ") and cur:  # the same fit turned level by BY: "with"
                v = [float(x) for x in line.split()[2:]]
                rows[cur]["mm"], rows[cur]["final"] = v[0], v[5]
    return rows


margin = next((float(a.split("=")[1]) for a in sys.argv[1:] if a.startswith("--margin=")), None)
by = next((a.split("=")[1] for a in sys.argv[1:] if a.startswith("--by=")), None)
versus = next((a.split("=")[1] for a in sys.argv[1:] if a.startswith("--versus=")), None)
runs = [a for a in sys.argv[1:] if not a.startswith("--")]
below: dict[str, list[tuple[float, float]]] = {}  # each material's (without, with) below its ideal, per run
for run in runs:
    paths = sorted(glob.glob(f"{HERE}/{run}*.log"))
    if versus:  # "without": the same draw's lines "by BY" in the logs of DIR
        rows = parse(paths)
        base = parse(sorted(glob.glob(f"{HERE}/{versus}/{Path(run).name}*.log")), by)
        for k, r in rows.items():
            r["wmm"], r["wfinal"] = base[k]["mm"], base[k]["final"]
    else:
        rows = parse(paths, by)
    for k, r in rows.items():  # the weak end kept only above the margin: else the fit without it
        if margin is not None and "margin" in r and r["margin"] <= margin:
            r["mm"], r["final"] = r["wmm"], r["wfinal"]
        below.setdefault(k, []).append((r["ideal"] - r["wfinal"], r["ideal"] - r["final"]))
    n = len(rows)
    a_with = sum(r["final"] for r in rows.values()) / n
    a_wo = sum(r["wfinal"] for r in rows.values()) / n
    c_with = sum(r["ideal"] - r["final"] <= 0.5 for r in rows.values())
    c_wo = sum(r["ideal"] - r["wfinal"] <= 0.5 for r in rows.values())
    fit = [r for r in rows.values() if r["fitted"]]
    d_with = sum(r["mm"] for r in fit) / len(fit)
    d_wo = sum(r["wmm"] for r in fit) / len(fit)
    print(
        f"{run}: {n} materials, (a) {a_wo:.3f} -> {a_with:.3f} ({a_with - a_wo:+.3f}) (c) {c_wo} -> {c_with} "
        f"(d) {len(fit)} fitted {d_wo:.3f} -> {d_with:.3f} mm"
    )
    for k, r in rows.items():
        if r["wfinal"] != r["final"] or r["wmm"] != r["mm"]:
            print(
                f"   {k:16s} below ideal {r['ideal'] - r['wfinal']:.2f} -> {r['ideal'] - r['final']:.2f}, "
                f"{r['wmm']:.2f} -> {r['mm']:.2f} mm"
                + ("" if by else f", margin {100 * r.get('margin', float('nan')):.2f}%, share {r.get('share')}")
            )
if len(runs) > 1:
    print(f"(b) below the ideal, averaged over the runs ({len(runs)}), without -> with:")
    for k, v in below.items():
        wo, w = (sum(x[i] for x in v) / len(v) for i in (0, 1))
        if w != wo:
            print(f"   {k:16s} {wo:.3f} -> {w:.3f} ({w - wo:+.3f}){' FAILS' if w - wo > 0.1 else ''} over {len(v)}")
