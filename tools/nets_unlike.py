"""The networks alone on the 8 map sets unlike the training set, fast (seconds, not the study's half hour).

For each weights file and each dome24 Table 4 count (``--counts``; 1, 2, 3, 6, 24): the mean over the 5
artist-style and 3 texture-photograph map sets (``matscan.materials.artist`` and
``photos``, never used in training) at SIZE² of the novel-light RMSE (16 lights the rig
does not have, ``matscan.evaluate.evaluation_lights``), of the diffuse, specular and
roughness RMSE and of the mean normal angle (``matscan.evaluate.map_scores``). Captures
as ``bench/anyrig.py`` makes them (8-bit sRGB, noise, seed = set index).
With ``--per-set COUNT`` it prints each set's numbers at that count instead; with
``--levers`` as well, each set's novel-light RMSE when one predicted map (or specular and
roughness together) is replaced by the true one: which map's error costs the relighting
most, and where a nearer map relights worse with the other predicted maps beside it.

A run folder in place of a weights file stands for its snapshots in step order
(``matscan train --snapshot-every N``, complete sets filled from the run's init): how far
the scores wander along one run, which a comparison of two runs' endpoints must exceed.
With more than one weights file, tables at the end: novel-light RMSE and roughness
RMSE per count, and every score's mean over the counts, one row per file.

Run: .venv/bin/python tools/nets_unlike.py WEIGHTS|RUN [...] [--size 128] [--per-set 2]
[--counts 1,2,3,6,10,16,24] [--levers] [--mapsets DIR] [--mirrors]
``--mirrors`` averages the networks' maps over the capture's mirrors, as ``reconstruct
--mirrors`` does.
``--mapsets DIR`` scores the map set folders in DIR instead (resampled to SIZE²), e.g.
the selection sets of ``tools/photo_library.py DIR --selection``: choosing among
snapshots there leaves the unlike sets to evaluate the choice.
``--procedural N [--prior v4]`` scores N procedural materials of that prior instead, with
the selection seeds 2^42 + i (training draws seeds below 2^40, the studies 2^41 + i): how
the networks do on the distribution they were trained on.
A count may be a list of dome24 lights joined by + (``--counts 6,4+8+12+16+20``): how much
the scores move between subsets of about one size, which a trend over counts must exceed.
Weights that hold only some networks are scored with the shipped ones for the others
(``export_weights(..., fill_from=...)`` first).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))

from anyrig import capture_of  # noqa: E402

from matscan.capture.virtual import resize_maps  # noqa: E402
from matscan.evaluate import evaluation_lights, map_scores  # noqa: E402
from matscan.mapset import MapSet  # noqa: E402
from matscan.materials.artist import ARTIST_NAMES, artist_material  # noqa: E402
from matscan.materials.library import read_any  # noqa: E402
from matscan.materials.photos import TINTS, photo_material  # noqa: E402
from matscan.materials.procedural import PRIORS, random_material  # noqa: E402
from matscan.reconstruct.networks import predict_maps  # noqa: E402
from matscan.render import render_maps  # noqa: E402
from matscan.rig import builtin_rig  # noqa: E402
from matscan.train import snapshots  # noqa: E402
from matscan.weights.format import load_weights  # noqa: E402

#: Procedural seeds of ``--procedural``: 2^42 + i, beyond training's (< 2^40) and the studies' (2^41 + i).
SELECTION_SEED = 2**42


def rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).square().mean().sqrt())


#: What ``--levers`` swaps in from the truth.
LEVERS = (("diffuse",), ("specular",), ("roughness",), ("normal",), ("specular", "roughness"))


def sized(maps: MapSet, size: int) -> MapSet:
    """The maps at size² (resampled where they are another size)."""
    return maps if maps.size == (size, size) else resize_maps(maps, size)


def novel_rmse(p: MapSet, m: MapSet, lights, field_mm) -> float:
    with torch.no_grad():
        return rmse(render_maps(p, lights, field_mm).clamp(0, 1), render_maps(m, lights, field_mm).clamp(0, 1))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("weights", nargs="+", type=Path, help="weights files, or run folders (their snapshots)")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--per-set", metavar="COUNT", help="each map set's numbers at this light count")
    parser.add_argument("--levers", action="store_true", help="with --per-set: novel RMSE with each map made true")
    parser.add_argument(
        "--mapsets",
        type=Path,
        help="score the map set folders in this folder instead (tools/photo_library.py OUT --selection)",
    )
    parser.add_argument("--procedural", type=int, metavar="N", help="score N procedural materials instead")
    parser.add_argument("--prior", default="v1", choices=sorted(PRIORS), help="with --procedural (default v1)")
    parser.add_argument(
        "--mirrors", action="store_true", help="the networks' maps averaged over the mirrors (reconstruct --mirrors)"
    )
    parser.add_argument(
        "--counts",
        default="1,2,3,6,24",
        help="light counts (Table 4 subsets; default 1,2,3,6,24), or light lists joined by + (0+4+8)",
    )
    args = parser.parse_args()
    if args.levers and not args.per_set:
        parser.error("--levers needs --per-set COUNT")
    torch.set_num_threads(2)
    if args.mapsets is not None and args.procedural:
        parser.error("--mapsets and --procedural: choose one")
    if args.procedural:
        drawn = [random_material(args.size, SELECTION_SEED + i, prior=args.prior) for i in range(args.procedural)]
        names = [f"{family}-{i}" for i, (family, _) in enumerate(drawn)]
        mats = [m for _, m in drawn]
    elif args.mapsets is not None:
        folders = sorted(p for p in args.mapsets.iterdir() if (p / "mapset.json").is_file())
        if not folders:
            parser.error(f"{args.mapsets}: no map set folders in it")
        names = [p.name for p in folders]
        mats = [sized(read_any(p), args.size) for p in folders]
    else:
        names = [f"artist-{n}" for n in ARTIST_NAMES] + [f"photo-{n}" for n in TINTS]
        mats = [artist_material(n, args.size) for n in ARTIST_NAMES] + [photo_material(n, args.size) for n in TINTS]
    dome = builtin_rig("dome24")
    novel_lights = evaluation_lights(dome)
    counts = [args.per_set] if args.per_set else args.counts.split(",")
    files = []
    for w in args.weights:
        if w.is_dir():
            found = snapshots(w)
            if not found:
                parser.error(f"{w}: a folder without snapshots (matscan train --snapshot-every N)")
            files += found
        else:
            files.append(w)
    table = {}
    for w in files:
        nets, _ = load_weights(w)
        for count in counts:
            rows = []
            for i, m in enumerate(mats):
                cap = capture_of(m, dome, dome.subset(count.replace("+", ",")), seed=i)
                p = predict_maps(nets, cap, symmetric=args.mirrors)
                s = map_scores(p, m)
                scores = (s["rmse_diffuse"], s["rmse_specular"], s["rmse_roughness"], s["normal_degrees"])
                rows.append((novel_rmse(p, m, novel_lights, dome.field_mm), *scores))
                if args.per_set:
                    print(
                        f"{w.name} {count} {names[i]:22s} novel {rows[-1][0]:.4f} diffuse {rows[-1][1]:.4f} "
                        f"specular {rows[-1][2]:.4f} (mean F0 {float(p.specular.mean()):.3f}, "
                        f"true {float(m.specular.mean()):.3f}) roughness {rows[-1][3]:.4f} normal {rows[-1][4]:.2f}°",
                        flush=True,
                    )
                if args.levers:
                    swapped = []
                    for lever in LEVERS:
                        q = MapSet(**{**p.present(), **{k: getattr(m, k) for k in lever}})
                        swapped.append(f"{'+'.join(lever)} {novel_rmse(q, m, novel_lights, dome.field_mm):.4f}")
                    print(f"    novel with the true map: {', '.join(swapped)}", flush=True)
            if not args.per_set:
                mean = [sum(r[k] for r in rows) / len(rows) for k in range(5)]
                table.setdefault(w, {})[count] = mean
                print(
                    f"{w.name} {count:>2} lights: novel {mean[0]:.4f} diffuse {mean[1]:.4f} specular {mean[2]:.4f} "
                    f"roughness {mean[3]:.4f} normal {mean[4]:.2f}°",
                    flush=True,
                )
    if len(table) > 1:
        name = max(len(_label(w)) for w in table)
        heads = " ".join(f"{c:>6s}" for c in counts)
        print(f"\nnovel-light RMSE | roughness RMSE, by light count\n{'':{name}s} {heads} | {heads}")
        for w, row in table.items():
            novel = " ".join(f"{row[c][0]:.4f}" for c in counts)
            rough = " ".join(f"{row[c][3]:.4f}" for c in counts)
            print(f"{_label(w):{name}s} {novel} | {rough}")
        print(f"\nmean over the counts\n{'':{name}s}  novel diffuse specular roughness normal°")
        for w, row in table.items():
            m = [sum(v[k] for v in row.values()) / len(row) for k in range(5)]
            print(f"{_label(w):{name}s} {m[0]:.4f}  {m[1]:.4f}   {m[2]:.4f}    {m[3]:.4f}  {m[4]:.2f}")
    return 0


def _label(w: Path) -> str:
    """A weights file's name; a snapshot's with its run's."""
    return f"{w.parent.parent.name}/{w.stem}" if w.parent.name == "snapshots" else w.name


if __name__ == "__main__":
    sys.exit(main())
