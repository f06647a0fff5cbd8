"""The capture folder format ``matscan-capture/1`` (shared/design.md).

A capture is a folder with ``capture.json`` and image files beside it::

    {
      "format": "matscan-capture/1",
      "rig": "dome24",              # built-in name, a rig object, or "rig.json"
      "encoding": "srgb",           # "srgb" or "linear" (integer files only)
      "images": [{"light": 0, "file": "led_00.png"}, ...],
      "backlight": {"green": ..., "blue": ..., "green_empty": ..., "blue_empty": ...},
      "calibration": "calibration.json"
    }

For a rig with per-image geometry (``flash``) each image entry gives
``light_position_mm`` and ``camera_position_mm`` instead of ``light``, and the
capture may state ``field_mm``. Images are rectified to the sample field (row 0
at +y). EXR and float TIFF are linear whatever ``encoding`` says; RAW files are
developed linearly. Reading never modifies the folder.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from matscan.atomic import atomic_folder
from matscan.color import linear_to_srgb, srgb_to_linear
from matscan.errors import MatscanError, input_error
from matscan.imagefile import read_image, write_image
from matscan.rig import BUILTIN_RIGS, Light, LightSet, Rig, builtin_rig, resolve_rig, rig_to_dict

CAPTURE_FORMAT = "matscan-capture/1"
ENCODINGS = ("srgb", "linear")
BACKLIGHT_KEYS = ("green", "blue", "green_empty", "blue_empty")
_KEYS = ("format", "rig", "encoding", "images", "backlight", "calibration", "field_mm", "simulation")
_IMAGE_KEYS_INDEXED = ("light", "file")
_IMAGE_KEYS_PER_IMAGE = ("file", "light_position_mm", "camera_position_mm", "intensity")


@dataclass
class Capture:
    """A capture in memory.

    Attributes:
        rig: the rig it was taken with.
        field_mm: (width, height) the images cover, mm.
        encoding: ``"srgb"`` or ``"linear"`` as recorded.
        images: (N, 3, H, W) float32 linear radiance (as exposed; not calibrated).
        saturated: (N, 1, H, W) bool, pixels at the top code value of an integer file.
        light_indices: the rig light of each image, or ``None`` with per-image geometry.
        lights: the light and camera geometry of each image, for the renderer.
        files: the image file of each entry, relative to the folder.
        backlight: backlight photos by key (linear, (3, H, W)), if any.
        calibration: the calibration JSON object, if any.
        folder: where it was read from.
        meta: other recorded fields (``simulation``).
    """

    rig: Rig
    field_mm: tuple[float, float]
    encoding: str
    images: Tensor
    saturated: Tensor
    light_indices: tuple[int | None, ...]
    lights: LightSet
    files: tuple[str, ...]
    backlight: dict[str, Tensor] = field(default_factory=dict)
    calibration: dict[str, Any] | None = None
    folder: Path | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> tuple[int, int]:
        return (self.images.shape[-2], self.images.shape[-1])

    @property
    def mm_per_pixel(self) -> tuple[float, float]:
        """(x, y) size of one pixel in mm."""
        h, w = self.size
        return (self.field_mm[0] / w, self.field_mm[1] / h)


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise input_error(path, "no such file") from None
    except json.JSONDecodeError as exc:
        raise input_error(path, f"not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise input_error(path, f"cannot read ({exc})") from None


def _decode(path: Path, encoding: str) -> tuple[Tensor, Tensor]:
    """Read an image as linear (3, H, W) plus its saturation mask (1, H, W)."""
    img = read_image(path)
    px = img.pixels
    if px.shape[2] == 4:
        px = px[:, :, :3]
    elif px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    elif px.shape[2] != 3:
        raise input_error(path, f"has {px.shape[2]} channels; expected RGB or grey")
    t = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).float()
    if not torch.isfinite(t).all():
        raise input_error(path, "holds NaN or infinite values")
    if img.kind in ("int", "raw"):
        saturated = (t >= 1.0 - 0.5 / ((1 << img.bits) - 1)).any(dim=0, keepdim=True)
    else:
        saturated = torch.zeros(1, *t.shape[1:], dtype=torch.bool)
    if img.kind == "int" and encoding == "srgb":
        t = srgb_to_linear(t)
    return t, saturated


def _position(value: Any, where: str) -> tuple[float, float, float]:
    if (
        not isinstance(value, Sequence)
        or isinstance(value, str)
        or len(value) != 3
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    ):
        raise MatscanError(f"{where}: expected 3 numbers (x, y, z in mm), got {value!r}")
    if value[2] <= 0:
        raise MatscanError(f"{where}: z = {value[2]:g} is not above the sample plane (z > 0)")
    return (float(value[0]), float(value[1]), float(value[2]))


def load_capture(folder: str | Path, lights: Sequence[int] | None = None) -> Capture:
    """Read and check a capture folder.

    ``lights`` keeps only the images of those rig lights (all by default).
    Errors name the file and the problem in one line.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise input_error(folder, "no such capture folder")
    path = folder / "capture.json"
    if not path.is_file():
        raise input_error(folder, "no capture.json here (not a matscan capture folder)")
    data = _load_json(path)
    if not isinstance(data, Mapping):
        raise input_error(path, "expected a JSON object")
    for key in data:
        if key not in _KEYS:
            raise input_error(path, f"unknown key {key!r} (expected one of {', '.join(_KEYS)})")
    for key in ("format", "rig", "images"):
        if key not in data:
            raise input_error(path, f"missing field {key!r}")
    if data["format"] != CAPTURE_FORMAT:
        raise input_error(path, f"format: expected {CAPTURE_FORMAT!r}, got {data['format']!r}")
    try:
        rig = resolve_rig(data["rig"], base=folder)
    except MatscanError as exc:
        raise input_error(path, str(exc)) from None
    encoding = data.get("encoding", "srgb")
    if encoding not in ENCODINGS:
        raise input_error(path, f"encoding: {encoding!r} is not one of {', '.join(ENCODINGS)}")
    field_mm = rig.field_mm
    if "field_mm" in data:
        f = data["field_mm"]
        if (
            not isinstance(f, Sequence)
            or len(f) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in f)
        ):
            raise input_error(path, f"field_mm: expected two positive sizes (width, height) in mm, got {f!r}")
        field_mm = (float(f[0]), float(f[1]))

    entries = data["images"]
    if not isinstance(entries, Sequence) or isinstance(entries, str) or not entries:
        raise input_error(path, "images: expected a non-empty list of {light, file} entries")
    keys = _IMAGE_KEYS_PER_IMAGE if rig.per_image_geometry else _IMAGE_KEYS_INDEXED
    required = ("file", "light_position_mm", "camera_position_mm") if rig.per_image_geometry else ("light", "file")
    seen_light: dict[int, int] = {}
    seen_file: dict[str, int] = {}
    chosen: list[tuple[int, Mapping[str, Any]]] = []
    for i, entry in enumerate(entries):
        where = f"{path}: images[{i}]"
        if not isinstance(entry, Mapping):
            raise MatscanError(f"{where}: expected an object with {', '.join(required)}")
        for key in entry:
            if key not in keys:
                raise MatscanError(f"{where}: unknown key {key!r} (expected one of {', '.join(keys)})")
        for key in required:
            if key not in entry:
                raise MatscanError(f"{where}: missing field {key!r}")
        file = entry["file"]
        if not isinstance(file, str) or not file:
            raise MatscanError(f"{where}: file: expected a file name, got {file!r}")
        if file in seen_file:
            raise MatscanError(f"{where}: file {file!r} is listed twice (also images[{seen_file[file]}])")
        seen_file[file] = i
        if not rig.per_image_geometry:
            k = entry["light"]
            if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < len(rig.lights):
                raise MatscanError(
                    f"{where}: light {k!r} is not a light of rig {rig.name!r} (0 to {len(rig.lights) - 1})"
                )
            if k in seen_light:
                raise MatscanError(f"{where}: light {k} appears twice (also images[{seen_light[k]}])")
            seen_light[k] = i
            if lights is not None and k not in lights:
                continue
        chosen.append((i, entry))
    if not chosen:
        raise input_error(path, f"none of the requested lights {list(lights or [])} is in this capture")

    images, saturated, files, indices, geometry = [], [], [], [], []
    size: tuple[int, int] | None = None
    first = ""
    for i, entry in chosen:
        file_path = folder / entry["file"]
        img, sat = _decode(file_path, encoding)
        if size is None:
            size, first = (img.shape[1], img.shape[2]), entry["file"]
        elif (img.shape[1], img.shape[2]) != size:
            raise input_error(file_path, f"is {img.shape[2]}×{img.shape[1]} pixels but {first} is {size[1]}×{size[0]}")
        images.append(img)
        saturated.append(sat)
        files.append(entry["file"])
        if rig.per_image_geometry:
            where = f"{path}: images[{i}]"
            template = rig.lights[0]
            inten = entry.get("intensity", template.intensity)
            light = Light(
                position_mm=_position(entry["light_position_mm"], f"{where}.light_position_mm"),
                intensity=tuple(float(v) for v in inten),
                exponent=template.exponent,
                aim_mm=template.aim_mm,
            )
            camera = _position(entry["camera_position_mm"], f"{where}.camera_position_mm")
            geometry.append((light, camera))
            indices.append(None)
        else:
            indices.append(int(entry["light"]))
    if rig.per_image_geometry:
        light_set = LightSet.from_lights([g[0] for g in geometry], [g[1] for g in geometry], rig.reference_distance_mm)
    else:
        light_set = rig.light_set(indices)

    backlight: dict[str, Tensor] = {}
    if "backlight" in data:
        bl = data["backlight"]
        if not isinstance(bl, Mapping):
            raise input_error(path, "backlight: expected an object with green and blue files")
        for key in bl:
            if key not in BACKLIGHT_KEYS:
                raise input_error(path, f"backlight: unknown key {key!r} (expected {', '.join(BACKLIGHT_KEYS)})")
        for key in ("green", "blue"):
            if key not in bl:
                raise input_error(path, f"backlight: missing {key!r}")
        for key, file in bl.items():
            img, _ = _decode(folder / str(file), encoding)
            if (img.shape[1], img.shape[2]) != size:
                raise input_error(
                    folder / str(file), f"is {img.shape[2]}×{img.shape[1]} pixels but {first} is {size[1]}×{size[0]}"
                )
            backlight[key] = img

    calibration = None
    if "calibration" in data:
        cal = data["calibration"]
        if isinstance(cal, str):
            calibration = _load_json(folder / cal)
        elif isinstance(cal, Mapping):
            calibration = dict(cal)
        else:
            raise input_error(path, "calibration: expected a file name or an object")

    return Capture(
        rig=rig,
        field_mm=field_mm,
        encoding=encoding,
        images=torch.stack(images),
        saturated=torch.stack(saturated),
        light_indices=tuple(indices),
        lights=light_set,
        files=tuple(files),
        backlight=backlight,
        calibration=calibration,
        folder=folder,
        meta={"simulation": data["simulation"]} if "simulation" in data else {},
    )


def _encode(img: Tensor, encoding: str, bits: int) -> np.ndarray:
    t = img.detach().float()
    if bits != 32:
        t = t.clamp(0, 1)
        if encoding == "srgb":
            t = linear_to_srgb(t)
    return t.permute(1, 2, 0).numpy()


def write_capture(
    folder: str | Path,
    images: Tensor,
    rig: Rig,
    light_indices: Sequence[int] | None = None,
    geometry: Sequence[tuple[Sequence[float], Sequence[float]]] | None = None,
    encoding: str = "srgb",
    bits: int = 8,
    backlight: Mapping[str, Tensor] | None = None,
    field_mm: Sequence[float] | None = None,
    extra: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    rig_ref: str | None = None,
) -> Path:
    """Write a capture folder atomically.

    Args:
        images: (N, 3, H, W) linear radiance; saved clipped to [0, 1] and encoded
            per ``encoding`` with ``bits`` 8 or 16 (PNG), or 32 (float EXR,
            linear, unclipped: ``encoding`` must be ``"linear"``).
        rig: the rig; stored by name when ``rig_ref`` is None and it is built in,
            else as an object.
        light_indices: the rig light of each image (rigs with fixed lights).
        geometry: (light_position_mm, camera_position_mm) of each image (rigs
            with per-image geometry).
        backlight: linear backlight photos by key (green, blue, green_empty, blue_empty).
    """
    if encoding not in ENCODINGS:
        raise MatscanError(f"encoding: {encoding!r} is not one of {', '.join(ENCODINGS)}")
    if bits not in (8, 16, 32):
        raise MatscanError(f"bits: {bits} is not one of 8, 16, 32")
    if bits == 32 and encoding != "linear":
        raise MatscanError("bits: 32-bit float files are linear; use --encoding linear")
    ext = "exr" if bits == 32 else "png"
    if rig_ref is None:
        rig_ref = rig.name if rig.name in BUILTIN_RIGS and builtin_rig(rig.name) == rig else None
    entries: list[dict[str, Any]] = []
    with atomic_folder(folder, overwrite=overwrite) as tmp:
        for n, img in enumerate(images):
            if rig.per_image_geometry:
                if geometry is None:
                    raise MatscanError(f"rig {rig.name!r} needs the light and camera position of every image")
                file = f"img_{n:02d}.{ext}"
                lpos, cpos = geometry[n]
                entries.append(
                    {
                        "file": file,
                        "light_position_mm": [float(v) for v in lpos],
                        "camera_position_mm": [float(v) for v in cpos],
                    }
                )
            else:
                if light_indices is None:
                    raise MatscanError("write_capture: light_indices is required for this rig")
                k = int(light_indices[n])
                file = f"led_{k:02d}.{ext}"
                entries.append({"light": k, "file": file})
            write_image(tmp / file, _encode(img, encoding, bits), bits=bits)
        doc: dict[str, Any] = {
            "format": CAPTURE_FORMAT,
            "rig": rig_ref if rig_ref is not None else rig_to_dict(rig),
            "encoding": encoding,
            "images": entries,
        }
        if field_mm is not None:
            doc["field_mm"] = [float(v) for v in field_mm]
        if backlight:
            doc["backlight"] = {}
            for key, img in backlight.items():
                file = f"back_{key}.{ext}"
                write_image(tmp / file, _encode(img, encoding, bits), bits=bits)
                doc["backlight"][key] = file
        if extra:
            doc.update(extra)
        (tmp / "capture.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return Path(folder)
