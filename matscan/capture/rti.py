"""Reflectance Transformation Imaging (RTI) light files and captures.

An RTI dome (or a handheld light with a chrome sphere in the frame) describes its
lights in an ``.lp`` file: the number of photos on the first line, then one line per
photo, ``FILE lx ly lz``, a unit vector toward the light with x toward the image's
right and z toward the camera. The lights are taken as directional and the camera as
orthographic (shared/design.md, "Directional lights and orthographic cameras").

The format's y axis: the files in use do not say whether +y points to the image's top
or bottom. matscan's sample frame has +y at the image's top (row 0 is the +y edge), so
``y="up"`` keeps the file's y and ``y="down"`` negates it. :func:`y_convention_evidence`
tells the two apart on a capture from the photos alone: a per-pixel fit relights both
equally well (mirroring y in every light and normal changes no dot product), but only
the right one gives a normal field that is the gradient field of a surface (little
curl); see :data:`LP_Y_DEFAULT` for what the real capture in the tests shows.

Quirks handled on reading: a missing or wrong count line (the list wins, with a
warning), blank lines, trailing spaces, tabs, Windows line ends and paths (only the
file name is kept), directions not quite unit length (normalised; more than 5% off is
an error), and directions at or below the sample plane (an error naming the line).
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path, PureWindowsPath
from typing import Any

import torch

from matscan.errors import MatscanError, input_error, not_a_folder
from matscan.imagefile import read_image
from matscan.jsonfile import check_file_name, dumps, short_repr
from matscan.outputs import claim_output
from matscan.rig import MAX_MM, Camera, Light, Rig, rig_to_dict

#: The ``.lp`` y convention matscan assumes unless told: established on the rti-icon
#: capture (tests/test_rti.py): both readings relight its photos equally well (re-render
#: RMSE 0.0400 each), but the solver's normals have a relative curl
#: (:func:`normal_curl`) of 1.13 read with y "up" against 1.67 with "down", and "up"
#: stays lower with the normals pooled 2×, 4× and 8× (1.09/1.69, 1.16/1.66, 1.20/1.65).
LP_Y_DEFAULT = "up"
LP_Y = ("up", "down")
#: A direction whose length differs from 1 by more than this is an error, not a rounding.
LP_NORM_TOLERANCE = 0.05
#: The distance (mm) recorded as an RTI rig's reference distance: with directional lights
#: and an orthographic camera it enters only novel lights drawn for evaluation.
RTI_REFERENCE_MM = 1000.0
#: The sample field's width (mm) when the user does not give it: RTI files have no scale.
RTI_FIELD_WIDTH_MM = 100.0


@dataclass(frozen=True)
class LightFile:
    """An ``.lp`` file's content: one file name and unit direction per photo
    (already in matscan's frame, y as chosen on reading), and what reading noticed."""

    files: tuple[str, ...]
    directions: tuple[tuple[float, float, float], ...]
    warnings: tuple[str, ...] = ()


def _check_y(y: str) -> float:
    if y not in LP_Y:
        raise MatscanError(f"y: {y!r} is not one of {', '.join(LP_Y)} (which way the file's +y points in the image)")
    return 1.0 if y == "up" else -1.0


def parse_lp(text: str, where: str = "lights.lp", y: str = LP_Y_DEFAULT) -> LightFile:
    """Parse ``.lp`` text (module doc); errors name ``where`` and the line."""
    sign = _check_y(y)
    lines = [(n + 1, line.strip()) for n, line in enumerate(text.replace("\r", "\n").split("\n"))]
    lines = [(n, line) for n, line in lines if line and not line.startswith("#")]
    if not lines:
        raise input_error(where, "is empty; an .lp file lists one 'FILE x y z' line per photo")
    warnings = []
    count = None
    first = lines[0][1].split()
    if len(first) == 1:
        try:
            count = int(first[0])
        except ValueError:
            raise input_error(where, f"line {lines[0][0]}: {first[0]!r} is not a count of photos") from None
        lines = lines[1:]
    files: list[str] = []
    directions: list[tuple[float, float, float]] = []
    for n, line in lines:
        parts = line.split()
        if len(parts) < 4:
            raise input_error(where, f"line {n}: expected 'FILE x y z', got {line[:60]!r}")
        name, numbers = " ".join(parts[:-3]), parts[-3:]
        try:
            x, yy, z = (float(v) for v in numbers)
        except ValueError:
            raise input_error(where, f"line {n}: {' '.join(numbers)!r} is not three numbers") from None
        if not all(math.isfinite(v) for v in (x, yy, z)):
            raise input_error(where, f"line {n}: the direction is not finite")
        norm = math.sqrt(x * x + yy * yy + z * z)
        if abs(norm - 1) > LP_NORM_TOLERANCE:
            raise input_error(where, f"line {n}: direction ({x:g}, {yy:g}, {z:g}) has length {norm:.3f}, not 1")
        if z <= 0:
            raise input_error(where, f"line {n}: direction ({x:g}, {yy:g}, {z:g}) is at or below the sample plane")
        base = PureWindowsPath(name).name if "\\" in name else Path(name).name
        if base in files:
            raise input_error(where, f"line {n}: {base} is listed twice")
        files.append(base)
        directions.append((x / norm, sign * yy / norm, z / norm))
    if not files:
        raise input_error(where, "lists no photos")
    if count is not None and count != len(files):
        warnings.append(f"{where}: says {count} photos but lists {len(files)}; using the {len(files)} listed")
    return LightFile(tuple(files), tuple(directions), tuple(warnings))


def read_lp(path: str | Path, y: str = LP_Y_DEFAULT) -> LightFile:
    """Read an ``.lp`` file (:func:`parse_lp`)."""
    path = Path(path)
    if not path.is_file():
        raise input_error(path, "no such light file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise input_error(path, f"cannot read it ({exc.strerror})") from None
    try:
        return parse_lp(raw.decode("utf-8-sig"), str(path), y)
    except UnicodeDecodeError:  # RTI tools on Windows write the system's code page
        lights = parse_lp(raw.decode("cp1252", errors="replace"), str(path), y)
        note = f"{path}: not UTF-8 text; its photo names were read as Windows-1252"
        return replace(lights, warnings=(note, *lights.warnings))


def rig_from_lp(
    lights: LightFile,
    field_mm: Sequence[float] = (RTI_FIELD_WIDTH_MM, RTI_FIELD_WIDTH_MM),
    name: str = "rti",
) -> Rig:
    """A rig of directional lights (one per photo, in file order) and an orthographic
    camera looking straight down, covering ``field_mm`` (each side above 0 and at most
    ``MAX_MM``, as a rig file allows). ``name`` keeps its printable characters (a file
    name's stem, say), the others become "_"."""
    for side in field_mm:
        if not (math.isfinite(side) and 0 < side <= MAX_MM):
            raise MatscanError(
                f"field: {list(field_mm)!r} must be two sizes (width, height) above 0 and at most {MAX_MM:g} mm"
            )
    return Rig(
        name="".join(c if c.isprintable() else "_" for c in name) or "rti",
        reference_distance_mm=RTI_REFERENCE_MM,
        camera=Camera(direction=(0.0, 0.0, 1.0)),
        field_mm=(float(field_mm[0]), float(field_mm[1])),
        lights=tuple(Light(direction=d) for d in lights.directions),
    )


def lp_text(rig: Rig, files: Sequence[str] | None = None, y: str = LP_Y_DEFAULT) -> str:
    """The ``.lp`` text of a rig's lights, one line per light (``files`` names them;
    default ``light_NN.png``). A point light is written as its direction from the
    field's centre: RTI software takes every light as directional."""
    sign = _check_y(y)
    if files is None:
        files = [f"light_{k:02d}.png" for k in range(len(rig.lights))]
    if len(files) != len(rig.lights):
        raise MatscanError(f"lp: {len(files)} file names for {len(rig.lights)} lights")
    out = [str(len(rig.lights))]
    for name, light in zip(files, rig.lights, strict=True):
        d = light.direction if light.direction is not None else light.position_mm
        assert d is not None
        norm = math.sqrt(sum(c * c for c in d))
        out.append(f"{name} {d[0] / norm:.9f} {sign * d[1] / norm:.9f} {d[2] / norm:.9f}")
    return "\n".join(out) + "\n"


def find_lp(folder: Path) -> Path:
    """The one ``.lp`` file in an RTI folder."""
    found = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".lp" and p.is_file())
    if not found:
        raise input_error(folder, "has no .lp light file; give one with --lp")
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise input_error(folder, f"has {len(found)} .lp files ({names}); choose one with --lp")
    return found[0]


def import_rti(
    folder: str | Path,
    out: str | Path,
    lp: str | Path | None = None,
    y: str = LP_Y_DEFAULT,
    field_width_mm: float | None = None,
    overwrite: bool = False,
    overwrite_any: bool = False,
) -> tuple[Path, list[str]]:
    """Make a matscan capture folder from an RTI folder (photos and an ``.lp`` file).

    The photos are copied unchanged (the RTI folder is not modified); ``capture.json``
    names them by light, ``rig.json`` holds the directional lights. Returns the capture
    folder and the warnings reading gave. ``field_width_mm`` is the sample field's
    width (RTI files carry no scale; default ``RTI_FIELD_WIDTH_MM``); the height
    follows the photos' aspect.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise not_a_folder(folder, "folder of RTI photos")
    lp_path = Path(lp) if lp is not None else find_lp(folder)
    fw = float(field_width_mm) if field_width_mm is not None else RTI_FIELD_WIDTH_MM
    if not (math.isfinite(fw) and 0 < fw <= MAX_MM):
        raise MatscanError(f"field width: {field_width_mm!r} must be a number of mm above 0 and at most {MAX_MM:g}")
    inputs = [folder, lp_path]
    with claim_output(out, "import-rti", inputs, overwrite=overwrite, overwrite_any=overwrite_any) as claim:
        lights = read_lp(lp_path, y)
        missing = [f for f in lights.files if not (folder / f).is_file()]
        if missing:
            more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
            raise input_error(folder / missing[0], f"is listed in {lp_path.name} but missing{more}")
        for f in lights.files:  # names capture.json can hold
            check_file_name(f, f"{lp_path}: {short_repr(f)}")
        first = read_image(folder / lights.files[0])
        height, width = first.stored.shape[:2]
        for f in lights.files[1:]:
            img = read_image(folder / f)
            if img.stored.shape[:2] != (height, width):
                raise input_error(
                    folder / f, f"is {img.stored.shape[1]}×{img.stored.shape[0]}, the other photos {width}×{height}"
                )
        rig = rig_from_lp(lights, (fw, fw * height / width), name=folder.name or "rti")
        linear = first.kind == "float"
        _import_into(claim, folder, lp_path, y, lights, rig, linear)
    return Path(out), list(lights.warnings)


def _import_into(claim: Any, folder: Path, lp_path: Path, y: str, lights: LightFile, rig: Rig, linear: bool) -> None:
    """Write the capture folder (copies of the photos, ``rig.json``, ``capture.json``)
    atomically through ``claim``."""
    with claim.folder() as tmp:
        for f in lights.files:
            shutil.copyfile(folder / f, tmp / f)
        (tmp / "rig.json").write_text(dumps(rig_to_dict(rig), "rig.json"), encoding="utf-8")
        doc = {
            "format": "matscan-capture/1",
            "rig": "rig.json",
            "encoding": "linear" if linear else "srgb",
            "images": [{"light": k, "file": f} for k, f in enumerate(lights.files)],
            "source": {"rti_folder": folder.name, "lp": lp_path.name, "lp_y": y},
        }
        (tmp / "capture.json").write_text(dumps(doc, "capture.json"), encoding="utf-8")


def normal_curl(normal: torch.Tensor) -> float:
    """Mean |curl| of the gradient field a normal map (3, H, W) implies, relative to
    the gradients' mean magnitude: near 0 for the normals of any surface z = h(x, y)
    (∂/∂y of ∂h/∂x equals ∂/∂x of ∂h/∂y), larger for a mirrored or noisy field."""
    nz = normal[2].clamp_min(0.05)
    p = -normal[0] / nz  # ∂h/∂x
    q = -normal[1] / nz  # ∂h/∂y, +y up: rows go toward −y
    # central differences both times, so the normals of a height field sampled by central
    # differences (normals_from_height) have no curl at all
    dp_dy = -(p[2:, 1:-1] - p[:-2, 1:-1]) / 2
    dq_dx = (q[1:-1, 2:] - q[1:-1, :-2]) / 2
    curl = (dp_dy - dq_dx).abs().mean()
    scale = (dp_dy.abs().mean() + dq_dx.abs().mean()) / 2
    return float(curl / scale.clamp_min(1e-12))
