"""How far off the four's calibrations put each simulated dome's lights, alone and merged:
``calibrate --merge``'s mean (with its astray rule), for comparison each light's median
of the four, and the weighted merge (``calibrate.MERGE_WEIGHTED``); each calibration's
mean radial shift in brackets (the dome's scale: + too far out), and each merge's error
once its own shift and scale are fitted out against the truth (what a fit of those four
numbers from a capture's photos could at best remove: ``lightpos.CALIBRATED_COMMON``).
From nearcal-calibrated/calibrations-s128.json (each calibration the bench's
``--calibration-cache`` kept, by material, draw and dome index: its places, gains and
whether its intensities were read) and the domes' true places, drawn as
bench/nearcal.py draws them. ``python runs/nearcal_merge.py`` from the repository root;
``--from-cache=DIR`` first adds to the file every calibration in the bench's cache DIR;
``--subsets`` instead prints every subset of the four merged; ``--with-own`` instead
compares, for each of the four on each dome, its own places, the merge of the other
three, and the mean of the two (a capture's own fit averaged with a merge it is not in);
``--to-cache=DIR`` writes
the file's calibrations to DIR as that cache, so that the bench reuses them on a new
machine."""

import importlib
import itertools
import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import torch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "bench"))
from nearcal import moved  # noqa: E402

from matscan.rig import builtin_rig  # noqa: E402

calibrate = importlib.import_module("matscan.calibrate")  # the package's calibrate is the function
FOUR = ("paper", "brick", "leather", "plastic")


def error(places: torch.Tensor, true: torch.Tensor) -> float:
    """The lights' mean distance from their true places (mm)."""
    return float((places.to(true.dtype) - true).norm(dim=1).mean())


def radial(places: torch.Tensor, true: torch.Tensor) -> float:
    """The lights' mean shift along their true directions from the origin (mm)."""
    u = true / true.norm(dim=1, keepdim=True)
    return float(((places.to(true.dtype) - true) * u).sum(1).mean())


def common_removed(places: torch.Tensor, true: torch.Tensor) -> float:
    """:func:`error` once the places' least-squares shift and scale about the truth are taken out."""
    e = (places.to(true.dtype) - true).reshape(-1, 1)
    d = true / true.norm(dim=1, keepdim=True)
    moves = torch.stack(
        [torch.eye(3, dtype=true.dtype)[j].expand_as(true).reshape(-1) for j in range(3)] + [d.reshape(-1)], 1
    )
    return float((e - moves @ torch.linalg.lstsq(moves, e).solution).reshape(-1, 3).norm(dim=1).mean())


def merged(read: list[torch.Tensor], weighted: bool) -> torch.Tensor:
    """``calibrate.merge_calibrations``' places of these calibrations, weighted or not."""
    docs = [
        {"format": "matscan-calibration/1", "light_positions_mm": {str(k): p[k].tolist() for k in range(24)}}
        for p in read
    ]
    calibrate.MERGE_WEIGHTED = weighted
    try:
        m = calibrate.merge_calibrations(docs, [f"calibration {k}" for k in range(len(docs))]).document
    finally:
        calibrate.MERGE_WEIGHTED = False
    return torch.tensor([m["light_positions_mm"][str(k)] for k in range(24)], dtype=torch.float64)


def from_cache(folder: Path, file: Path) -> None:
    """Add each calibration in bench/nearcal.py's ``--calibration-cache`` ``folder`` to ``file``."""
    cal = json.loads(file.read_text())
    for path in sorted(folder.glob("*-128-seed*-*.pt")):
        lights, gains, record, _ = torch.load(path, weights_only=False)
        cal[path.stem] = {
            "read": bool(record["updated"]),
            "light_positions_mm": [[round(float(v), 4) for v in p] for p in lights.position],
            "light_gains": [[round(float(v), 5) for v in g] for g in gains],
        }
    file.write_text(json.dumps(dict(sorted(cal.items())), separators=(",", ":")) + "\n")


def to_cache(file: Path, folder: Path) -> None:
    """Write each calibration in ``file`` to ``folder`` as bench/nearcal.py's
    ``--calibration-cache`` reads it (the lights at its places, each aimed where the rig
    file aims it; its gains; whether its intensities were read), so that a new machine
    reruns the bench without calibrating again. Files already there are left alone."""
    rig = builtin_rig("dome24")
    nominal = rig.light_set()
    aims = torch.tensor([light.aim_mm for light in rig.lights], dtype=nominal.position.dtype)
    folder.mkdir(parents=True, exist_ok=True)
    for key, c in json.loads(file.read_text()).items():
        path = folder / f"{key}.pt"
        if path.exists():
            continue
        pos = torch.tensor(c["light_positions_mm"], dtype=nominal.position.dtype)
        axis = (aims - pos) / (aims - pos).norm(dim=1, keepdim=True)
        lights = replace(nominal, position=pos, axis=axis)
        torch.save((lights, torch.tensor(c["light_gains"]), {"updated": c["read"]}, {}), path)


def subsets(cal: dict, nominal) -> None:
    """Each subset of the four merged (its intensities read), over the domes all four
    calibrated: mean and largest error and mean radial shift (mm), best first."""
    rows: dict[tuple[int, ...], list[tuple[float, float]]] = {}
    for draw in (1, 2, 0):
        for i in range(13):
            got = [cal.get(f"{k}-128-seed{draw}-{i}") for k in FOUR]
            if None in got:
                continue
            delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + 1000 * draw)) * 2 - 1) * 5
            true = moved(nominal, delta).position.double()
            for r in range(1, len(FOUR) + 1):
                for sub in itertools.combinations(range(len(FOUR)), r):
                    read = [torch.tensor(got[j]["light_positions_mm"], dtype=true.dtype) for j in sub if got[j]["read"]]
                    if read:
                        m = merged(read, False)
                        rows.setdefault(sub, []).append((error(m, true), radial(m, true)))
    print(f"{'merged':34s} domes  mean error  largest  radial shift (mm)")
    for sub, v in sorted(rows.items(), key=lambda kv: statistics.mean(e for e, _ in kv[1])):
        e, shift = [x for x, _ in v], [y for _, y in v]
        name = " + ".join(FOUR[j] for j in sub)
        print(f"{name:34s} {len(v):5d} {statistics.mean(e):12.2f} {max(e):8.2f} {statistics.mean(shift):+13.2f}")


def with_own(cal: dict, nominal) -> None:
    """Each of the four's own places, the other three merged, and the two averaged (mm off,
    over the domes where all four were calibrated; the mean, the largest, and on how many
    domes the average beats both: it cannot be worse than both, the mean distance being
    convex)."""
    rows: dict[str, list[tuple[float, float, float]]] = {k: [] for k in FOUR}
    for draw in (1, 2, 0):
        for i in range(13):
            got = [cal.get(f"{k}-128-seed{draw}-{i}") for k in FOUR]
            if None in got:
                continue
            delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + 1000 * draw)) * 2 - 1) * 5
            true = moved(nominal, delta).position.double()
            places = [torch.tensor(c["light_positions_mm"], dtype=true.dtype) for c in got]
            for j, name in enumerate(FOUR):
                others = [places[k] for k in range(len(FOUR)) if k != j and got[k]["read"]]
                if got[j]["read"] and others:
                    three = merged(others, False)
                    both = (places[j] + three) / 2
                    rows[name].append((error(places[j], true), error(three, true), error(both, true)))
    print(
        f"{'capture':8s} domes  own: mean  largest  others merged: mean  largest  the two averaged: mean  largest"
        "  beats both"
    )
    for name, v in rows.items():
        mean = [statistics.mean(r[k] for r in v) for k in range(3)]
        top = [max(r[k] for r in v) for k in range(3)]
        wins = sum(r[2] < min(r[0], r[1]) for r in v)
        print(
            f"{name:8s} {len(v):5d} {mean[0]:10.2f} {top[0]:8.2f} {mean[1]:20.2f} {top[1]:8.2f} {mean[2]:23.2f} "
            f"{top[2]:8.2f} {wins:11d}"
        )


def main() -> None:
    file = HERE / "nearcal-calibrated" / "calibrations-s128.json"
    for a in sys.argv[1:]:
        if a.startswith("--from-cache="):
            from_cache(Path(a.split("=", 1)[1]), file)
        if a.startswith("--to-cache="):
            to_cache(file, Path(a.split("=", 1)[1]))
            return
    cal = json.loads(file.read_text())
    nominal = builtin_rig("dome24").light_set()
    if "--subsets" in sys.argv:
        subsets(cal, nominal)
        return
    if "--with-own" in sys.argv:
        with_own(cal, nominal)
        return
    rows = []
    print("draw dome  each of the four's mean error (mean radial shift; mm; - unread)")
    print(f"{'':10s}{'':52s}merged: mean  fitted out  median  weighted  fitted out")
    for draw in (1, 2, 0):
        for i in range(13):
            got = [cal.get(f"{k}-128-seed{draw}-{i}") for k in FOUR]
            if None in got:
                continue
            delta = (torch.rand(24, 3, generator=torch.Generator().manual_seed(200 + i + 1000 * draw)) * 2 - 1) * 5
            true = moved(nominal, delta).position.double()
            read = [torch.tensor(c["light_positions_mm"], dtype=true.dtype) for c in got if c["read"]]
            mean, weighted = merged(read, False), merged(read, True)
            median = torch.stack(read).quantile(0.5, dim=0)  # the middle two's mean where four
            places = [torch.tensor(c["light_positions_mm"], dtype=true.dtype) for c in got]
            each = [
                f"{error(p, true):4.2f} ({radial(p, true):+.2f})" if c["read"] else f"{'-':>12s}"
                for p, c in zip(places, got, strict=True)
            ]
            rows.append(
                (error(mean, true), common_removed(mean, true), error(median, true))
                + (error(weighted, true), common_removed(weighted, true))
            )
            r = rows[-1]
            print(f"{draw:4d} {i:4d}  {' '.join(each)}  {r[0]:11.2f} {r[1]:11.2f} {r[2]:7.2f} {r[3]:9.2f} {r[4]:11.2f}")
    avg = [statistics.mean(c) for c in zip(*rows, strict=True)]
    print(
        f"{len(rows)} domes, mean errors (mm): merged by mean {avg[0]:.2f} ({avg[1]:.2f} with its shift and scale "
        f"fitted out), by median {avg[2]:.2f}, weighted {avg[3]:.2f} ({avg[4]:.2f})"
    )


if __name__ == "__main__":
    main()
