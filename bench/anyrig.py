"""The any-rig network against the dome24 networks on dome24, and against the solver alone
on a rig it never saw.

Materials: the 8 non-procedural evaluation sets (5 artist-style, 3 built from texture
photos; never trained on), SIZE² px over the 120 mm field, 8-bit sRGB with read noise 0.002.

* dome24, the paper's Table 4 subsets of 1, 2, 3 and 6 LEDs: the shipped dome24 networks
  and the any-rig network, each alone (no refinement);
* the 49-light RTI dome of bench/rti_dome.py (directional lights, orthographic camera; no
  such rig is in the any-rig training), 1, 2, 3, 6 and 12 of its lights spread evenly: the
  any-rig network alone, and the solver alone from flat maps;
* on both, each network's maps refined by the solver (``+ solver``: the ``lm`` solver
  started from them, held near them with the strength ``reconstruct`` uses: 1 for the
  dome24 networks, ``anyrig_hold`` of the photo count for the any-rig network, as ``--anyrig`` does
  from 2 photos (from one, ``reconstruct`` starts from flat maps instead);
  ``--anyrig-hold S`` tries another, here and in ``reconstruct`` on rti-icon);
* the real RTI capture tests/data/rti-icon (72 photos, handheld light, `.lp` directions;
  every 4th photo held out, the fit from 3, 6, 12, 24 or all 54 of the others spread
  evenly): PSNR and SSIM of the 18 held-out photos as displayed, for ``reconstruct``
  with flat maps and with ``--anyrig WEIGHTS``, and HSH where it has enough photos.

Printed per rig and light count: novel-light RMSE (linear, clipped; 16 lights for dome24,
the 20 test lights for the RTI dome) against the true maps, and the normals' mean error
in degrees, averaged over the materials; then the RMSE's mean over the 5 artist-style
sets and over the 3 photo-built ones apart (a network trained on photo-built library
sets, made by the same rule from other photos, is nearer the second group).

With ``--networks-only``: the networks alone, without the solver or rti-icon (about a
minute): the dome24 networks, each WEIGHTS given (several any-rig networks side by side,
same photos), and the photometric-stereo estimate that ``--ps-skip`` networks start from
(its albedo and normals, specular 0.04, roughness 0.5). With ``--table4`` dome24 is
scored at every Table 4 count (10, 16 and 24 LEDs too), here and in the full bench.

With ``--tilt DEG`` every material lies tilted by DEG degrees toward the azimuth 30° (its
normals turned, :func:`matscan.anyrig.tilted`), as a sample not lying flat on the stage.

With ``--procedural`` the materials are instead 8 procedural ones of prior v2 (the
any-rig training's prior) whose seeds, 2^31 and up, training never draws (it draws seeds
below 2^31); the artist and photo columns are then the first 5 and the last 3 of them.

With ``--starts`` (about 2 minutes): which of the network's maps costs on rti-icon. From
3 and 6 of its photos the ``lm`` solver is started from hybrids of the network's maps and
flat maps, each held near its start with the flat start's strength (what ``--anyrig`` did
before its hold depended on the photo count), so that the hybrids compare alike;
printed: the held-out PSNR of the start and of the solved maps, SSIM, and the solved
specular and roughness means.

With ``--subsets K`` (about 3 minutes for K = 6 and three networks): rti-icon from 3, 6
and 12 photos, K interleaved choices of them per count (no photo in two choices), flat
maps and ``--anyrig`` with each WEIGHTS given; printed: the held-out PSNR's mean and
standard deviation over the choices, and each network's paired difference from flat maps
(mean, standard deviation, and in how many choices it is higher); ``--counts`` takes
other counts (no photo is in two choices while count × K ≤ 54). One choice of 3 photos
decides little: over 6 choices of 3 photos, flat maps' PSNR has a standard deviation of
1.4 dB.

With ``--miscalibration DEG,REL`` the unseen dome's photos are taken under lights other
than the ones its captures name (:func:`matscan.anyrig.miscalibrated`: each turned by
|N(0, DEG)| degrees, scaled by 1 + N(0, REL)), as a handheld light or a dome whose LEDs
are not where its file says makes them.

With ``--hold [--library DIR]`` (about 30 s; 2.5 minutes with a library of 20): how hard
the solver should hold the network's maps, chosen on data that neither the unseen dome
nor rti-icon is: 8 procedural materials of prior v2 that training never drew, and with
``--library`` every map set in DIR (``tools/photo_library.py``'s, say), centre crops of
SIZE², photographed by a tuning dome of near LEDs (32 at 300 mm on rings at 15°, 35°, 55°
and 75°, a perspective camera 300 mm up) from 2, 3, 6, 12 and 24 of its lights, the
network's maps refined by the solver held with strengths 0.2 (the flat start's
``FLAT_START_PRIOR``) to 4 (1 is what the dome24 networks get); printed per group:
novel-light RMSE (16 lights, :func:`matscan.evaluate.evaluation_lights`) per strength
and count, and the network alone; then each strength's ratio to 0.2 (the mean of the
groups' ratios), the best strength per count, and those as an ``--anyrig-hold``
schedule (up to the geometric mean of two neighbouring counts the lower one's).

With ``--anyrig-hold S`` or ``N:S,...,S``: the any-rig network's maps held with S, or with
S up to N photos (:data:`matscan.reconstruct.job.ANYRIG_HOLD`), everywhere in the bench.

Run by hand: .venv/bin/python bench/anyrig.py WEIGHTS [WEIGHTS ...] [--size 128] [--networks-only]
[--table4] [--tilt DEG] [--miscalibration 3,0.1] [--procedural] [--starts] [--subsets K [--counts 3,6,12]] [--hold]
[--library DIR] [--anyrig-hold S]
(``WEIGHTS SIZE`` also works; ``WEIGHTS:raw`` scores a checkpoint's raw weights where it
also keeps their moving average, ``train-anyrig --ema``, which ``WEIGHTS`` scores)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace

import torch

from matscan.anyrig import load, miscalibrated, photo_input, predict_capture, ps_estimate
from matscan.capture import Capture
from matscan.capture.virtual import CameraModel, simulate_images
from matscan.evaluate import evaluation_lights
from matscan.mapset import MapSet
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.materials.photos import TINTS, photo_material
from matscan.materials.procedural import random_material
from matscan.reconstruct import ReconstructConfig, job, reconstruct_capture
from matscan.reconstruct.networks import predict_maps
from matscan.reconstruct.solver import solve_maps
from matscan.render import render_maps, surface_points
from matscan.rig import Camera, Light, Rig, builtin_rig
from matscan.weights import load_model

sys.path.insert(0, "bench")
from rti_dome import TEST, TRAIN, rti_rig  # noqa: E402


def capture_of(maps, rig, indices, seed, off: tuple[float, float] = (0.0, 0.0)) -> Capture:
    """The rig's photos of ``maps`` under lights ``indices``; with ``off`` (degrees,
    relative intensity) taken under :func:`matscan.anyrig.miscalibrated` lights (drawn
    from the seed and the count) while the capture names the rig's."""
    lights = rig.light_set(indices)
    shot = lights
    if any(off):
        shot = miscalibrated(lights, torch.Generator().manual_seed(1000 * seed + len(indices)), *off)
    photos = simulate_images(maps, shot, rig.field_mm, CameraModel(read_noise=0.002), seed=seed)
    return Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        (photos >= 1 - 0.5 / 255).any(1, keepdim=True),
        tuple(indices),
        lights,
        tuple(f"{k:02d}.png" for k in indices),
    )


def scores(pred: MapSet, truth: MapSet, lights, field) -> tuple[float, float]:
    with torch.no_grad():
        a = render_maps(pred, lights, field).clamp(0, 1)
        b = render_maps(truth, lights, field).clamp(0, 1)
    cos = (pred.normal * truth.normal).sum(0).clamp(-1, 1)
    return float((a - b).square().mean().sqrt()), float(torch.rad2deg(torch.acos(cos)).mean())


def means(vals: list[tuple[float, float]]) -> tuple[float, float, float, float]:
    """Mean novel-light RMSE and normals' error over the materials, then the RMSE's mean over
    the artist-style sets and over the photo-built ones (they come in that order)."""
    a = len(ARTIST_NAMES)

    def mean(xs):
        return sum(xs) / len(xs)

    return (
        mean([v[0] for v in vals]),
        mean([v[1] for v in vals]),
        mean([v[0] for v in vals[:a]]),
        mean([v[0] for v in vals[a:]]),
    )


def refined(start: MapSet, cap: Capture, strength: float, networks: bool = False) -> MapSet:
    """The ``lm`` solver started from a network's maps and held near them; from the dome24
    networks' (``networks``) without the steps on the pixels still converging, as
    ``reconstruct`` runs it (:mod:`matscan.reconstruct.lm`)."""
    cfg = ReconstructConfig().lm
    return solve_maps(start, cap, replace(cfg, more_iterations=0) if networks else cfg, strength)[0]


def spread(n: int, count: int) -> list[int]:
    return sorted({round((i + 0.5) * n / count - 0.5) for i in range(count)})


def photometric_stereo(cap: Capture) -> MapSet:
    """The ``--ps-skip`` networks' photometric-stereo estimate as maps (specular 0.04,
    roughness 0.5)."""
    h, w = cap.size
    points = surface_points(cap.field_mm, (h, w))
    xs = [photo_input(cap.linear([i])[0], cap.lights.select([i]), points)[None] for i in range(len(cap.files))]
    slope, albedo, _ = ps_estimate(lambda: ((x, None) for x in xs))
    n = torch.cat([slope[0], torch.ones(1, h, w)])
    return MapSet(
        diffuse=albedo[0].clamp(0, 1),
        specular=torch.full((3, h, w), 0.04),
        roughness=torch.full((1, h, w), 0.5),
        normal=n / n.norm(dim=0, keepdim=True),
    )


def load_spec(spec: str):
    """WEIGHTS, or WEIGHTS:raw for a checkpoint's raw weights where it also keeps their
    moving average (``train-anyrig --ema``), which plain WEIGHTS gives."""
    if spec.endswith(":raw"):
        return load(spec[: -len(":raw")], averaged=False)
    return load(spec)


def materials_of(size: int, procedural: bool = False, tilt: float = 0.0) -> list[MapSet]:
    """The 8 non-procedural evaluation sets, or 8 procedural materials training never drew;
    with ``tilt`` each lies tilted by that many degrees toward the azimuth 30°."""
    from matscan.anyrig import tilted

    if procedural:
        sets = [random_material(size, 2**31 + i, prior="v2")[1] for i in range(8)]
    else:
        sets = [artist_material(n, size) for n in ARTIST_NAMES] + [photo_material(n, size) for n in TINTS]
    return [replace(m, normal=tilted(m.normal, tilt, 30.0)) for m in sets] if tilt else sets


def networks_only(
    paths: list[str],
    size: int,
    off: tuple[float, float] = (0.0, 0.0),
    procedural: bool = False,
    table4: bool = False,
    tilt: float = 0.0,
) -> None:
    nets, _ = load_model("default")
    anyrigs = [(path, load_spec(path)) for path in paths]
    materials = materials_of(size, procedural, tilt)
    dome = builtin_rig("dome24")
    rti, test = rti_rig(TRAIN), rti_rig(TEST)
    rows: dict[tuple, list[tuple[float, float]]] = {}
    t0 = time.perf_counter()
    for i, maps in enumerate(materials):
        counts = ("1", "2", "3", "6", "10", "16", "24") if table4 else ("1", "2", "3", "6")
        cases = [("dome24", c, dome, dome.subset(c), evaluation_lights(dome)) for c in counts]
        cases += [("RTI dome (unseen)", str(c), rti, spread(len(TRAIN), c), test.light_set()) for c in (1, 2, 3, 6, 12)]
        for rig_name, count, rig, indices, lights in cases:
            cap = capture_of(maps, rig, indices, seed=i, off=off if rig is rti else (0.0, 0.0))
            got = [("photometric stereo", photometric_stereo(cap))]
            if rig_name == "dome24":
                got.append(("dome24 networks", predict_maps(nets, cap)))
            got += [(path, MapSet(**predict_capture(net, cap))) for path, net in anyrigs]
            for method, pred in got:
                rows.setdefault((rig_name, count, method), []).append(scores(pred, maps, lights, rig.field_mm))
    print(f"{'rig':20s} {'lights':>6s} {'novel RMSE':>10s} {'normal °':>9s} {'artist':>7s} {'photo':>7s}  method")
    for (rig, count, method), vals in rows.items():
        rmse, deg, artist, photo = means(vals)
        print(f"{rig:20s} {count:>6s} {rmse:10.4f} {deg:9.2f} {artist:7.4f} {photo:7.4f}  {method}")
    print(f"{len(materials)} materials at {size}², {time.perf_counter() - t0:.0f} s")


def main() -> None:
    torch.set_num_threads(2)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("weights", nargs="+")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--networks-only", dest="networks_only", action="store_true")
    parser.add_argument(
        "--miscalibration",
        default="0,0",
        metavar="DEG,REL",
        help="the unseen dome's photos taken under lights turned by |N(0, DEG)| degrees and scaled by 1 + N(0, REL), "
        "the capture naming the rig's (rti-icon and dome24 unchanged)",
    )
    parser.add_argument("--table4", action="store_true", help="dome24 at all of Table 4's counts, 10, 16, 24 too")
    parser.add_argument("--tilt", type=float, default=0.0, metavar="DEG", help="the materials lie tilted DEG degrees")
    parser.add_argument("--procedural", action="store_true", help="8 procedural materials training never drew")
    parser.add_argument("--starts", action="store_true", help="rti-icon from hybrids of network and flat maps")
    parser.add_argument(
        "--subsets", type=int, default=0, metavar="K", help="rti-icon from K interleaved choices of --counts photos"
    )
    parser.add_argument("--counts", default="3,6,12", help="--subsets: the photo counts (default 3,6,12)")
    parser.add_argument(
        "--anyrig-hold",
        default=None,
        metavar="S",
        help="the solver's hold on the any-rig network's maps: S, or N:S,...,S by photo count",
    )
    parser.add_argument("--library", default=None, help="--hold: a folder of map sets to tune on as well")
    parser.add_argument("--hold", action="store_true", help="the solver's hold on the network's maps, on a tuning dome")
    args = parser.parse_args()
    off = tuple(float(v) for v in args.miscalibration.split(","))
    if args.anyrig_hold is not None:
        job.ANYRIG_HOLD = hold_schedule(args.anyrig_hold)  # reconstruct_capture reads it at each call
    if len(args.weights) > 1 and args.weights[-1].isdigit():  # the older form: WEIGHTS SIZE
        args.size = int(args.weights.pop())
    if args.networks_only:
        networks_only(args.weights, args.size, off, args.procedural, args.table4, args.tilt)
        return
    if args.starts:
        starts(load_spec(args.weights[0]))
        return
    if args.subsets:
        subsets_of(args.weights, args.subsets, tuple(int(c) for c in args.counts.split(",")))
        return
    if args.hold:
        hold(load_spec(args.weights[0]), args.size, args.library)
        return
    weights, size = args.weights[0], args.size
    anyrig = load_spec(weights)
    nets, _ = load_model("default")
    materials = materials_of(size, args.procedural, args.tilt)
    dome = builtin_rig("dome24")
    rti, test = rti_rig(TRAIN), rti_rig(TEST)
    rows: dict[tuple, list[tuple[float, float]]] = {}
    t0 = time.perf_counter()
    for i, maps in enumerate(materials):
        for count in ("1", "2", "3", "6", "10", "16", "24") if args.table4 else ("1", "2", "3", "6"):
            cap = capture_of(maps, dome, dome.subset(count), seed=i)
            lights = evaluation_lights(dome)
            start = predict_maps(nets, cap)
            rows.setdefault(("dome24", count, "dome24 networks"), []).append(scores(start, maps, lights, dome.field_mm))
            rows.setdefault(("dome24", count, "dome24 + solver"), []).append(
                scores(refined(start, cap, 1.0, networks=True), maps, lights, dome.field_mm)
            )
            start = MapSet(**predict_capture(anyrig, cap))
            rows.setdefault(("dome24", count, "any-rig network"), []).append(scores(start, maps, lights, dome.field_mm))
            rows.setdefault(("dome24", count, "any-rig + solver"), []).append(
                scores(refined(start, cap, job.anyrig_hold(len(cap.files))), maps, lights, dome.field_mm)
            )
        for count in (1, 2, 3, 6, 12):
            cap = capture_of(maps, rti, spread(len(TRAIN), count), seed=i, off=off)
            lights = test.light_set()
            start = MapSet(**predict_capture(anyrig, cap))
            rows.setdefault(("RTI dome (unseen)", str(count), "any-rig network"), []).append(
                scores(start, maps, lights, rti.field_mm)
            )
            rows.setdefault(("RTI dome (unseen)", str(count), "any-rig + solver"), []).append(
                scores(refined(start, cap, job.anyrig_hold(len(cap.files))), maps, lights, rti.field_mm)
            )
            res = reconstruct_capture(cap, ReconstructConfig(model="none", refine="on"))
            rows.setdefault(("RTI dome (unseen)", str(count), "solver alone"), []).append(
                scores(res.maps, maps, lights, rti.field_mm)
            )
    head = f"{'novel RMSE':>10s} {'normal °':>9s} {'artist':>7s} {'photo':>7s}"
    print(f"{'rig':20s} {'lights':>6s} {'method':18s} {head}")
    for (rig, count, method), vals in rows.items():
        rmse, deg, artist, photo = means(vals)
        print(f"{rig:20s} {count:>6s} {method:18s} {rmse:10.4f} {deg:9.2f} {artist:7.4f} {photo:7.4f}")
    print(f"{len(materials)} materials at {size}², {time.perf_counter() - t0:.0f} s")
    real_capture(anyrig, nets)


def rti_icon() -> tuple[Capture, list[int], list[int]]:
    """rti-icon imported, the positions of its 18 held-out photos, and of the 54 others."""
    import tempfile
    from pathlib import Path

    from matscan.capture import load_capture
    from matscan.capture.rti import import_rti
    from matscan.reconstruct.job import held_out_positions

    with tempfile.TemporaryDirectory() as tmp:
        import_rti(Path(__file__).parents[1] / "tests" / "data" / "rti-icon", Path(tmp) / "icon")
        cap = load_capture(Path(tmp) / "icon")
    left = held_out_positions(len(cap.files), 18)
    return cap, left, [i for i in range(len(cap.files)) if i not in left]


def kept_of(rest: list[int], count: int) -> list[int]:
    """``count`` of the photos ``rest``, spread evenly."""
    return [rest[round((j + 0.5) * len(rest) / count - 0.5)] for j in range(count)]


def real_capture(anyrig, nets) -> None:
    """rti-icon: held-out PSNR / SSIM from few to all of the other photos (module doc)."""
    from matscan.reconstruct.job import display, hsh_validation, photo_scores

    t0 = time.perf_counter()
    cap, left, rest = rti_icon()
    print(f"rti-icon, 18 photos held out: {'photos':>6s}  flat maps (dB / SSIM)  --anyrig  HSH")
    for count in (3, 6, 12, 24, 54):
        kept = kept_of(rest, count)
        sub = cap.select(kept)
        cells = []
        for a in (None, anyrig):
            res = reconstruct_capture(sub, ReconstructConfig(), nets, anyrig=a)
            sc = photo_scores(
                cap,
                left,
                lambda i, r=res: display(render_maps(r.maps, cap.lights.select([i]), cap.field_mm, r.intensity_scale)),
            )
            cells.append(f"{sc['psnr_left_out']:.2f} / {sc['ssim_left_out']:.3f}")
        if count >= 9:
            h = hsh_validation(cap, kept, left)
            cells.append(f"{h['psnr_left_out']:.2f} / {h['ssim_left_out']:.3f}")
        print(f"{'':30s} {count:6d}  " + "  ".join(cells))
    print(f"rti-icon in {time.perf_counter() - t0:.0f} s")


def phased(rest: list[int], count: int, k: int, subsets: int) -> list[int]:
    """``count`` of the photos ``rest`` spread evenly, the ``k``-th of ``subsets`` phases:
    the j-th photo at (j + (k + 0.5) / subsets) · len(rest) / count, so the subsets
    interleave and share no photo while count · subsets ≤ len(rest)."""
    return [rest[int((j + (k + 0.5) / subsets) * len(rest) / count)] for j in range(count)]


def subsets_of(specs: list[str], subsets: int, counts: tuple[int, ...] = (3, 6, 12)) -> None:
    """``--subsets K``: rti-icon from ``counts`` photos (3, 6 and 12), K interleaved choices of them
    each, flat maps against every WEIGHTS's ``--anyrig`` (module doc)."""
    from matscan.reconstruct.job import display, photo_scores

    t0 = time.perf_counter()
    cap, left, rest = rti_icon()
    dome24, _ = load_model("default")  # set aside on rti-icon's rig, as in real_capture
    nets = [load_spec(s) for s in specs]
    print(f"rti-icon, 18 photos held out, {subsets} choices of the others per count: held-out PSNR (dB)")
    print(f"{'photos':>6s} {'start':48s} {'mean':>6s} {'sd':>5s}  {'− flat: mean':>12s} {'sd':>5s} {'wins':>5s}")
    for count in counts:
        psnr: dict[str, list[float]] = {}
        for k in range(subsets):
            sub = cap.select(phased(rest, count, k, subsets))
            for name, a in [("flat maps", None), *zip(specs, nets, strict=True)]:
                res = reconstruct_capture(sub, ReconstructConfig(), dome24, anyrig=a)
                sc = photo_scores(
                    cap,
                    left,
                    lambda i, r=res: display(
                        render_maps(r.maps, cap.lights.select([i]), cap.field_mm, r.intensity_scale)
                    ),
                )
                psnr.setdefault(name, []).append(sc["psnr_left_out"])
        flat = torch.tensor(psnr["flat maps"], dtype=torch.float64)
        for name, vals in psnr.items():
            v = torch.tensor(vals, dtype=torch.float64)
            d = v - flat
            paired = (
                ""
                if name == "flat maps"
                else f"{float(d.mean()):+12.2f} {float(d.std()):5.2f} {int((d > 0).sum()):2d}/{subsets}"
            )
            print(f"{count:6d} {name[-48:]:48s} {float(v.mean()):6.2f} {float(v.std()):5.2f}  {paired}", flush=True)
    print(f"rti-icon subsets in {time.perf_counter() - t0:.0f} s")


HOLDS = (0.2, 0.5, 1.0, 2.0, 4.0)
HOLD_COUNTS = (2, 3, 6, 12, 24)


def tuning_dome() -> Rig:
    """``--hold``'s rig: 32 LEDs at 300 mm on rings at 15°, 35°, 55° and 75° (each ring
    turned 22.5° from the last), aimed at the centre, a perspective camera 300 mm up."""
    lights = []
    for ring, elevation in enumerate((15.0, 35.0, 55.0, 75.0)):
        e = math.radians(elevation)
        for k in range(8):
            a = math.radians(45.0 * k + 22.5 * ring)
            lights.append(
                Light(position_mm=(300 * math.cos(e) * math.cos(a), 300 * math.cos(e) * math.sin(a), 300 * math.sin(e)))
            )
    return Rig("tuning32", 300.0, Camera(position_mm=(0.0, 0.0, 300.0)), (120.0, 120.0), tuple(lights))


def hold_schedule(spec: str) -> tuple[tuple[float, float], ...]:
    """``--anyrig-hold``: "S" (one strength) or "N:S,N:S,...,S" (up to N photos S, the last
    for any count), as :data:`matscan.reconstruct.job.ANYRIG_HOLD`."""
    parts = spec.split(",")
    pairs = [tuple(float(v) for v in p.split(":")) for p in parts[:-1]]
    return (*pairs, (math.inf, float(parts[-1])))


def hold(anyrig, size: int, library: str | None) -> None:
    """``--hold``: novel-light RMSE of the network's maps refined with each strength, and
    per count the strength that does best (module doc)."""
    from pathlib import Path

    from matscan.anyrig import read_library

    t0 = time.perf_counter()
    rig = tuning_dome()
    lights = evaluation_lights(rig)
    groups = {"procedural": materials_of(size, procedural=True)}
    if library:
        sets = read_library(sorted(p for p in Path(library).iterdir() if p.is_dir()))
        groups["library"] = [m.crop((m.size[0] - size) // 2, (m.size[1] - size) // 2, size, size) for m in sets]
    names = ["network alone"] + [f"hold {s:g}" for s in HOLDS]
    mean: dict[tuple[str, str, int], float] = {}
    for group, materials in groups.items():
        rmse: dict[tuple[str, int], list[float]] = {}
        for i, maps in enumerate(materials):
            for count in HOLD_COUNTS:
                cap = capture_of(maps, rig, spread(len(rig.lights), count), seed=i)
                start = MapSet(**predict_capture(anyrig, cap))
                rmse.setdefault(("network alone", count), []).append(scores(start, maps, lights, rig.field_mm)[0])
                for s in HOLDS:
                    rmse.setdefault((f"hold {s:g}", count), []).append(
                        scores(refined(start, cap, s), maps, lights, rig.field_mm)[0]
                    )
        mean |= {(group, *k): sum(v) / len(v) for k, v in rmse.items()}
        print(f"tuning dome, {len(materials)} {group} materials at {size}², novel-light RMSE")
        print(f"{'':16s}" + "".join(f"{c:>9d}" for c in HOLD_COUNTS))
        for name in names:
            print(f"{name:16s}" + "".join(f"{mean[(group, name, c)]:9.4f}" for c in HOLD_COUNTS))
    print("ratio to hold 0.2, mean over the groups")
    best = []
    for name in names:
        ratios = [sum(mean[(g, name, c)] / mean[(g, "hold 0.2", c)] for g in groups) / len(groups) for c in HOLD_COUNTS]
        print(f"{name:16s}" + "".join(f"{r:9.4f}" for r in ratios))
        best.append(ratios)
    picks = [HOLDS[min(range(len(HOLDS)), key=lambda j, k=k: best[j + 1][k])] for k in range(len(HOLD_COUNTS))]
    tops = [math.sqrt(a * b) for a, b in zip(HOLD_COUNTS, HOLD_COUNTS[1:], strict=False)]
    spec = [f"{top:.2f}:{s:g}" for top, s, nxt in zip(tops, picks, picks[1:], strict=False) if s != nxt]
    spec.append(f"{picks[-1]:g}")
    print(f"best per count: {dict(zip(HOLD_COUNTS, picks, strict=True))}; --anyrig-hold {','.join(spec)}")
    print(f"in {time.perf_counter() - t0:.0f} s")


MAPS = ("diffuse", "specular", "roughness", "normal")
HYBRIDS = {
    "flat": (),
    "network": MAPS,
    "net normal": ("normal",),
    "net diffuse": ("diffuse",),
    "net spec+rough": ("specular", "roughness"),
    "net diffuse+normal": ("diffuse", "normal"),
}


def starts(anyrig) -> None:
    """``--starts``: which of the network's maps costs on rti-icon (module doc)."""
    from matscan.reconstruct.job import display, photo_scores
    from matscan.reconstruct.solver import flat_start

    def held_out(maps: MapSet, scale: float) -> dict[str, float]:
        return photo_scores(
            cap, left, lambda i: display(render_maps(maps, cap.lights.select([i]), cap.field_mm, scale))
        )

    cap, left, rest = rti_icon()
    for count in (3, 6):
        sub = cap.select(kept_of(rest, count))
        flat, net = flat_start(sub), MapSet(**predict_capture(anyrig, sub))
        for name, keys in HYBRIDS.items():
            start = MapSet(**{k: getattr(net if k in keys else flat, k) for k in MAPS})
            maps, _, scale = solve_maps(start, sub, ReconstructConfig().lm, job.FLAT_START_PRIOR)
            before, after = held_out(start, 1.0), held_out(maps, scale)
            print(
                f"{count} photos  {name:20s} start {before['psnr_left_out']:.2f}  "
                f"solved {after['psnr_left_out']:.2f} dB / {after['ssim_left_out']:.3f}  "
                f"specular {float(maps.specular.mean()):.3f}  roughness {float(maps.roughness.mean()):.3f}",
                flush=True,
            )
        tilt = float(torch.rad2deg(torch.acos(net.normal[2].clamp(-1, 1))).mean())
        print(
            f"  the network's start: specular {float(net.specular.mean()):.3f}, roughness "
            f"{float(net.roughness.mean()):.3f}, diffuse {float(net.diffuse.mean()):.3f} (flat maps' "
            f"{float(flat.diffuse.mean()):.3f}), normals {tilt:.2f}° from the vertical on average"
        )


if __name__ == "__main__":
    main()
