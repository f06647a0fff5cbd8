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

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from matscan.color import linear_to_srgb, srgb_to_linear
from matscan.errors import MatscanError, input_error, not_a_folder
from matscan.imagefile import read_image, write_image
from matscan.jsonfile import check_file_name, check_number, check_object, check_vector, dumps, read_json, short_repr
from matscan.outputs import claim_output
from matscan.rig import (
    BUILTIN_RIGS,
    MAX_INTENSITY,
    MAX_MM,
    MIN_AIM_DISTANCE_MM,
    Light,
    LightSet,
    Rig,
    builtin_rig,
    resolve_rig,
    rig_to_dict,
)
from matscan.samples import capture_folder

CAPTURE_FORMAT = "matscan-capture/1"
ENCODINGS = ("srgb", "linear")
BACKLIGHT_KEYS = ("green", "blue", "green_empty", "blue_empty")
_KEYS = (
    "format",
    "rig",
    "encoding",
    "images",
    "backlight",
    "calibration",
    "field_mm",
    "simulation",
    "source",
    "acquisition",
)
_IMAGE_KEYS_INDEXED = ("light", "file")
_IMAGE_KEYS_PER_IMAGE = ("file", "light_position_mm", "camera_position_mm", "intensity")


#: Pixel-photos in one strip of work (:meth:`Capture.strips`): 4 Mi, so a float32 strip of
#: photos is 48 MiB and what is computed from it a few times that.
STRIP_VALUES = 1 << 22


def _region(
    t: Tensor, positions: Sequence[int] | None, rows: tuple[int, int] | None, cols: tuple[int, int] | None
) -> Tensor:
    if rows is not None:  # views first; picking photos copies, and only the region then
        t = t[..., rows[0] : rows[1], :]
    if cols is not None:
        t = t[..., cols[0] : cols[1]]
    if positions is not None:
        t = t[list(positions)]
    return t


@dataclass(frozen=True)
class Correction:
    """A capture's calibration, applied to photos as they are read (design.md, the
    capture folder): linear = max(0, M · photo / gain / flat)."""

    matrix: Tensor | None  # (3, 3) colour matrix, or None
    gain: Tensor  # (N, 3) each photo is divided by its light's scale, per channel
    flats: tuple[Tensor | None, ...]  # per photo a (1|3, H, W) float16 flat field, or None

    def select(self, positions: Sequence[int]) -> Correction:
        return Correction(self.matrix, self.gain[list(positions)], tuple(self.flats[i] for i in positions))

    def apply(
        self, photos: Tensor, index: list[int], rows: tuple[int, int] | None, cols: tuple[int, int] | None
    ) -> Tensor:
        """Correct photos (n, 3, h, w), the region ``rows``/``cols`` of photos ``index``."""
        if self.matrix is not None:
            photos = torch.einsum("ij,njhw->nihw", self.matrix, photos)
        photos = photos / self.gain[index].view(-1, 3, 1, 1)
        for j, i in enumerate(index):
            flat = self.flats[i]
            if flat is not None:
                photos[j] /= _region(flat, None, rows, cols).float()
        return photos.clamp_min(0)


@dataclass
class Capture:
    """A capture in memory.

    Attributes:
        rig: the rig it was taken with.
        field_mm: (width, height) the images cover, mm.
        encoding: ``"srgb"`` or ``"linear"`` as recorded.
        images: (N, 3, H, W) the photos as stored: uint8 or uint16 code values
            (decoded by ``lut``), or float32 linear radiance. Read them with
            :meth:`linear`, which decodes and calibrates a region at a time, so a
            large capture is never held as floats all at once.
        saturated: (N, 1, H, W) bool, pixels at the top code value of an integer file.
        light_indices: the rig light of each image, or ``None`` with per-image geometry.
        lights: the light and camera geometry of each image, for the renderer.
        files: the image file of each entry, relative to the folder.
        backlight: backlight photos by key (linear, (3, H, W)), if any.
        calibration: the calibration JSON object, if any.
        folder: where it was read from.
        meta: other recorded fields (``simulation``; ``exposure_s`` and ``led_level`` from
            ``acquisition``, where ``matscan capture`` set them), and ``warnings`` (a list of
            one-line messages: ``acquisition`` keys matscan does not know, from reading;
            what applying a calibration found, once it has been applied).
        calibration_file: the calibration file, when the capture names one (its
            flat fields lie beside it).
        lut: (2^bits,) float32 linear radiance of each code value, when ``images``
            holds codes (sRGB-decoded or scaled, by the capture's encoding).
        correction: the calibration, applied by :meth:`linear` as photos are read
            (:func:`matscan.calibrate.apply_calibration` sets it).
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
    calibration_file: Path | None = None
    lut: Tensor | None = None
    correction: Correction | None = None

    @property
    def size(self) -> tuple[int, int]:
        return (self.images.shape[-2], self.images.shape[-1])

    def linear(
        self,
        positions: Sequence[int] | None = None,
        rows: tuple[int, int] | None = None,
        cols: tuple[int, int] | None = None,
    ) -> Tensor:
        """Photos as float32 linear radiance, calibrated: (n, 3, h, w), a new tensor.

        ``positions``: which photos (indices into ``images``; all by default);
        ``rows``, ``cols``: (start, stop) of the region (the whole image by default).
        """
        values = _region(self.images, positions, rows, cols)
        out = self.lut[values.int()] if self.lut is not None else values.float().clone()
        if self.correction is not None:
            index = range(len(self.images)) if positions is None else positions
            out = self.correction.apply(out, list(index), rows, cols)
        return out

    def saturation(
        self,
        positions: Sequence[int] | None = None,
        rows: tuple[int, int] | None = None,
        cols: tuple[int, int] | None = None,
    ) -> Tensor:
        """The saturation masks (n, 1, h, w) of a region (arguments as for :meth:`linear`)."""
        return _region(self.saturated, positions, rows, cols)

    def select(self, positions: Sequence[int]) -> Capture:
        """The same capture with only some of its photos (positions in ``images``)."""
        positions = list(positions)
        return replace(
            self,
            images=self.images[positions],
            saturated=self.saturated[positions],
            light_indices=tuple(self.light_indices[i] for i in positions),
            lights=self.lights.select(positions),
            files=tuple(self.files[i] for i in positions),
            correction=None if self.correction is None else self.correction.select(positions),
        )

    def strips(self, photos: int | None = None, budget: int = STRIP_VALUES) -> list[tuple[int, int]]:
        """Row ranges (start, stop) covering the image, each holding at most ``budget``
        pixel-photos (at least one row) for ``photos`` photos (all by default): the unit
        of work that keeps memory bounded whatever the capture's size."""
        h, w = self.size
        n = len(self.images) if photos is None else photos
        step = max(1, budget // max(1, w * n))
        return [(r, min(h, r + step)) for r in range(0, h, step)]

    @property
    def mm_per_pixel(self) -> tuple[float, float]:
        """(x, y) size of one pixel in mm."""
        h, w = self.size
        return (self.field_mm[0] / w, self.field_mm[1] / h)


def _decode(path: Path) -> tuple[Tensor, Tensor, tuple[int, bool]]:
    """Read an image as stored (3, H, W): uint8/uint16 codes or float32; its saturation
    mask (1, H, W); and how it is stored: (bit depth, 32 for floats; whether it is RAW)."""
    img = read_image(path)
    px = img.stored
    if px.ndim != 3 or px.shape[0] == 0 or px.shape[1] == 0:
        raise input_error(path, f"holds no pixels (shape {px.shape})")
    if px.shape[2] == 4:
        px = px[:, :, :3]
    elif px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    elif px.shape[2] != 3:
        raise input_error(path, f"has {px.shape[2]} channels; expected RGB or grey")
    t = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).contiguous()
    if img.kind in ("int", "raw"):
        saturated = (t == (1 << img.bits) - 1).any(dim=0, keepdim=True)
        return t, saturated, (img.bits, img.kind == "raw")
    if not torch.isfinite(t).all():
        raise input_error(path, "holds NaN or infinite values")
    if float(t.abs().max()) > MAX_PHOTO_VALUE:
        raise input_error(
            path, f"holds values up to {float(t.abs().max()):.4g}; a float photo's lie within ±{MAX_PHOTO_VALUE:g}"
        )
    return t, torch.zeros(1, *t.shape[1:], dtype=torch.bool), (32, False)


def code_lut(bits: int, encoding: str, raw: bool = False) -> Tensor:
    """Linear radiance of every code value of a ``bits``-bit file: sRGB-decoded for an
    sRGB capture (not for RAW, which is developed linearly), else scaled to [0, 1]."""
    codes = torch.arange(1 << bits, dtype=torch.float64) / ((1 << bits) - 1)
    return (srgb_to_linear(codes) if encoding == "srgb" and not raw else codes).float()


def _to_linear(t: Tensor, stored: tuple[int, bool], encoding: str) -> Tensor:
    """Stored values (from :func:`_decode`) as float32 linear."""
    bits, raw = stored
    return t if bits == 32 else code_lut(bits, encoding, raw)[t.int()]


def _linear(path: Path, encoding: str) -> tuple[Tensor, Tensor]:
    """An image as float32 linear (3, H, W) and its saturation mask (backlight photos)."""
    t, saturated, stored = _decode(path)
    return _to_linear(t, stored, encoding), saturated


def _position(value: Any, where: str) -> tuple[float, float, float]:
    """A light or camera position of a per-image entry: 3 finite numbers (mm), z > 0."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise MatscanError(f"{where}: expected 3 numbers (x, y, z in mm), got {short_repr(value)}")
    pos = check_vector(value, 3, where, -MAX_MM, MAX_MM)
    if pos[2] <= 0:
        raise MatscanError(f"{where}: z = {pos[2]:g} is not above the sample plane (z > 0)")
    return (pos[0], pos[1], pos[2])


@dataclass(frozen=True)
class _Entry:
    """One checked ``images`` entry: its position in the list, file, and light or geometry."""

    index: int
    file: str
    light: int | None = None
    geometry: tuple[Light, tuple[float, float, float]] | None = None


def _read_document(folder: Path) -> tuple[Path, Mapping[str, Any]]:
    """``capture.json`` of a folder, parsed strictly, with its top-level keys checked."""
    if not folder.is_dir():
        raise not_a_folder(folder, "capture folder")
    path = folder / "capture.json"
    if not path.is_file():
        raise input_error(folder, "no capture.json here (not a matscan capture folder)")
    data = read_json(path)
    if not isinstance(data, Mapping):
        raise input_error(path, "expected a JSON object")
    for key in data:
        if key not in _KEYS:
            raise input_error(path, f"unknown key {short_repr(key)} (expected one of {', '.join(_KEYS)})")
    for key in ("format", "rig", "images"):
        if key not in data:
            raise input_error(path, f"missing field {key!r}")
    if data["format"] != CAPTURE_FORMAT:
        raise input_error(path, f"format: expected {CAPTURE_FORMAT!r}, got {short_repr(data['format'])}")
    return path, data


def _read_rig(spec: Any, folder: Path, path: Path) -> Rig:
    """The capture's rig: a built-in name, a rig file beside the capture, or an object."""
    if isinstance(spec, str):
        check_file_name(spec, f"{path}: rig")
    elif not isinstance(spec, Mapping):
        raise input_error(path, f"rig: expected a rig name, a .json file or a rig object, got {short_repr(spec)}")
    try:
        return resolve_rig(spec, base=folder)
    except MatscanError as exc:
        raise input_error(path, str(exc)) from None


def _read_field(data: Mapping[str, Any], rig: Rig, path: Path) -> tuple[float, float]:
    """``field_mm``: two finite positive sizes in mm (the rig's when absent)."""
    if "field_mm" not in data:
        return rig.field_mm
    f = data["field_mm"]
    if not isinstance(f, (list, tuple)) or len(f) != 2:
        raise input_error(path, f"field_mm: expected two positive sizes (width, height) in mm, got {short_repr(f)}")
    w, h = check_vector(f, 2, f"{path}: field_mm", high=MAX_MM)
    if min(w, h) <= 0:
        raise input_error(path, f"field_mm: expected two positive sizes (width, height) in mm, got {short_repr(f)}")
    return (w, h)


def _per_image_light(entry: Mapping[str, Any], rig: Rig, where: str) -> tuple[Light, tuple[float, float, float]]:
    """The light and camera of an entry of a per-image-geometry capture (``flash``)."""
    template = rig.lights[0]
    position = _position(entry["light_position_mm"], f"{where}.light_position_mm")
    if math.dist(position, template.aim_mm) < MIN_AIM_DISTANCE_MM:
        raise MatscanError(f"{where}.light_position_mm: is the rig's aim point {list(template.aim_mm)}; move it")
    intensity = template.intensity
    if "intensity" in entry:
        v = check_vector(entry["intensity"], 3, f"{where}.intensity", 0.0, MAX_INTENSITY)
        intensity = (v[0], v[1], v[2])
    light = Light(position_mm=position, intensity=intensity, exponent=template.exponent, aim_mm=template.aim_mm)
    return light, _position(entry["camera_position_mm"], f"{where}.camera_position_mm")


def _read_entries(raw: Any, rig: Rig, path: Path, lights: Sequence[int] | None) -> list[_Entry]:
    """The checked ``images`` entries, keeping only ``lights`` (all when None)."""
    if isinstance(raw, (list, tuple)) and not raw:
        raise input_error(
            path,
            "images: lists no photos (matscan capture lists none until its first LED frame: run the same "
            "command to resume a capture stopped before it; a chart target's capture holds only its chart photo)",
        )
    if not isinstance(raw, (list, tuple)):
        raise input_error(path, "images: expected a non-empty list of {light, file} entries")
    keys = _IMAGE_KEYS_PER_IMAGE if rig.per_image_geometry else _IMAGE_KEYS_INDEXED
    required = ("file", "light_position_mm", "camera_position_mm") if rig.per_image_geometry else ("light", "file")
    seen_light: dict[int, int] = {}
    seen_file: dict[str, int] = {}
    chosen: list[_Entry] = []
    for i, entry in enumerate(raw):
        where = f"{path}: images[{i}]"
        if not isinstance(entry, Mapping):
            raise MatscanError(f"{where}: expected an object with {', '.join(required)}")
        check_object(entry, where, {k: k in required for k in keys})
        file = check_file_name(entry["file"], f"{where}: file")
        if file in seen_file:
            raise MatscanError(f"{where}: file {file!r} is listed twice (also images[{seen_file[file]}])")
        seen_file[file] = i
        if rig.per_image_geometry:
            chosen.append(_Entry(i, file, geometry=_per_image_light(entry, rig, where)))
            continue
        k = entry["light"]
        if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < len(rig.lights):
            raise MatscanError(
                f"{where}: light {short_repr(k)} is not a light of rig {rig.name!r} (0 to {len(rig.lights) - 1})"
            )
        if k in seen_light:
            raise MatscanError(f"{where}: light {k} appears twice (also images[{seen_light[k]}])")
        seen_light[k] = i
        if lights is None or k in lights:
            chosen.append(_Entry(i, file, light=k))
    if not chosen:
        raise input_error(path, f"none of the requested lights {list(lights or [])} is in this capture")
    return chosen


def _read_images(folder: Path, chosen: list[_Entry], encoding: str) -> tuple[Tensor, Tensor, Tensor | None]:
    """(N, 3, H, W) photos as stored, (N, 1, H, W) saturation masks, and the table
    decoding codes to linear (None for float photos). Photos of mixed depth or kind
    (8- and 16-bit, or RAW and PNG) are all held as float32 linear."""
    images, saturated, kinds = [], [], []
    for entry in chosen:
        file_path = folder / entry.file
        img, sat, stored = _decode(file_path)
        if images and img.shape[1:] != images[0].shape[1:]:
            h, w = images[0].shape[1:]
            raise input_error(file_path, f"is {img.shape[2]}×{img.shape[1]} pixels but {chosen[0].file} is {w}×{h}")
        images.append(img)
        saturated.append(sat)
        kinds.append(stored)
    if len(set(kinds)) == 1 and kinds[0][0] != 32:
        bits, raw = kinds[0]
        return torch.stack(images), torch.stack(saturated), code_lut(bits, encoding, raw)
    linear = [_to_linear(img, stored, encoding) for img, stored in zip(images, kinds, strict=True)]
    return torch.stack(linear), torch.stack(saturated), None


def _read_backlight(raw: Any, folder: Path, path: Path, encoding: str, like: Tensor, first: str) -> dict[str, Tensor]:
    """The backlight photos by key, each the size of ``like`` (a photo, (3, H, W))."""
    bl = check_object(raw, f"{path}: backlight", {k: k in ("green", "blue") for k in BACKLIGHT_KEYS})
    backlight: dict[str, Tensor] = {}
    for key, file in bl.items():
        file_path = folder / check_file_name(file, f"{path}: backlight.{key}")
        img, _ = _linear(file_path, encoding)
        if img.shape[1:] != like.shape[1:]:
            h, w = like.shape[1:]
            raise input_error(file_path, f"is {img.shape[2]}×{img.shape[1]} pixels but {first} is {w}×{h}")
        backlight[key] = img
    return backlight


def _read_calibration(raw: Any, folder: Path, path: Path) -> tuple[dict[str, Any], Path | None]:
    """The calibration object (inline, or read from the file it names) and that file."""
    if isinstance(raw, str):
        cal_path = folder / check_file_name(raw, f"{path}: calibration")
        data = read_json(cal_path)
        if not isinstance(data, Mapping):
            raise input_error(cal_path, "expected a JSON object (a matscan calibration)")
        return dict(data), cal_path
    if isinstance(raw, Mapping):
        return dict(raw), None
    raise input_error(path, f"calibration: expected a file name or an object, got {short_repr(raw)}")


#: The largest magnitude a float (EXR, TIFF) photo may hold, in its own units (1 = white
#: for matscan's photos; a bright highlight a few hundred).
MAX_PHOTO_VALUE = 1e6

#: Exposures (s) as a capture or a calibration records them: an hour at most (a camera's
#: longest are a few minutes; a larger number is likely milliseconds), and down to the
#: nanosecond, below any camera's shortest (1/32000 s) and the 0.01 s / 2^15 that
#: ``matscan capture``'s metering may reach with the virtual camera.
EXPOSURE_LIMITS = (1e-9, 3600.0)


#: The keys ``matscan capture`` writes in ``acquisition``; any other is warned of.
ACQUISITION_KEYS = frozenset(
    {
        "camera",
        "leds",
        "exposure_s",
        "led_level",
        "dark",
        "target",
        "frames",
        "retakes",
        "complete",
        "drift_px",
        "drift_response",
        "chart",
    }
)


def _read_exposure(acquisition: Any, path: Path) -> dict[str, Any]:
    """What ``acquisition`` says of the photos' brightness: ``exposure_s`` (where
    ``matscan capture`` set the exposure; null where the camera did) and ``led_level``
    (the LEDs' level, 0-1; 1 where a capture made before it was recorded), for
    :func:`matscan.calibrate.apply_calibration`, which scales a calibration made at
    another exposure or level by the ratio."""
    where = f"{path}: acquisition"
    check_object(acquisition, where)
    found: dict[str, Any] = {}
    unknown = sorted(k for k in acquisition if k not in ACQUISITION_KEYS)
    if unknown:  # a record, so not refused; but "exposure" for "exposure_s" would drop the ratio unseen
        found["warnings"] = [
            f"{where}: {'keys' if len(unknown) > 1 else 'key'} {', '.join(map(short_repr, unknown))} not known to "
            "matscan, ignored (it reads exposure_s and led_level; the rest is a record of the capture)"
        ]
    if acquisition.get("exposure_s") is not None:
        found["exposure_s"] = check_number(
            acquisition["exposure_s"], f"{where}: exposure_s", *EXPOSURE_LIMITS, positive=True
        )
        found["led_level"] = 1.0
    if acquisition.get("led_level") is not None:
        found["led_level"] = check_number(acquisition["led_level"], f"{where}: led_level", 0.0, 1.0, positive=True)
    return found


def with_calibration_file(capture: Capture, file: str | Path) -> Capture:
    """The capture with the calibration in ``file`` in place of its own (if any), not yet
    applied: another capture's ``self_calibration.json``, say, for a capture of the same
    rig whose own photos cannot place the lights as well. Flat fields it names lie beside
    it. Where the capture named a calibration of its own, ``meta["warnings"]`` says which
    was set aside. Errors name the file in one line."""
    path = Path(file)
    data = read_json(path)
    if not isinstance(data, Mapping):
        raise input_error(path, "expected a JSON object (a matscan calibration)")
    warnings = list(capture.meta.get("warnings", []))
    if capture.calibration is not None:
        own = capture.calibration_file.name if capture.calibration_file is not None else "its inline calibration"
        warnings.append(f"the capture's calibration ({own}) was set aside for {path}")
    meta = {**capture.meta, "warnings": warnings} if warnings else capture.meta
    return replace(capture, calibration=dict(data), calibration_file=path, meta=meta)


def load_capture(folder: str | Path, lights: Sequence[int] | None = None) -> Capture:
    """Read and check a capture folder (``"@sample"``: the built-in sample capture).

    ``lights`` keeps only the images of those rig lights (all by default).
    Errors name the file and the problem in one line; nothing in the folder changes.
    The calibration is read (and checked to be an object) but not applied: see
    :func:`matscan.calibrate.apply_calibration`, which checks its fields.
    """
    folder = capture_folder(folder)
    path, data = _read_document(folder)
    rig = _read_rig(data["rig"], folder, path)
    encoding = data.get("encoding", "srgb")
    if encoding not in ENCODINGS:
        raise input_error(path, f"encoding: {short_repr(encoding)} is not one of {', '.join(ENCODINGS)}")
    field_mm = _read_field(data, rig, path)
    chosen = _read_entries(data["images"], rig, path, lights)
    calibration, calibration_file = None, None
    if "calibration" in data:
        calibration, calibration_file = _read_calibration(data["calibration"], folder, path)
    meta: dict[str, Any] = {}
    if "simulation" in data:
        meta["simulation"] = check_object(data["simulation"], f"{path}: simulation")
    if "acquisition" in data:
        meta.update(_read_exposure(data["acquisition"], path))

    images, saturated, lut = _read_images(folder, chosen, encoding)
    backlight: dict[str, Tensor] = {}
    if "backlight" in data:
        backlight = _read_backlight(data["backlight"], folder, path, encoding, images[0], chosen[0].file)
    if rig.per_image_geometry:
        geometry = [e.geometry for e in chosen if e.geometry is not None]
        light_set = LightSet.from_lights([g[0] for g in geometry], [g[1] for g in geometry], rig.reference_distance_mm)
    else:
        light_set = rig.light_set([e.light for e in chosen if e.light is not None])
    return Capture(
        rig=rig,
        field_mm=field_mm,
        encoding=encoding,
        images=images,
        saturated=saturated,
        light_indices=tuple(e.light for e in chosen),
        lights=light_set,
        files=tuple(e.file for e in chosen),
        backlight=backlight,
        calibration=calibration,
        folder=folder,
        meta=meta,
        calibration_file=calibration_file,
        lut=lut,
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
    with claim_output(folder, "write_capture", overwrite=overwrite) as claim, claim.folder() as tmp:
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
        (tmp / "capture.json").write_text(dumps(doc, "capture.json"), encoding="utf-8")
    return Path(folder)
