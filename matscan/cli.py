"""The ``matscan`` command: parses arguments, calls the library, prints one summary line.

Bad input exits with status 2 and one line ``matscan: error: <file>: <problem>``.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from matscan import __version__
from matscan.errors import MatscanError, input_error, not_a_folder

#: ``--led-gradient``'s choices (matscan.reconstruct.job.LED_GRADIENTS, not imported here:
#: it would import torch for --help)
LED_GRADIENTS = ("auto", "fit", "none", "choose")
#: A rig file's limits (matscan.rig's, not imported here for the same reason; a test
#: holds them equal): positions in mm, light intensities, emission exponents.
MAX_MM = 1e6
MAX_INTENSITY = 1e6
MAX_EXPONENT = 1e3


def _maps_arg(text: str) -> Path:
    """A map set folder, or ``@name`` for a built-in sample map set."""
    from matscan.samples import maps_folder

    return maps_folder(text)


def _capture_arg(text: str) -> Path:
    """A capture folder, or ``@name`` for a built-in sample capture."""
    from matscan.samples import capture_folder

    return capture_folder(text)


def _vector(text: str, n: int, name: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise MatscanError(f"{name}: {text!r} is not {n} comma-separated numbers") from None
    if len(values) != n:
        raise MatscanError(f"{name}: {text!r} is not {n} comma-separated numbers")
    if not all(math.isfinite(v) for v in values):
        raise MatscanError(f"{name}: {text!r} holds a number that is not finite")
    return values


def _shown(bound: float) -> str:
    """A bound as a message gives it: integers whole, other numbers short."""
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def _number(kind: type, low: float | None = None, high: float | None = None, low_open: bool = False):
    """An argparse type: a finite int or float within [low, high] (low excluded if ``low_open``)."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if low is not None and (value <= low if low_open else value < low):
            raise argparse.ArgumentTypeError(f"{text} must be {'above' if low_open else 'at least'} {_shown(low)}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"{text} must be at most {_shown(high)}")
        return value

    return parse


positive_int = _number(int, 1)
non_negative_int = _number(int, 0)
positive_float = _number(float, 0.0, low_open=True)
non_negative_float = _number(float, 0.0)
finite_float = _number(float)
#: A seed: to 2^31 − 1, so the seeds the commands derive from it (up to about 10^7 times
#: it) stay within what torch's and NumPy's generators take (2^63 − 1).
seed_int = _number(int, 0, 2**31 - 1)
#: A map or capture side in pixels: the paper's 3072² and well beyond (a 16384² capture of
#: 24 photos is about 19 GB in 8-bit codes alone).
MAX_SIZE = 16384
size_int = _number(int, 1, MAX_SIZE)

#: Options whose value is a comma-separated vector that may start with a minus sign
#: (argparse would take "-50,0,150" for an option).
VECTOR_OPTIONS = ("--light", "--corners", "--sphere", "--principal-point", "--distortion", "--dome-centre")


def _join_vectors(argv: Sequence[str]) -> list[str]:
    """``--light -50,0,150`` → ``--light=-50,0,150``."""
    out: list[str] = []
    it = iter(argv)
    for arg in it:
        if arg in VECTOR_OPTIONS:
            value = next(it, None)
            out.append(arg if value is None else f"{arg}={value}")
        else:
            out.append(arg)
    return out


def cmd_simulate(args: argparse.Namespace) -> str:
    from matscan.capture.virtual import CameraModel, default_flash_geometry, simulate
    from matscan.mapset import read_mapset
    from matscan.rig import resolve_rig

    t0 = time.perf_counter()
    rig = resolve_rig(args.rig)
    maps_path = _maps_arg(args.maps)
    maps = read_mapset(maps_path)
    bits = args.bits or (8 if args.encoding == "srgb" else 32)
    camera = CameraModel(
        exposure=args.exposure, read_noise=args.noise, full_well=args.full_well, encoding=args.encoding, bits=bits
    )
    lights = None if rig.per_image_geometry else rig.subset(args.lights)
    out = simulate(
        maps,
        rig,
        args.out,
        lights=lights,
        camera=camera,
        seed=args.seed,
        size=args.size,
        overwrite=args.overwrite,
        progress=True,
        inputs=[maps_path] + ([Path(args.rig)] if args.rig.endswith(".json") else []),
        overwrite_any=args.overwrite_any,
    )
    size = args.size or maps.size[0]
    count = len(default_flash_geometry()) if rig.per_image_geometry else len(lights or ())
    return (
        f"simulate: wrote {count} photos ({size}×{size}, rig {rig.name}, {args.encoding} {bits}-bit, "
        f"noise {args.noise:g}) to {out} in {time.perf_counter() - t0:.1f} s"
    )


def _choice_note(choice: dict | None) -> str:
    """What ``--refine auto`` chose and why, for the summary line ("" when it chose nothing)."""
    if not choice:
        return ""
    if "left_out" in choice:
        left = f"{len(choice['left_out'])} photo(s) left out"
        scores = choice["rmse_left_out"]
        default = next(iter(scores))
        if choice["chosen"] != default:
            return f" ({choice['chosen']}: clearly the best at predicting {left})"
        if min(scores, key=scores.get) != default:
            margin = choice.get("margin", 0.0)
            return f" ({default}: the default; no other predicted the {left} {margin:.0%} better)"
        return f" ({default}: the best at predicting {left})"
    return f" ({choice['chosen']}: the rule for {choice['rule']})"


def cmd_reconstruct(args: argparse.Namespace) -> str:
    from matscan.reconstruct import ReconstructConfig, reconstruct

    cfg = ReconstructConfig(
        model=args.model,
        anyrig=args.anyrig,
        refine=args.refine,
        solver=args.solver,
        refine_steps=args.steps,
        tile=args.tile,
        mirrors=args.mirrors,
        emissive=args.emissive,
        exr=args.exr,
        directx_normals=args.directx_normals,
        validate=args.validate,
        self_calibrate=args.self_calibrate or args.self_calibrate_positions or args.shared_f0 is not None,
        self_calibrate_positions=args.self_calibrate_positions or args.shared_f0 is not None,
        shared_f0=args.shared_f0,
        led_gradient=args.led_gradient,
        calibration=_calibration_arg(args.calibration),
    )
    rec = reconstruct(
        _capture_arg(args.capture),
        args.out,
        cfg,
        overwrite=args.overwrite,
        progress=True,
        overwrite_any=args.overwrite_any,
    )
    for warning in rec["warnings"]:
        print(f"matscan: warning: {warning}", file=sys.stderr)
    w, h = rec["size_px"]
    return (
        f"reconstruct: wrote maps of {w}×{h} px ({rec['mm_per_pixel'][0]:.3f} mm/px) from {len(rec['inputs'])} photos "
        f"to {args.out}; model {rec['model']['name']}, started from {START_NAMES[rec['start']]}, "
        f"refined {'yes' if rec['refined'] else 'no'}" + _choice_note(rec.get("choice")) + "; "
        f"re-render RMSE {rec['rerender_rmse']:.4f}"
        + (_validation_summary(rec["validation"]) if "validation" in rec else "")
        + f"; {rec['timings_s']['total_s']:.1f} s"
    )


def _calibration_arg(file: str | None) -> str | None:
    """``--calibration``'s file as an absolute path (recorded in matscan.json and a batch's
    manifest, which must name it wherever they are read), checked to be a file."""
    if file is None:
        return None
    path = Path(file)
    if not path.is_file():
        raise input_error(path, "no such file" if not path.exists() else "is not a file")
    return str(path.resolve())


def _merge_calibrations(args: argparse.Namespace) -> str:
    from matscan.calibrate import merge

    m = merge(args.out, args.merge, overwrite=args.overwrite)
    for name, mm in m.left_out.items():
        print(
            f"matscan: warning: {name}: left out, its lights lie {mm:.1f} mm (RMS) from the files' median places; "
            "its capture's self-calibration may have gone astray",
            file=sys.stderr,
        )
    parts = [f"{m.files} calibrations merged" + (f" ({len(m.left_out)} left out)" if m.left_out else "")]
    if m.positions:
        counts = sorted(set(m.positions.values()))
        each = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"
        spread = f"; their spread about the mean {m.position_spread_mm:.2f} mm RMS" if m.position_spread_mm else ""
        parts.append(f"{len(m.positions)} light positions (each the mean of {each}{spread})")
    if m.scale_spread is not None:
        parts.append(f"light scales (geometric means; spread {100 * m.scale_spread:.1f}%)")
    return f"calibrate: wrote {args.out}: " + ", ".join(parts)


#: How the summary line names where the maps started (``matscan.json``'s ``start``).
START_NAMES = {"networks": "the networks' maps", "any-rig network": "the any-rig network's maps", "flat": "flat maps"}


def cmd_calibrate(args: argparse.Namespace) -> str:
    from matscan.calibrate import calibrate

    if args.merge:
        if args.grey or args.chart:
            raise MatscanError("calibrate: --merge merges calibration files; measure with --grey/--chart apart")
        return _merge_calibrations(args)
    if not args.grey and not args.chart:
        raise MatscanError("calibrate: give --grey CAPTURE (grey card under each light) and/or --chart PHOTO")
    if args.positions and not args.grey:
        raise MatscanError("calibrate: --positions fits the lights to grey-card photos; give --grey CAPTURE")
    corners = None
    if args.corners:
        v = _vector(args.corners, 8, "--corners")
        corners = [(v[0], v[1]), (v[2], v[3]), (v[4], v[5]), (v[6], v[7])]
    cal = calibrate(
        args.out,
        grey=args.grey or None,
        chart=args.chart or None,
        corners=corners,
        chart_encoding=args.chart_encoding,
        flat_fields=args.flat_fields,
        overwrite=args.overwrite,
        positions=args.positions,
    )
    for warning in cal.warnings:
        print(f"matscan: warning: {warning}", file=sys.stderr)
    parts = []
    if cal.colour_matrix is not None:
        parts.append(f"colour matrix (mean patch error {cal.chart_error:.4f})")
    if args.grey:
        means = [sum(s) / 3 for s in cal.light_scales.values()]
        at = f" at {cal.exposure_s:.4g} s, LED level {cal.led_level:g}" if cal.exposure_s is not None else ""
        parts.append(f"{len(means)} light scales{at} (RGB, mean {min(means):.3f} to {max(means):.3f})")
    fit = cal.light_fit
    if fit is not None and fit.moved_mm:
        moved = fit.moved_mm.values()
        parts.append(
            f"{len(fit.positions)} light positions ({min(moved):.1f} to {max(moved):.1f} mm from the rig file; "
            f"fit residual {100 * fit.residual:.2f}%)"
        )
    elif fit is not None:
        parts.append("no near lights to place")
    return f"calibrate: wrote {args.out}: " + ", ".join(parts)


#: ``evaluate``'s named map-set groups, and the most procedural materials one study makes
SETS = ("photos", "artist")
MAX_PROCEDURAL = 10000


def _procedural_count(spec: str) -> int:
    """N of ``procedural:N``, checked."""
    try:
        count = int(spec.split(":", 1)[1])
    except ValueError:
        raise MatscanError(f"{spec}: write procedural:N with N a number of materials") from None
    if not 1 <= count <= MAX_PROCEDURAL:
        raise MatscanError(f"{spec}: write procedural:N with N from 1 to {MAX_PROCEDURAL}")
    return count


def cmd_evaluate(args: argparse.Namespace) -> str:
    from matscan.evaluate import check_methods, evaluate_to_folder, method_inputs
    from matscan.materials.artist import ARTIST_NAMES, artist_material
    from matscan.materials.library import read_any
    from matscan.materials.photos import photo_material
    from matscan.materials.procedural import random_material
    from matscan.outputs import check_destination

    lights = [s.strip() for s in args.lights.split(",")]
    methods = [m.strip() for m in args.methods.split(",")]
    encodings = [e.strip() for e in args.encodings.split(",")]
    check_methods(methods, encodings, lights)  # before any material is made
    counts = {spec: _procedural_count(spec) for spec in args.mapsets if spec.startswith("procedural:")}
    inputs = [_maps_arg(spec) for spec in args.mapsets if spec not in counts and spec not in SETS]
    # the output first, before any material is made (evaluate_to_folder checks it again, locked)
    check_destination(
        args.out, [*inputs, *method_inputs(methods)], "folder", args.overwrite, args.overwrite_any, command="evaluate"
    )
    materials = []
    for spec in args.mapsets:
        if spec in counts:
            for i in range(counts[spec]):  # seeds above 2^41: never drawn in training (seeds below 2^40)
                family, maps = random_material(args.size, 2**41 + i)
                materials.append((f"procedural-{i:03d}-{family}", maps))
        elif spec == "photos":
            materials += [(f"photo-{n}", photo_material(n, args.size)) for n in ("brick", "grass", "gravel")]
        elif spec == "artist":
            materials += [(f"artist-{n}", artist_material(n, args.size)) for n in ARTIST_NAMES]
        else:
            from matscan.capture.virtual import resize_maps

            maps = read_any(_maps_arg(spec))
            materials.append((Path(spec).name, resize_maps(maps, args.size) if maps.size[0] != args.size else maps))
    res = evaluate_to_folder(
        materials,
        Path(args.out),
        lights,
        methods,
        encodings,
        args.steps,
        args.overwrite,
        progress=True,
        jobs=args.jobs,
        inputs=inputs,
        overwrite_any=args.overwrite_any,
    )
    return f"evaluate: {res['rows']} reconstructions scored into {args.out}/results.md in {res['seconds']:.0f} s"


def cmd_render(args: argparse.Namespace) -> str:
    from matscan.outputs import claim_output

    t0 = time.perf_counter()
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".exr"):
        raise MatscanError(f"--out: {out.name}: write .png (sRGB, 8-bit) or .exr (linear float)")
    pos = _vector(args.light, 3, "--light")
    if pos[2] <= 0:
        raise MatscanError(f"--light: z = {pos[2]:g} is not above the sample plane (z > 0)")
    if max(abs(v) for v in pos) > MAX_MM:
        raise MatscanError(f"--light: {args.light!r} lies farther than {MAX_MM:g} mm (a rig file's limit)")
    maps_path = _maps_arg(args.maps)
    inputs = [maps_path] + ([Path(args.rig)] if args.rig.endswith(".json") else [])
    with claim_output(out, "render", inputs, kind="file", overwrite=args.overwrite):
        return _render(args, maps_path, pos, out, t0)


def _validation_summary(val: dict) -> str:
    text = f" (left-out photos {val['rmse_left_out']:.4f}, PSNR {val['psnr_left_out']:.2f} dB"
    if "hsh" in val:
        text += f"; HSH {val['hsh']['psnr_left_out']:.2f} dB"
    return text + ")"


def _render(args: argparse.Namespace, maps_path: Path, pos: tuple[float, ...], out: Path, t0: float) -> str:
    import numpy as np

    from matscan.color import linear_to_srgb
    from matscan.imagefile import write_image
    from matscan.mapset import read_mapset
    from matscan.render import render_maps
    from matscan.rig import LightSet, resolve_rig

    rig = resolve_rig(args.rig)
    maps = read_mapset(maps_path)
    lights = LightSet.points(
        [pos], rig.camera_point, rig.reference_distance_mm, args.intensity, args.exponent, rig.camera_w
    )
    img = render_maps(maps, lights, rig.field_mm)[0]
    if out.suffix.lower() == ".exr":
        write_image(out, img.permute(1, 2, 0).numpy(), bits=32)
    else:
        write_image(out, linear_to_srgb(img.clamp(0, 1)).permute(1, 2, 0).numpy(), bits=8)
    peak = float(np.percentile(img.numpy(), 99.9))
    return (
        f"render: wrote {out} ({maps.size[1]}×{maps.size[0]}, light at {pos} mm, "
        f"99.9th percentile {peak:.3f}) in {time.perf_counter() - t0:.1f} s"
    )


def cmd_sheet(args: argparse.Namespace) -> str:
    from matscan.outputs import capture_inputs, claim_output

    source = _capture_arg(args.folder)
    inputs = capture_inputs(source) + (capture_inputs(_maps_arg(args.maps)) if args.maps else [])
    with claim_output(args.out, "sheet", inputs, kind="file", overwrite=args.overwrite, suffixes=(".png",)):
        return _sheet(args, source)


def _sheet(args: argparse.Namespace, source: Path) -> str:
    from matscan.capture import load_capture
    from matscan.mapset import read_mapset
    from matscan.report.sheet import capture_tiles, contact_sheet, map_tiles, save_sheet

    tiles = []
    if (source / "capture.json").is_file():
        cap = load_capture(source)
        labels = [
            f"light {k}" if k is not None else Path(f).stem for k, f in zip(cap.light_indices, cap.files, strict=True)
        ]
        tiles += capture_tiles((cap.linear([i])[0] for i in range(len(cap.files))), labels)
        tiles += capture_tiles(list(cap.backlight.values()), list(cap.backlight)) if cap.backlight else []
    else:
        tiles += map_tiles(read_mapset(_maps_arg(args.folder)).present())
    if args.maps:
        tiles += map_tiles(read_mapset(_maps_arg(args.maps)).present())
    columns = min(args.columns, len(tiles)) if args.columns else (8 if len(tiles) > 16 else None)
    save_sheet(args.out, contact_sheet(tiles, columns=columns))
    return f"sheet: wrote {args.out} ({len(tiles)} tiles)"


def cmd_export(args: argparse.Namespace) -> str:
    from matscan.export import export_maps

    field = _vector(args.field_mm, 2, "--field-mm") if args.field_mm else None
    if field is not None and min(field) <= 0:
        raise MatscanError(f"--field-mm: {args.field_mm!r} must be two positive sizes (width, height) in mm")
    record = export_maps(
        args.maps,
        args.out,
        field_mm=field,
        rig=args.rig,
        exr=args.exr,
        directx_normals=args.directx_normals,
        normal_convention=args.normal_convention,
        overwrite=args.overwrite,
        overwrite_any=args.overwrite_any,
    )
    (w, h), (fw, fh) = record["size_px"], record["field_mm"]
    kinds = [name for name, ext in EXPORT_KINDS if any(f.endswith(ext) for f in record["exports"])]
    return (
        f"export: wrote {args.out} ({w}×{h} {', '.join(record['maps'])}; {', '.join(kinds)}; "
        f"{fw:.4g}×{fh:.4g} mm from {record['field_from']}) in {record['seconds']:.1f} s"
    )


#: The exports the summary names, by the ending of a file that shows them.
EXPORT_KINDS = (
    ("glTF", ".gltf"),
    ("GLB", ".glb"),
    ("MaterialX", ".mtlx"),
    ("USD", ".usda"),
    ("USDZ", ".usdz"),
    ("EXR", "exr/"),
    ("DirectX normals", "normal_directx.png"),
)


def cmd_rig_from_lp(args: argparse.Namespace) -> str:
    from matscan.atomic import write_text
    from matscan.capture.rti import RTI_FIELD_WIDTH_MM, read_lp, rig_from_lp
    from matscan.jsonfile import dumps
    from matscan.outputs import claim_output
    from matscan.rig import rig_to_dict

    field = _vector(args.field_mm, 2, "--field-mm") if args.field_mm else (RTI_FIELD_WIDTH_MM, RTI_FIELD_WIDTH_MM)
    if min(field) <= 0:
        raise MatscanError(f"--field-mm: {args.field_mm!r} must be two positive sizes (width, height) in mm")
    with claim_output(args.out, "rig from-lp", [args.lp], kind="file", overwrite=args.overwrite, suffixes=(".json",)):
        lights = read_lp(args.lp, args.y)
        for warning in lights.warnings:
            print(f"matscan: warning: {warning}", file=sys.stderr)
        rig = rig_from_lp(lights, field, name=Path(args.lp).stem)
        write_text(args.out, dumps(rig_to_dict(rig), str(args.out)))
    return (
        f"rig from-lp: wrote {args.out} ({len(rig.lights)} directional lights, orthographic camera, "
        f"field {field[0]:.4g}×{field[1]:.4g} mm, .lp y {args.y})"
    )


def cmd_rig_to_lp(args: argparse.Namespace) -> str:
    from matscan.atomic import write_text
    from matscan.capture.rti import lp_text
    from matscan.outputs import claim_output
    from matscan.rig import resolve_rig

    files = None
    if (Path(args.rig) / "capture.json").is_file():  # a capture: its photos' lights, named by the photos
        from dataclasses import replace

        from matscan.capture import load_capture
        from matscan.outputs import capture_inputs

        capture = load_capture(args.rig)
        if capture.rig.per_image_geometry or None in capture.light_indices:
            raise input_error(Path(args.rig), "has a light of its own for each photo; an .lp lists a rig's lights")
        rig = replace(capture.rig, lights=tuple(capture.rig.lights[k] for k in capture.light_indices))
        files, inputs = list(capture.files), capture_inputs(args.rig)
    else:
        rig = resolve_rig(args.rig)
        inputs = [args.rig] if str(args.rig).endswith(".json") else []
    with claim_output(args.out, "rig to-lp", inputs, kind="file", overwrite=args.overwrite, suffixes=(".lp",)):
        write_text(args.out, lp_text(rig, files, y=args.y))
    kinds = sum(lt.directional for lt in rig.lights)
    note = "" if kinds == len(rig.lights) else " (point lights written as directions from the field's centre)"
    return f"rig to-lp: wrote {args.out} ({len(rig.lights)} lights{note})"


def cmd_rig_from_sphere(args: argparse.Namespace) -> str:
    from matscan.atomic import write_text
    from matscan.capture.rti import LightFile, lp_text, rig_from_lp
    from matscan.capture.sphere import DISTORTION, Pinhole, directions_from_sphere, find_sphere
    from matscan.imagefile import READABLE
    from matscan.jsonfile import dumps
    from matscan.outputs import claim_output
    from matscan.rig import rig_to_dict

    given = _vector(args.sphere, 3, "--sphere") if args.sphere is not None else None
    principal = _vector(args.principal_point, 2, "--principal-point") if args.principal_point is not None else None
    distortion = {"k1": args.k1} if args.k1 != 0 else {}
    if args.distortion is not None:
        if args.k1 != 0:
            raise MatscanError("--k1 and --distortion: give k1 in one of them")
        values = args.distortion.split(",")
        if len(values) not in (4, 5):
            raise MatscanError(
                f"--distortion: {args.distortion!r} is not 4 or 5 comma-separated numbers (k1,k2,p1,p2[,k3])"
            )
        distortion = dict(zip(DISTORTION, _vector(args.distortion, len(values), "--distortion"), strict=False))
    if args.fov is None and (principal is not None or distortion):
        raise MatscanError(
            "--principal-point, --k1 and --distortion describe a pinhole camera: give its angle of view with --fov"
        )
    lens = Pinhole(args.fov, principal, **distortion) if args.fov is not None else None
    folder = Path(args.folder)
    if not folder.is_dir():
        raise not_a_folder(folder, "folder of photos")
    if (folder / "capture.json").is_file():  # a capture: its photos under the lights, not its dark frame or backlight
        from matscan.jsonfile import read_json

        doc = read_json(folder / "capture.json")
        images = doc.get("images") if isinstance(doc, dict) else None
        if not isinstance(images, list) or not all(
            isinstance(e, dict) and isinstance(e.get("file"), str) for e in images
        ):
            raise input_error(folder / "capture.json", "has no list of images naming their files")
        photos = [folder / e["file"] for e in images]
    else:
        photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in READABLE)
    if not photos:
        raise MatscanError(f"{folder}: holds no photos ({', '.join(sorted(READABLE))})")
    out = Path(args.out)
    if out.suffix.lower() not in (".lp", ".json"):
        raise MatscanError(f"--out: {out.name} must end in .lp (an RTI light file) or .json (a rig)")
    with claim_output(out, "rig from-sphere", [folder], kind="file", overwrite=args.overwrite):
        cx, cy, radius = given if given is not None else find_sphere(photos, args.encoding, str(folder), lens)
        directions = directions_from_sphere(photos, (cx, cy), radius, args.encoding, lens)
        lights = LightFile(tuple(p.name for p in photos), tuple(directions))
        if out.suffix.lower() == ".lp":
            write_text(out, lp_text(rig_from_lp(lights), lights.files, y=args.y))
        else:
            write_text(out, dumps(rig_to_dict(rig_from_lp(lights, name=folder.name or "rti")), str(out)))
    lowest = min(math.degrees(math.asin(d[2])) for d in directions)
    found = "" if given is not None else f"; the sphere found at ({cx:.1f}, {cy:.1f}), radius {radius:.1f} px"
    return (
        f"rig from-sphere: wrote {out} ({len(photos)} light directions, the lowest {lowest:.1f}° above the sample"
        f"{found})"
    )


def cmd_rig_from_spheres(args: argparse.Namespace) -> str:
    from matscan.atomic import write_text
    from matscan.capture import load_capture
    from matscan.capture.sphere import rig_from_spheres
    from matscan.jsonfile import dumps
    from matscan.outputs import capture_inputs, claim_output
    from matscan.rig import rig_to_dict
    from matscan.samples import capture_folder

    spheres = []
    for text in args.sphere:
        x, y, z, r = _vector(text, 4, "--sphere")
        if r <= 0:
            raise MatscanError(f"--sphere: radius {r:g} must be positive (mm)")
        if z <= 0:
            raise MatscanError(f"--sphere: {text}: its centre lies at or below the sample's plane (z = {z:g} mm)")
        for (other, q), given in zip(spheres, args.sphere, strict=False):
            if math.dist((x, y, z), other) < r + q:
                raise MatscanError(
                    f"--sphere: {text} and {given} overlap (centres {math.dist((x, y, z), other):g} mm apart, "
                    f"radii {r:g} and {q:g}); give each sphere's own centre"
                )
        spheres.append(((x, y, z), r))
    dome = None
    if args.dome_radius is not None:
        centre = _vector(args.dome_centre, 3, "--dome-centre") if args.dome_centre is not None else (0.0, 0.0, 0.0)
        dome = (centre, args.dome_radius)
    elif args.dome_centre is not None:
        raise MatscanError("--dome-centre: give the dome's radius with --dome-radius")
    if len(spheres) < 2 and dome is None:
        raise MatscanError(
            "--sphere: a light's position needs two spheres or more (one gives only its direction), "
            "or one with --dome-radius (the lights on a shell of known radius)"
        )
    folder = capture_folder(args.capture)
    with claim_output(
        args.out, "rig from-spheres", capture_inputs(folder), kind="file", overwrite=args.overwrite, suffixes=(".json",)
    ):
        rig, spreads = rig_from_spheres(load_capture(folder), spheres, dome)
        write_text(args.out, dumps(rig_to_dict(rig), str(args.out)))
    worst = max(spreads.values(), default=0.0)
    if dome is None:
        how = f"rays within {worst:.2f} mm"
    elif len(spheres) == 1:
        how = f"on the dome of radius {dome[1]:g} mm"
    else:
        how = f"on the dome; the spheres agree within {worst:.2f} mm"
    return f"rig from-spheres: wrote {args.out} ({len(spreads)} lights placed; {how})"


def cmd_import_rti(args: argparse.Namespace) -> str:
    from matscan.capture.rti import import_rti

    out, warnings = import_rti(
        args.folder,
        args.out,
        lp=args.lp,
        y=args.y,
        field_width_mm=args.field_width_mm,
        overwrite=args.overwrite,
        overwrite_any=args.overwrite_any,
    )
    for warning in warnings:
        print(f"matscan: warning: {warning}", file=sys.stderr)
    from matscan.capture import load_capture

    cap = load_capture(out)
    h, w = cap.size
    return (
        f"import-rti: wrote {out} ({len(cap.files)} photos of {w}×{h} px, directional lights, "
        f"field {cap.field_mm[0]:.4g}×{cap.field_mm[1]:.4g} mm, .lp y {args.y})"
    )


def _check_capture_out(args: argparse.Namespace) -> None:
    """``capture --out`` where a capture may go, before any device is opened: not an input
    (the rig file, the virtual camera's maps, the folder a folder camera watches) nor in
    or around one, not the current folder, not inside another capture (it resumes its
    own folder, so what that holds is checked by the capture itself)."""
    from matscan.outputs import capture_above, check_place
    from matscan.samples import maps_folder

    inputs: list[str | Path] = [args.rig] if str(args.rig).endswith(".json") else []
    for prefix in ("virtual:", "folder:"):
        if args.camera.startswith(prefix) and len(args.camera) > len(prefix):
            source = args.camera[len(prefix) :]
            inputs.append(maps_folder(source) if prefix == "virtual:" else Path(source))
    given, path = check_place(args.out, inputs)
    holder = capture_above(path)
    if holder is not None:
        raise MatscanError(f"{given}: lies in the capture {holder}; matscan never writes into a capture")


def _ask_operator(message: str) -> None:
    """Ask the operator at the terminal and wait for Enter; end of input (Ctrl-D) stops
    the capture with one line, its photos kept."""
    try:
        input(f"matscan: {message} ")
    except EOFError:
        raise MatscanError(
            "capture: no answer (end of input); the photos so far are kept: run the same command to resume"
        ) from None


def cmd_capture(args: argparse.Namespace) -> str:
    from matscan.capture.acquire import AcquireConfig, acquire, target_maps
    from matscan.hardware.cameras import open_camera
    from matscan.hardware.leds import open_leds
    from matscan.rig import resolve_rig

    _check_capture_out(args)
    rig = resolve_rig(args.rig)
    cfg = AcquireConfig(
        lights=rig.subset(args.lights) if args.lights else None,
        backlight=args.backlight,
        target=args.target,
        exposure_s=args.exposure,
        level=args.level,
        max_saturated=args.max_saturated,
        retakes=args.retakes,
    )
    leds, board = open_leds(args.leds)
    camera = None
    try:
        targets = None
        if args.target and args.camera.startswith("virtual:"):
            from matscan.mapset import read_mapset
            from matscan.samples import maps_folder

            size = read_mapset(maps_folder(args.camera[len("virtual:") :])).size[0]
            targets = target_maps(args.target, size)
        camera = open_camera(
            args.camera, rig, leds, args.seed, targets, aperture=args.aperture, iso=args.iso, raw=not args.jpeg
        )
        ask = _ask_operator if sys.stdin.isatty() else None
        try:
            record = acquire(args.out, rig, camera, leds, cfg, progress=True, ask=ask)
        except KeyboardInterrupt:
            raise KeyboardInterrupt(
                f"the photos taken so far are in {args.out}; run the same command to resume"
            ) from None
    finally:
        if camera is not None:
            camera.close()
        leds.close()
        if board is not None:
            board.close()
    exposure = f"{record['exposure_s']:.4g} s" if record["exposure_s"] else "set by the camera"
    drift = f", sample moved {record['drift_px']:.2f} px" if record.get("drift_px") is not None else ""
    return (
        f"capture: wrote {args.out} ({record['frames']} photos, exposure {exposure}, "
        f"{record['retakes']} retaken{drift}; camera {record['camera']}, LEDs {record['leds']})"
    )


def cmd_batch(args: argparse.Namespace) -> str:
    from matscan.batch import batch
    from matscan.reconstruct import ReconstructConfig

    cfg = ReconstructConfig(
        model=args.model,
        anyrig=args.anyrig,
        refine=args.refine,
        solver=args.solver,
        validate=args.validate,
        self_calibrate=args.self_calibrate or args.self_calibrate_positions or args.shared_f0 is not None,
        self_calibrate_positions=args.self_calibrate_positions or args.shared_f0 is not None,
        shared_f0=args.shared_f0,
        led_gradient=args.led_gradient,
        exr=args.exr,
        mirrors=args.mirrors,
        calibration=_calibration_arg(args.calibration),
    )

    def report(name: str, result: dict) -> None:
        if result["state"] == "failed":
            print(f"matscan: warning: {name}: {result['error']}", file=sys.stderr)

    manifest = batch(
        args.captures,
        args.out,
        cfg,
        workers=args.workers,
        scheduler=args.scheduler,
        threads=args.threads,
        retry_failed=args.retry_failed,
        redo=args.redo,
        progress=True,
        on_result=report,
    )
    entries = manifest["captures"].values()
    done = sum(e["state"] == "done" for e in entries)
    failed = sum(e["state"] == "failed" for e in entries)
    summary = (
        f"batch: {done} done, {failed} failed of {len(manifest['captures'])}; catalogue {Path(args.out) / 'index.html'}"
    )
    return (summary, 1) if failed else summary  # a failed capture is reported in the exit status too


def cmd_train_anyrig(args: argparse.Namespace) -> str:
    from matscan.anyrig import AnyRigConfig, TrainAnyRig, train

    miscal = _vector(args.miscalibration, 2, "--miscalibration")
    tilt = _vector(args.tilt, 2, "--tilt")
    cfg = TrainAnyRig(
        size=args.size,
        batch=args.batch,
        max_photos=args.max_photos,
        lr=args.lr,
        seed=args.seed,
        prior=args.prior,
        device=args.device,
        library=tuple(args.library),
        library_prob=args.library_prob,
        library_metal_prob=args.library_metal_prob,
        ema=args.ema,
        miscal_degrees=miscal[0],
        miscal_intensity=miscal[1],
        miscal_min_photos=args.miscal_from,
        render_weight=args.render_weight,
        render_lights=args.render_lights,
        tilt_degrees=tilt[0],
        tilt_prob=tilt[1],
    )
    net_cfg = None if args.ps_skip is None else AnyRigConfig(ps_skip=args.ps_skip)
    result = train(args.out, cfg, minutes=args.minutes, max_steps=args.max_steps, progress=True, net_cfg=net_cfg)
    return (
        f"train-anyrig: {result['steps']} steps in all; checkpoint {result['checkpoint']}, weights {result['weights']}"
    )


def cmd_synth(args: argparse.Namespace) -> str:
    from matscan.data import synthesize

    t0 = time.perf_counter()
    out = synthesize(
        args.out,
        args.count,
        size=args.size,
        seed=args.seed,
        family=args.family,
        rig=args.rig,
        lights=args.lights,
        overwrite=args.overwrite,
        progress=True,
        overwrite_any=args.overwrite_any,
    )
    seconds = time.perf_counter() - t0
    return f"synth: wrote {args.count} materials with captures and {out}/contact_sheet.png in {seconds:.1f} s"


#: ``matscan train``'s moving average of the weights for a new run (runs/dome24-ema-cpu/README.md)
TRAIN_EMA = 0.999


def cmd_train(args: argparse.Namespace) -> str:

    from matscan.train import TrainConfig, check_train_config, read_run_config, train

    values = {}
    if args.config:
        from matscan.jsonfile import read_json

        path = Path(args.config)
        values = read_json(path)
        if not isinstance(values, dict):
            raise MatscanError(f"{path}: expected a JSON object of training settings")
        check_train_config(values, str(path))  # each setting's type, named in the file
    for key in (
        "preset",
        "variant",
        "rig",
        "crop",
        "batch",
        "lr",
        "steps",
        "render_lights",
        "render_with",
        "named_subset_prob",
        "workers",
        "seed",
        "val_every",
        "val_count",
        "snapshot_every",
        "ema",
        "checkpoint_minutes",
        "init",
        "prior",
        "device",
        "prefetch",
    ):
        value = getattr(args, key)
        if value is not None:
            values[key] = value
    if args.maps:
        values["maps"] = tuple(m.strip() for m in args.maps.split(","))
    if "ema" not in values:  # a new run averages its weights; a resumed one keeps what it began with
        if args.config:  # a run's config.json from before the average: none, so the run is remade as it was
            values["ema"] = 0.0
        elif (kept := read_run_config(args.out)) is not None:
            values["ema"] = kept.ema
        else:
            values["ema"] = TRAIN_EMA
    cfg = TrainConfig.from_dict(values, args.config or "train")
    res = train(cfg, args.out, max_steps=args.max_steps, max_minutes=args.minutes)
    val = ", ".join(f"{k} {v:.4f}" for k, v in res["validation"].items()) or "no validation yet"
    return f"train: {args.out} at step {res['step']} ({res['seconds'] / 3600:.2f} h in all); {val}"


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (no usage block), exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="matscan", description="Photographs of a flat material under known lights → material maps.")
    parser.add_argument("--version", action="version", version=f"matscan {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="render a capture folder of a map set through a rig (the virtual rig)")
    p.add_argument("maps", metavar="MAPS", help="map set folder, or @sample for the built-in sample")
    p.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to write")
    p.add_argument("--rig", default="dome24", help="built-in rig name or rig .json file (default dome24)")
    p.add_argument("--lights", default=None, help="named subset (24, 6, …) or indices like 0,4,8 (default all)")
    p.add_argument("--size", type=size_int, default=None, help="resample maps to SIZE×SIZE pixels first")
    p.add_argument(
        "--noise",
        type=non_negative_float,
        default=0.002,
        metavar="SIGMA",
        help="read noise std (fraction of full scale); >0 also adds photon shot noise; 0 = noise-free (default 0.002)",
    )
    p.add_argument(
        "--full-well",
        type=positive_float,
        default=20000.0,
        help="electrons at full scale, sets shot noise (default 20000)",
    )
    p.add_argument(
        "--exposure",
        type=_number(float, 0.0, 1e6, low_open=True),
        default=1.0,
        help="radiance multiplier before the sensor (default 1)",
    )
    p.add_argument("--encoding", choices=["srgb", "linear"], default="srgb", help="file encoding (default srgb)")
    p.add_argument(
        "--bits",
        type=int,
        choices=[8, 16, 32],
        default=None,
        help="8/16-bit PNG, or 32 = float EXR (default 8 for srgb, 32 for linear)",
    )
    p.add_argument("--seed", type=seed_int, default=0, help="noise seed (default 0)")
    _overwrite_folder(p)
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("reconstruct", help="capture → maps (networks, then refinement by inverse rendering)")
    p.add_argument("capture", metavar="CAPTURE", help="capture folder, or @sample for the built-in sample capture")
    p.add_argument("--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--model", default="default", help="shipped model name, a .safetensors file, or none")
    p.add_argument(
        "--anyrig",
        default="none",
        metavar="default|WEIGHTS|none",
        help="an any-rig network whose maps the solver starts from on rigs the model does not read (another dome, "
        "a flash), from 2 photos: default (the shipped one), or the weights.safetensors or checkpoint of a matscan "
        "train-anyrig run; default none: flat maps",
    )
    p.add_argument(
        "--refine",
        default="auto",
        choices=["auto", "on", "off"],
        help="refine by inverse rendering (auto, lm solver with the networks: 1 photo, the networks alone; "
        "2 or 3, networks + solver unless the solver alone predicts photos left out at least 5%% better; from 4, "
        "always; adam: from 10; always without networks; docs/results.md)",
    )
    p.add_argument(
        "--solver",
        default="lm",
        choices=["lm", "adam"],
        help="lm (default): second-order fit of every pixel at once, with confidence maps; "
        "adam: first-order descent (with --emissive, always)",
    )
    p.add_argument("--steps", type=positive_int, default=150, help="adam refinement steps per tile (default 150)")
    p.add_argument("--tile", type=_number(int, 16), default=512, help="network tile size in pixels (default 512)")
    p.add_argument(
        "--mirrors",
        action="store_true",
        help="average the networks' maps over the rig's mirror symmetries that keep the lit lights (dome24: "
        "2 views at 1, 2 and 10 photos, 4 at 6, 8 at 24): networks' maps a little better, networks' time "
        "× views; off by default, as the solver's maps gained at some counts, lost at one (docs/results.md)",
    )
    p.add_argument("--emissive", action="store_true", help="also fit an emissive map (fluorescent inks)")
    p.add_argument(
        "--self-calibrate",
        dest="self_calibrate",
        action="store_true",
        help="estimate each light's RGB intensity with the maps, from the photos alone (8 photos or more); "
        "writes self_calibration.json, a calibration later captures can name",
    )
    p.add_argument(
        "--self-calibrate-positions",
        dest="self_calibrate_positions",
        action="store_true",
        help="--self-calibrate, and each near light's position too, fitted jointly with the intensities and "
        "the maps (about 1 mm on simulated domes; helps samples with relief or texture, can cost a flat "
        "uniform one: docs/rti.md)",
    )
    f0 = p.add_mutually_exclusive_group()
    f0.add_argument(
        "--shared-f0",
        dest="shared_f0",
        action="store_const",
        const=True,
        default=None,
        help="--self-calibrate-positions with one F0 for the sample's dielectric pixels in that fit, its default: "
        "on simulated domes whose LEDs have their own brightness gradients, relighting 0.16-0.27 dB nearer the "
        "ideal dome's on average (paper, grass, gravel: up to 2.8 dB) than with --own-f0 (docs/rti-record.md)",
    )
    f0.add_argument(
        "--own-f0",
        dest="shared_f0",
        action="store_const",
        const=False,
        help="--self-calibrate-positions with each pixel's own F0 in that fit, as before the shared one became its "
        "default: a third of the time at 512² (32 s against 105 s on 2 cores), relit worse on most simulated "
        "materials (docs/rti-record.md)",
    )
    p.add_argument(
        "--led-gradient",
        dest="led_gradient",
        choices=LED_GRADIENTS,
        default="auto",
        help="with --self-calibrate: what fixes the LEDs' brightness gradient from one side of the dome to the "
        "other, which a tilted sample photographs like: fit (the sample lies level), none (the LEDs have no "
        "gradient; the sample's tilt is fitted), choose (both, the one that re-renders the photos better kept, "
        "none if by 1%%, or within 1%% where the level gains' gradient is at least 0.15), auto (the default: "
        "choose, but none where the calibration scales every light, as a "
        "grey card measures them); on simulated domes with LEDs ±20%% at random, fit relit 0.8-2.0 dB better on "
        "average than none, and on samples tilted 5° up to 22 dB worse; choose within 0.15 dB of fit on level "
        "samples and 0.4-22 dB better where they differed on tilted ones, at twice the time (docs/rti-record.md)",
    )
    p.add_argument(
        "--calibration",
        default=None,
        metavar="FILE",
        help="a calibration file to read instead of the one the capture names: the places and scales of the "
        "same dome merged from other captures' self_calibration.json (calibrate --merge), for a sample whose "
        "photos cannot place the lights; with --self-calibrate-positions the lights are fitted from there, or "
        'kept there where the photos confirm or cannot read their intensities (docs/rti.md, "A dome calibrated '
        'once"); the capture is not changed',
    )
    p.add_argument(
        "--validate",
        type=non_negative_int,
        default=0,
        metavar="K",
        help="leave K photos out, reconstruct, and report their re-rendering error",
    )
    p.add_argument("--exr", action="store_true", help="also write every map as float EXR (exr/)")
    p.add_argument(
        "--directx-normals",
        dest="directx_normals",
        action="store_true",
        help="also write normal_directx.png (green flipped)",
    )
    _overwrite_folder(p)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser(
        "calibrate", help="write calibration.json from a ColorChecker photo and/or a grey card, or merge calibrations"
    )
    p.add_argument("--out", required=True, help="calibration.json to write (put it in the capture folder)")
    p.add_argument("--grey", default=None, metavar="CAPTURE", help="capture of an 18%% grey card under each light")
    p.add_argument("--flat-fields", dest="flat_fields", action="store_true", help="also write per-light flat fields")
    p.add_argument(
        "--positions",
        action="store_true",
        help="also fit each near light's position to its grey-card photo (the card must fill the field)",
    )
    p.add_argument("--chart", default=None, metavar="PHOTO", help="photo of a ColorChecker Classic (24 patches)")
    p.add_argument("--chart-encoding", dest="chart_encoding", choices=["srgb", "linear"], default="srgb")
    p.add_argument(
        "--corners",
        default=None,
        metavar="X,Y,…",
        help="outer corners of the chart's grid of patches TL,TR,BR,BL as 8 numbers in pixels "
        "(default: found in the photo)",
    )
    p.add_argument(
        "--merge",
        nargs="+",
        default=None,
        metavar="FILE",
        help="merge calibration files of one dome instead (the self_calibration.json of several captures): "
        "each light's position their mean, its scale their geometric mean (docs/rti.md, "
        '"A dome calibrated once")',
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing calibration file")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("evaluate", help="simulate, reconstruct and score map sets (the accuracy study)")
    p.add_argument(
        "mapsets",
        nargs="+",
        metavar="MAPSETS",
        help="map set folders, procedural:N (unseen procedural materials), photos (texture photographs), "
        "artist (artist-style map sets: foil print, leather, embossed coins, lacquer, worn metal)",
    )
    p.add_argument("--out", required=True, help="folder for results.json, results.md and plots")
    p.add_argument("--lights", default="1,2,3,6,10,16,24", help="light subsets (default the paper's Table 4)")
    p.add_argument(
        "--methods",
        default="baseline,nets,nets+refine,fit",
        help="baseline, nets, nets+refine, fit, auto, hsh (the RTI field's per-pixel curve fit, relighting "
        "only, from 9 lights), or nets:FILE / nets+refine:FILE / auto:FILE for other weights",
    )
    p.add_argument(
        "--jobs", type=positive_int, default=1, help="worker processes, one capture each at a time (default 1)"
    )
    p.add_argument("--encodings", default="srgb8,linear16", help="capture encodings: srgb8, linear16")
    p.add_argument(
        "--size",
        type=_number(int, 8, MAX_SIZE),
        default=256,
        help="material size in pixels, covering the rig field (default 256: 0.47 mm a pixel on dome24, the coarse end "
        "of the scales the networks are trained on)",
    )
    p.add_argument("--steps", type=positive_int, default=150, help="refinement steps (default 150)")
    _overwrite_folder(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("render", help="render a map set under one point light")
    p.add_argument("maps", metavar="MAPS", help="map set folder, or @sample")
    p.add_argument("--out", required=True, metavar="IMAGE", help=".png (sRGB 8-bit) or .exr (linear float)")
    p.add_argument("--light", required=True, metavar="X,Y,Z", help="light position in mm (sample frame)")
    p.add_argument("--rig", default="dome24", help="rig giving camera, field and reference distance")
    p.add_argument(
        "--intensity", type=_number(float, 0.0, MAX_INTENSITY), default=1.0, help="light intensity (default 1)"
    )
    p.add_argument(
        "--exponent",
        type=_number(float, 0.0, MAX_EXPONENT),
        default=0.0,
        help="emission exponent m (default 0, isotropic)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing image")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("synth", help="write procedural materials, their captures and a contact sheet")
    p.add_argument("--out", required=True, help="folder to write")
    p.add_argument("--count", type=positive_int, required=True, help="how many materials")
    p.add_argument("--size", type=_number(int, 8, MAX_SIZE), default=256, help="map size in pixels (default 256)")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--family", default=None, help="one family only (default: drawn by the prior's weights)")
    p.add_argument("--rig", default="dome24")
    p.add_argument("--lights", default=None, help="subset of lights to photograph (default all)")
    _overwrite_folder(p)
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("train", help="train the map networks (resumes a run folder that has a checkpoint)")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder (config, checkpoint, logs)")
    p.add_argument("--config", default=None, help="JSON file of TrainConfig fields (flags override it)")
    p.add_argument("--preset", default=None, help="network shape: paper, cpu, tiny (default cpu)")
    p.add_argument("--variant", default=None, help="four, one_encoder, global_track, no_global_skip")
    p.add_argument("--maps", default=None, help="train only these networks, e.g. diffuse,normal")
    p.add_argument("--rig", default=None)
    p.add_argument("--crop", type=_number(int, 16), default=None)
    p.add_argument("--batch", type=positive_int, default=None)
    p.add_argument("--lr", type=positive_float, default=None)
    p.add_argument("--steps", type=positive_int, default=None, help="total steps of the run")
    p.add_argument("--render-lights", dest="render_lights", type=positive_int, default=None)
    p.add_argument(
        "--render-with",
        dest="render_with",
        choices=("own", "joint"),
        default=None,
        help="rendering loss: own (each network's, the other maps true; the paper's, the default) "
        "or joint (all trained maps' predictions rendered together)",
    )
    p.add_argument(
        "--named-subset-prob",
        dest="named_subset_prob",
        type=float,
        default=None,
        metavar="P",
        help="share of samples lit by one of the rig's named subsets, the rest by random ones (default 0.5; "
        "docs/results.md 'Which lights' measures what the default costs on other subsets)",
    )
    p.add_argument("--workers", type=non_negative_int, default=None, help="data worker processes")
    p.add_argument("--seed", type=seed_int, default=None)
    p.add_argument("--val-every", dest="val_every", type=non_negative_int, default=None)
    p.add_argument("--val-count", dest="val_count", type=positive_int, default=None)
    p.add_argument(
        "--snapshot-every",
        dest="snapshot_every",
        type=non_negative_int,
        default=None,
        metavar="N",
        help="keep the weights every N steps in RUN/snapshots (float16, filled from --init), "
        "to score the run along its way (default 0: none)",
    )
    p.add_argument(
        "--ema",
        type=_number(float, 0, 1),
        default=None,
        metavar="DECAY",
        help="keep the weights' moving average, this decay per step (0.999: about the last 1,000 steps); "
        "exports and snapshots take it in place of the weights (default: 0.999 for a new run, a resumed run's "
        "own, a --config file's own or none; 0: none)",
    )
    p.add_argument("--checkpoint-minutes", dest="checkpoint_minutes", type=positive_float, default=None)
    p.add_argument(
        "--init",
        default=None,
        metavar="WEIGHTS",
        help="start a new run from trained weights (checkpoint or exported file), with a fresh optimiser",
    )
    p.add_argument(
        "--prior",
        default=None,
        help="material prior: v1 (the default), v2 (adds relief, varying specular, dark glossy), "
        "v3 (adds dark glossy in deep relief), v4 (v3 with dark glossy drawn twice as often), "
        "v5 (adds bright glossy coats)",
    )
    p.add_argument("--device", default=None, help="auto (default: cuda when there is one), cpu, cuda, cuda:N")
    p.add_argument("--prefetch", type=positive_int, default=None, help="batches each data worker prepares ahead")
    p.add_argument(
        "--max-steps", dest="max_steps", type=non_negative_int, default=None, help="stop after this many more steps"
    )
    p.add_argument("--minutes", type=positive_float, default=None, help="stop after this much wall time")
    p.set_defaults(func=cmd_train)

    from matscan.capture.rti import LP_Y, LP_Y_DEFAULT, RTI_FIELD_WIDTH_MM

    y_help = (
        f"which way the .lp file's +y points in the image: up (toward row 0) or down (default {LP_Y_DEFAULT}; "
        "see docs/rti.md)"
    )
    p = sub.add_parser("rig", help="rig files: from and to RTI .lp light files; lights from chrome spheres")
    rig_sub = p.add_subparsers(dest="rig_command", required=True)
    q = rig_sub.add_parser("from-lp", help="a rig of directional lights from an RTI .lp file")
    q.add_argument("lp", metavar="LP", help=".lp light file")
    q.add_argument("--out", required=True, help="rig .json to write")
    q.add_argument("--y", choices=LP_Y, default=LP_Y_DEFAULT, help=y_help)
    q.add_argument(
        "--field-mm",
        default=None,
        metavar="W,H",
        help=f"sample field the photos cover, mm (default {RTI_FIELD_WIDTH_MM:g},{RTI_FIELD_WIDTH_MM:g})",
    )
    q.add_argument("--overwrite", action="store_true", help="replace an existing file")
    q.set_defaults(func=cmd_rig_from_lp)
    q = rig_sub.add_parser("to-lp", help="an RTI .lp file of a rig's lights (directions from the field's centre)")
    q.add_argument(
        "rig",
        metavar="RIG",
        help="built-in rig name, rig .json file, or a capture folder (its photos' lights, named by the photos)",
    )
    q.add_argument("--out", required=True, help=".lp file to write")
    q.add_argument("--y", choices=LP_Y, default=LP_Y_DEFAULT, help=y_help)
    q.add_argument("--overwrite", action="store_true", help="replace an existing file")
    q.set_defaults(func=cmd_rig_to_lp)

    q = rig_sub.add_parser(
        "from-sphere", help="light directions from the highlight on a chrome sphere in each photo of a folder"
    )
    q.add_argument("folder", metavar="FOLDER", help="folder of photos, one per light, the sphere in each")
    q.add_argument(
        "--sphere",
        metavar="CX,CY,R",
        help="the sphere's centre (column, row) and radius, pixels (default: found in the photos)",
    )
    q.add_argument(
        "--fov",
        type=_number(float, 0, 180, low_open=True),
        default=None,
        metavar="DEG",
        help="the camera's angle of view across the photos' width, degrees (a 50 mm lens on a 36 mm wide sensor: "
        "39.6); the sphere is then seen through a pinhole (centred on the photo unless --principal-point), not from "
        "straight above "
        "(default: orthographic, as RTI software assumes)",
    )
    q.add_argument(
        "--principal-point",
        dest="principal_point",
        metavar="CX,CY",
        help="with --fov: where the optical axis meets the photos (column, row; pixels), as a lens calibration "
        "gives it (default: the photos' centre)",
    )
    q.add_argument(
        "--k1",
        type=_number(float),
        default=0.0,
        metavar="K",
        help="with --fov: the lens's radial distortion, OpenCV's first coefficient k1 (negative: barrel; default 0)",
    )
    q.add_argument(
        "--distortion",
        metavar="K1,K2,P1,P2[,K3]",
        help="with --fov: the lens's distortion as OpenCV's coefficients in its order (what cv2.calibrateCamera "
        "gives as distCoeffs; radial k1, k2, k3, tangential p1, p2; default none)",
    )
    q.add_argument("--out", required=True, help=".lp light file or rig .json to write")
    q.add_argument("--y", choices=LP_Y, default=LP_Y_DEFAULT, help=y_help)
    q.add_argument(
        "--encoding", choices=["srgb", "linear"], default="srgb", help="how 8/16-bit photos are encoded (default srgb)"
    )
    q.add_argument("--overwrite", action="store_true", help="replace an existing file")
    q.set_defaults(func=cmd_rig_from_sphere)

    q = rig_sub.add_parser(
        "from-spheres",
        help="near-light positions from their highlights on two or more chrome spheres "
        "(or one, on a dome of known radius)",
    )
    q.add_argument(
        "capture", metavar="CAPTURE", help="capture of the spheres under each light (capture --target sphere)"
    )
    q.add_argument(
        "--sphere",
        action="append",
        required=True,
        metavar="X,Y,Z,R",
        help="a sphere's centre and radius, mm, in the sample frame (give two or more, or one with --dome-radius)",
    )
    q.add_argument(
        "--dome-radius",
        dest="dome_radius",
        type=_number(float, 0, low_open=True),
        metavar="MM",
        help="the lights sit on a shell of this radius (a hemispherical dome): each is placed where its highlight's "
        "ray meets it, so one sphere suffices",
    )
    q.add_argument(
        "--dome-centre",
        dest="dome_centre",
        metavar="X,Y,Z",
        help="with --dome-radius: the shell's centre, mm, in the sample frame (default 0,0,0: the field's centre)",
    )
    q.add_argument("--out", required=True, help="rig .json to write (the capture's rig, lights moved)")
    q.add_argument("--overwrite", action="store_true", help="replace an existing file")
    q.set_defaults(func=cmd_rig_from_spheres)

    p = sub.add_parser("import-rti", help="a capture folder from an RTI folder (photos and an .lp light file)")
    p.add_argument("folder", metavar="FOLDER", help="RTI folder: photos and one .lp file")
    p.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to write")
    p.add_argument("--lp", default=None, help="the .lp file, when the folder has none or several")
    p.add_argument("--y", choices=LP_Y, default=LP_Y_DEFAULT, help=y_help)
    p.add_argument(
        "--field-width-mm",
        type=positive_float,
        default=None,
        help=f"width of the field the photos cover, mm (default {RTI_FIELD_WIDTH_MM:g}; the height follows)",
    )
    _overwrite_folder(p)
    p.set_defaults(func=cmd_import_rti)

    p = sub.add_parser("capture", help="take a capture with a camera and the LED controller (resumes when interrupted)")
    p.add_argument("--rig", default="dome24", help="built-in rig name or rig .json file (default dome24)")
    p.add_argument(
        "--camera",
        required=True,
        help="virtual:MAPS (render a map set folder or @sample), folder:PATH (photos a camera's software saves), "
        "or gphoto2 (a tethered camera; the camera extra)",
    )
    p.add_argument(
        "--leds",
        default="virtual",
        help="serial:PORT (the LED board), simulated (the firmware on this computer, over a pseudo-terminal), "
        "or virtual (default)",
    )
    p.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to write (or to resume)")
    p.add_argument("--lights", default=None, help="named subset (24, 6, …) or indices like 0,4,8 (default all)")
    p.add_argument(
        "--backlight",
        action="store_true",
        help="also the green and blue backlight photos, with the sample and then of the empty stage (alpha)",
    )
    p.add_argument(
        "--target", choices=["grey", "chart", "sphere"], default=None, help="photograph a calibration target"
    )
    p.add_argument("--exposure", type=positive_float, default=None, help="fixed exposure, seconds (default: chosen)")
    p.add_argument("--level", type=positive_float, default=1.0, help="LED level, above 0 and at most 1 (default 1)")
    p.add_argument(
        "--max-saturated",
        dest="max_saturated",
        type=non_negative_float,
        default=0.001,
        help="largest fraction of saturated pixels in an LED photo, below 1 (default 0.001)",
    )
    p.add_argument("--retakes", type=non_negative_int, default=2, help="retakes of a frame that fails its checks")
    p.add_argument("--seed", type=seed_int, default=0, help="noise seed of the virtual camera (default 0)")
    p.add_argument("--aperture", default=None, help="gphoto2: the aperture as the camera lists it (for example 8)")
    p.add_argument("--iso", default=None, help="gphoto2: the ISO as the camera lists it (for example 100)")
    p.add_argument("--jpeg", action="store_true", help="gphoto2: JPEG instead of RAW")
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("batch", help="reconstruct many captures with the same settings (Dask), and a catalogue")
    p.add_argument("captures", nargs="+", metavar="CAPTURES", help="capture folders, glob patterns, or list files")
    p.add_argument("--out", required=True, metavar="DIR", help="batch folder: one output per capture, the manifest")
    p.add_argument("--workers", type=positive_int, default=None, help="local worker processes (default: one per core)")
    p.add_argument("--scheduler", default=None, help="address of a running Dask scheduler to use instead")
    p.add_argument(
        "--threads", type=positive_int, default=None, help="torch threads per task (default: cores ÷ workers)"
    )
    p.add_argument("--retry-failed", dest="retry_failed", action="store_true", help="run the failed captures again")
    p.add_argument("--redo", action="store_true", help="recompute every capture, finished ones too")
    p.add_argument("--model", default="default", help="shipped model name, a .safetensors file, or none")
    p.add_argument("--anyrig", default="none", metavar="default|WEIGHTS|none", help="as for reconstruct")
    p.add_argument("--refine", default="auto", choices=["auto", "on", "off"], help="as for reconstruct")
    p.add_argument("--solver", default="lm", choices=["lm", "adam"], help="as for reconstruct")
    p.add_argument("--validate", type=non_negative_int, default=0, metavar="K", help="leave K photos out of each")
    p.add_argument("--self-calibrate", dest="self_calibrate", action="store_true", help="as for reconstruct")
    p.add_argument(
        "--self-calibrate-positions", dest="self_calibrate_positions", action="store_true", help="as for reconstruct"
    )
    f0 = p.add_mutually_exclusive_group()
    f0.add_argument("--shared-f0", dest="shared_f0", action="store_const", const=True, help="as for reconstruct")
    f0.add_argument("--own-f0", dest="shared_f0", action="store_const", const=False, help="as for reconstruct")
    p.add_argument(
        "--led-gradient", dest="led_gradient", choices=LED_GRADIENTS, default="auto", help="as for reconstruct"
    )
    p.add_argument("--calibration", default=None, metavar="FILE", help="as for reconstruct, for every capture")
    p.add_argument("--exr", action="store_true", help="also write every map as float EXR")
    p.add_argument("--mirrors", action="store_true", help="as for reconstruct")
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("train-anyrig", help="train the any-rig network (resumes a run folder with a checkpoint)")
    p.add_argument(
        "--out", required=True, metavar="RUN", help="run folder: checkpoint.safetensors, log.csv, weights.safetensors"
    )
    p.add_argument("--minutes", type=positive_float, default=10.0, help="how long to train (default 10)")
    p.add_argument("--max-steps", dest="max_steps", type=positive_int, default=None, help="stop after this step")
    p.add_argument("--size", type=positive_int, default=64, help="crop size, a multiple of 4 (default 64)")
    p.add_argument("--batch", type=positive_int, default=4, help="samples per step (default 4)")
    p.add_argument("--max-photos", dest="max_photos", type=positive_int, default=12, help="most photos a sample")
    p.add_argument("--lr", type=positive_float, default=3e-4, help="Adam's learning rate (default 3e-4)")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--prior", default="v2", help="procedural material prior, as for train (default v2)")
    p.add_argument(
        "--library",
        nargs="+",
        default=[],
        metavar="MAPSET",
        help="map set folders mixed with the procedural materials (tools/photo_library.py builds some)",
    )
    p.add_argument(
        "--library-prob",
        dest="library_prob",
        type=_number(float, 0, 1),
        default=0.5,
        metavar="P",
        help="share of samples drawn from --library (default 0.5)",
    )
    p.add_argument(
        "--library-metal-prob",
        dest="library_metal_prob",
        type=_number(float, 0, 1),
        default=0.0,
        metavar="P",
        help="share of those given metal patches, as train's library_metal_prob (default 0)",
    )
    p.add_argument(
        "--ema",
        type=_number(float, 0, 1),
        default=0.0,
        metavar="DECAY",
        help="also keep the weights' moving average, this decay per step (0.999: about the last 1,000 steps), "
        "which the checkpoint's users load (default 0: none)",
    )
    p.add_argument(
        "--miscalibration",
        default="0,0",
        metavar="DEG,REL",
        help="photograph each sample under lights other than those the network is told: each light's place off "
        "by |N(0, DEG)| degrees and its intensity by N(0, REL), as on real domes and handheld captures "
        "(default 0,0)",
    )
    p.add_argument(
        "--miscal-from",
        dest="miscal_from",
        type=positive_int,
        default=1,
        metavar="N",
        help="miscalibrate only samples of at least N photos: a single photo cannot show that its light is off "
        "(default 1: every sample)",
    )
    p.add_argument(
        "--render-weight",
        dest="render_weight",
        type=_number(float, 0, 100),
        default=0.0,
        metavar="W",
        help="also judge the maps by rendering them under novel lights, this weight (the paper's λ_r is 0.0417; "
        "default 0: maps only)",
    )
    p.add_argument(
        "--render-lights",
        dest="render_lights",
        type=_number(int, 1, 64),
        default=8,
        metavar="K",
        help="novel lights per sample for --render-weight (default 8)",
    )
    p.add_argument(
        "--tilt",
        default="0,0.5",
        metavar="DEG,SHARE",
        help="lay that share of the samples tilted, every normal turned by up to DEG degrees, as a sample not "
        "lying flat (default 0,0.5: none)",
    )
    p.add_argument("--device", default="auto", help="auto (CUDA when there is one), cpu or cuda")
    p.add_argument(
        "--ps-skip",
        dest="ps_skip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="whether a new run's network gets the per-pixel photometric-stereo estimate and corrects it "
        "(default: yes; a resumed run keeps its own; docs/rti-record.md)",
    )
    p.set_defaults(func=cmd_train_anyrig)

    p = sub.add_parser("sheet", help="contact sheet PNG of a capture or map set folder")
    p.add_argument("folder", metavar="FOLDER", help="capture or map set folder (or @sample)")
    p.add_argument("--maps", default=None, help="also show this map set (folder or @sample)")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--columns", type=positive_int, default=None)
    p.add_argument("--overwrite", action="store_true", help="replace an existing PNG")
    p.set_defaults(func=cmd_sheet)

    p = sub.add_parser(
        "export", help="a map set (or a public library's maps) as glTF, GLB, MaterialX, USD and PNG/EXR maps"
    )
    p.add_argument(
        "maps",
        metavar="MAPS",
        help="a map set or reconstruction folder, a folder of maps from a PBR library, a Deschaintre panel "
        "image, or @sample",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write (the maps and the exports)")
    p.add_argument(
        "--field-mm",
        dest="field_mm",
        default=None,
        metavar="W,H",
        help="the sample's size in mm (default: what the maps' matscan.json records, else the rig's field)",
    )
    p.add_argument("--rig", default="dome24", help="rig whose field the maps cover when nothing says (dome24)")
    p.add_argument("--exr", action="store_true", help="also write every map as float EXR (exr/)")
    p.add_argument(
        "--directx-normals",
        dest="directx_normals",
        action="store_true",
        help="also write normal_directx.png (green flipped)",
    )
    p.add_argument(
        "--normal-convention",
        dest="normal_convention",
        choices=("auto", "opengl", "directx"),
        default="auto",
        help="how a library folder's normal map is encoded (auto: OpenGL unless its file name says DX)",
    )
    _overwrite_folder(p)
    p.set_defaults(func=cmd_export)
    return parser


def _one_line(text: str) -> str:
    """A message on one line, its control characters (a NUL in a file name, say) shown
    escaped rather than sent to the terminal."""
    line = " ".join(str(text).split())
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in line)


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM ends a command as Ctrl-C does: temporaries removed, outputs untouched."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:  # the command itself: started again once with glibc told to reuse freed memory
        from matscan.allocator import environment

        env = environment()
        if env is not None:
            sys.stdout.flush()
            sys.stderr.flush()
            try:
                os.execve(sys.executable, [sys.executable, "-m", "matscan.cli", *sys.argv[1:]], env)
            except OSError:  # not started again: run as it is
                pass
    parser = build_parser()
    args = parser.parse_args(_join_vectors(sys.argv[1:] if argv is None else argv))
    previous = signal.signal(signal.SIGTERM, _terminate)
    code = 0
    try:
        result = args.func(args)
        if isinstance(result, tuple):  # (summary, exit status): done, but not all of it
            result, code = result
        print(result)
    except MatscanError as exc:
        print(f"matscan: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file system refusal the checks could not foresee (a full disk mid-write)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"matscan: error: {_one_line(where + (exc.strerror or str(exc)))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"matscan: interrupted; {str(exc) or 'nothing was written'}", file=sys.stderr)
        return 130
    except (MemoryError, RuntimeError) as exc:  # the allocators' "out of memory", nothing else
        text = str(exc)
        if not isinstance(exc, MemoryError) and "allocate" not in text:
            raise
        print(
            "matscan: error: not enough memory for this work on this machine "
            f"({_one_line(text)[:120] or type(exc).__name__}); nothing was written. Try smaller images, "
            "fewer lights, or a smaller --tile",
            file=sys.stderr,
        )
        return 2
    finally:
        signal.signal(signal.SIGTERM, previous)
    return code


def _overwrite_folder(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing output folder that holds a previous matscan output (never an input)",
    )
    p.add_argument(
        "--overwrite-any",
        dest="overwrite_any",
        action="store_true",
        help="with --overwrite: replace the folder even if it holds files matscan did not write (they are deleted)",
    )


if __name__ == "__main__":
    sys.exit(main())
