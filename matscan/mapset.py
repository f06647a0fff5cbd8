"""Map sets: the material maps in memory, and the map set folder on disk.

A map set folder holds one file per map, named after the map (``diffuse``,
``specular``, ``roughness``, ``normal``; optionally ``alpha``, ``metallic``,
``basecolor``, ``emissive``, ``height``), each ``.png`` (8 or 16 bit), ``.tif``
or ``.exr`` (shared/design.md, "Map set folder"). Encodings:

=========  ========  ===================  ===========================  ============
map        channels  in memory            in PNG / integer TIFF        default file
=========  ========  ===================  ===========================  ============
diffuse    3         linear [0, 1]        sRGB-encoded                 8-bit PNG
specular   3         linear [0, 1]        sRGB-encoded                 8-bit PNG
roughness  1         r in [0, 1]          linear                       16-bit PNG
normal     3         unit vector          (n + 1)/2, linear            16-bit PNG
alpha      1         [0, 1]               linear                       8-bit PNG
metallic   1         [0, 1]               linear                       8-bit PNG
basecolor  3         linear [0, 1]        sRGB-encoded                 8-bit PNG
emissive   3         linear [0, 1]        sRGB-encoded                 8-bit PNG
height     1         mm                   (h − min)/(max − min)        16-bit PNG
=========  ========  ===================  ===========================  ============

EXR and float TIFF files are linear; normals in them are stored (n + 1)/2 like
in PNG, and height in millimetres. A grey map may have one channel or three
equal ones. The writer adds ``mapset.json`` recording these conventions and the
height range of a PNG height map.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from matscan.atomic import atomic_file
from matscan.color import linear_to_srgb, srgb_to_linear
from matscan.errors import MatscanError, input_error, not_a_folder
from matscan.imagefile import REC709_CHROMATICITIES, read_image, write_image
from matscan.jsonfile import (
    check_file_name,
    check_int,
    check_list,
    check_number,
    check_object,
    check_string,
    dumps,
    read_json,
    short_repr,
)
from matscan.outputs import claim_output
from matscan.samples import maps_folder

MAPSET_FORMAT = "matscan-maps/1"
REQUIRED = ("diffuse", "specular", "roughness", "normal")
OPTIONAL = ("alpha", "metallic", "basecolor", "emissive", "height")
ENDINGS = (".png", ".tif", ".tiff", ".exr")


@dataclass(frozen=True)
class MapSpec:
    channels: int
    encoding: str  # "srgb", "linear", "normal", "height"
    bits: int  # default PNG bit depth when written


SPECS: dict[str, MapSpec] = {
    "diffuse": MapSpec(3, "srgb", 8),
    "specular": MapSpec(3, "srgb", 8),
    "roughness": MapSpec(1, "linear", 16),
    "normal": MapSpec(3, "normal", 16),
    "alpha": MapSpec(1, "linear", 8),
    "metallic": MapSpec(1, "linear", 8),
    "basecolor": MapSpec(3, "srgb", 8),
    "emissive": MapSpec(3, "srgb", 8),
    "height": MapSpec(1, "height", 16),
}

#: The conventions written into every map set and output (design.md).
CONVENTIONS: dict[str, Any] = {
    "frame": "sample in z = 0, +z toward the camera, mm; row 0 at +y, column index grows with +x",
    "normal": "tangent frame +x right, +y up (OpenGL), +z out; files hold (n + 1)/2",
    "roughness": "perceptual r; GGX alpha = r^2; glossiness = 1 - r",
    "diffuse": "albedo rho, linear in memory and EXR, sRGB-encoded in PNG",
    "specular": "F0, linear in memory and EXR, sRGB-encoded in PNG",
    "brdf": "f_r = rho/pi + D G F / (4 (n.l)(n.v)); GGX D, uncorrelated Smith G, Schlick F",
    "height": "mm; PNG holds (h - min)/(max - min) with min and max in mapset.json",
    "alpha": "coverage: 1 material, 0 a hole; linear",
    "metallic": "glTF metalness: 0 dielectric, 1 metal; linear",
    "basecolor": "glTF base colour (albedo where dielectric, F0 where metal), linear in memory and EXR, "
    "sRGB-encoded in PNG",
    "emissive": "light the sample gives off, linear radiance in photo units (1 = the exposure's white), "
    "linear in memory and EXR, sRGB-encoded in PNG",
    "colour": "Rec. 709 / sRGB primaries, D65 white; PNGs say so in sRGB or gAMA 1.0 and cHRM chunks, "
    "EXRs in their chromaticities attribute",
}


@dataclass(frozen=True)
class MapSet:
    """A material's maps, each a float32 tensor (C, H, W) as in the table above."""

    diffuse: Tensor
    specular: Tensor
    roughness: Tensor
    normal: Tensor
    alpha: Tensor | None = None
    metallic: Tensor | None = None
    basecolor: Tensor | None = None
    emissive: Tensor | None = None
    height: Tensor | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return (self.diffuse.shape[-2], self.diffuse.shape[-1])

    def present(self) -> dict[str, Tensor]:
        """The maps that are present, by name."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    def check(self, where: str = "maps") -> MapSet:
        """Check shapes and sizes; return self."""
        size = self.size
        for name, t in self.present().items():
            c = SPECS[name].channels
            if t.ndim != 3 or t.shape[0] != c:
                raise MatscanError(f"{where}: {name} must be ({c}, H, W), got {tuple(t.shape)}")
            if tuple(t.shape[-2:]) != size:
                raise MatscanError(
                    f"{where}: {name} is {t.shape[-1]}×{t.shape[-2]} pixels but diffuse is {size[1]}×{size[0]}"
                )
        return self

    def transformed(self, rotations: int = 0, flip_x: bool = False) -> MapSet:
        """The material turned ``rotations`` × 90° counter-clockwise (seen from the
        camera), after mirroring x → −x when ``flip_x``.

        Pixels move and normal vectors turn with them: mirroring negates n_x;
        a 90° turn maps (n_x, n_y) → (−n_y, n_x). So rendering the result under
        lights moved by the same transform gives the moved images
        (:func:`matscan.rig.transform_points` moves lights).
        """
        out = {}
        for name, t in self.present().items():
            if flip_x:
                t = t.flip(-1)
                if name == "normal":
                    t = torch.stack([-t[0], t[1], t[2]])
            if rotations % 4:
                t = torch.rot90(t, rotations % 4, dims=(-2, -1))  # rows are −y: this is CCW in x, y
                if name == "normal":
                    for _ in range(rotations % 4):
                        t = torch.stack([-t[1], t[0], t[2]])
            out[name] = t.contiguous()
        return MapSet(**out)

    def crop(self, top: int, left: int, height: int, width: int) -> MapSet:
        """A crop of every map."""
        return replace(self, **{k: v[:, top : top + height, left : left + width] for k, v in self.present().items()})


def normalize_normals(normal: Tensor) -> Tensor:
    """Unit-length normals; a zero vector becomes (0, 0, 1)."""
    x, y, z = normal.unbind(-3)
    length = torch.sqrt(x * x + y * y + z * z).unsqueeze(-3)
    up = torch.zeros_like(normal)
    up[..., 2, :, :] = 1
    return torch.where(length > 1e-8, normal / length.clamp_min(1e-8), up)


def _find_file(folder: Path, name: str) -> Path | None:
    found = [folder / f"{name}{e}" for e in ENDINGS if (folder / f"{name}{e}").is_file()]
    if len(found) > 1:
        raise input_error(folder, f"more than one {name} map ({', '.join(p.name for p in found)}); keep one")
    return found[0] if found else None


def drop_alpha(px: np.ndarray, path: Path, name: str) -> np.ndarray:
    """A ``name`` map file's (H, W, C) pixels as grey (C = 1) or RGB (C = 3): an alpha
    channel (grey + alpha, RGB + alpha) dropped; any other channel count, and a normal map
    that is not RGB, refused naming the file."""
    c = px.shape[2]
    if name == "normal" and c not in (3, 4):
        raise input_error(path, f"has {c} channel{'s' if c > 1 else ''}; a normal map needs 3 (RGB, may add alpha)")
    if c in (2, 4):
        return px[:, :, : c - 1]
    if c not in (1, 3):
        raise input_error(path, f"has {c} channels; a map has 1 (grey) or 3 (RGB), and may add alpha")
    return px


def _read_map(path: Path, name: str, meta: dict[str, Any]) -> Tensor:
    spec = SPECS[name]
    img = read_image(path)
    px = drop_alpha(img.pixels, path, name)
    c = px.shape[2]
    if spec.channels == 1:
        if c == 3:
            spread = float(np.abs(px - px.mean(axis=2, keepdims=True)).max())
            if spread > 2.5 / 255:
                raise input_error(
                    path,
                    f"a {name} map must be grey: one channel or three equal ones (channels differ by {spread:.3f})",
                )
            px = px.mean(axis=2, keepdims=True)
    elif c == 1:
        px = np.repeat(px, 3, axis=2)
    t = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).float()
    linear_file = img.kind == "float"
    if linear_file:  # integer files hold 0 to 1 by construction; float ones may hold anything
        t = check_float_map(t, path, name)
    if spec.encoding == "srgb" and not linear_file:
        t = srgb_to_linear(t)
    elif spec.encoding == "normal":
        t = normalize_normals(t * 2 - 1)
    elif spec.encoding == "height" and not linear_file:
        rng = meta.get("height")  # checked by _read_meta: two finite numbers, min ≤ max
        if rng is None:
            raise input_error(
                path, "an integer height map needs its range: mapset.json with height.min_mm and height.max_mm"
            )
        t = rng["min_mm"] + t * (rng["max_mm"] - rng["min_mm"])
    return t


#: The largest height magnitude a map set may record (1 km; real ones are millimetres).
MAX_HEIGHT_MM = 1e6
#: Maps whose values are fractions (0 to 1, design.md), and how far past that a float
#: file's values may stray (an albedo a little over 1, a filter's ringing below 0) before
#: they are taken for other units (0-255 codes, percent) and refused.
FRACTION_MAPS = frozenset(
    {"diffuse", "specular", "roughness", "alpha", "metallic", "basecolor"}  # and as PBR libraries name them:
    | {"glossiness", "metalness", "opacity"}
)
FRACTION_SPAN = (-0.5, 1.5)
#: The largest magnitude a float file's map may hold (other than a height, in mm): far
#: beyond any meaningful albedo, F0, roughness or emission, short of overflowing a render.
MAX_FLOAT_VALUE = 1e6


def check_float_map(t: Tensor, path: Path, name: str) -> Tensor:
    """A float file's ``name`` map (any layout) with its values checked: finite, and
    within ``MAX_HEIGHT_MM`` (heights) or ``MAX_FLOAT_VALUE`` (the rest), and for maps of
    fractions within ``FRACTION_SPAN``, so a value in the wrong units or a blown-up export
    is refused naming the file rather than failing a render or rendering as something
    else. Values are kept as they are."""
    if not torch.isfinite(t).all():
        raise input_error(path, "holds NaN or infinite values")
    limit = MAX_HEIGHT_MM if name == "height" else MAX_FLOAT_VALUE
    lo, hi = float(t.min()), float(t.max())
    if max(-lo, hi) > limit:
        unit = " mm" if name == "height" else ""
        raise input_error(
            path, f"holds values from {lo:.4g} to {hi:.4g}{unit}; a {name} map's lie within ±{limit:g}{unit}"
        )
    if name in FRACTION_MAPS and not (FRACTION_SPAN[0] <= lo and hi <= FRACTION_SPAN[1]):
        raise input_error(
            path,
            f"holds values from {lo:.4g} to {hi:.4g}; a {name} map's lie within 0 to 1 (is it in 0-255 codes "
            "or percent? divide it so)",
        )
    return t


_FILE_KEYS = {"file": True, "bits": True}


def _read_meta(folder: Path) -> dict[str, Any]:
    """``mapset.json`` of a folder, checked (empty when there is none).

    Known fields must have their types: ``format`` (``matscan-maps/1``), ``size``
    (two positive integers), ``conventions`` (an object), ``files`` (map name →
    ``{file, bits}``), ``height`` (``min_mm`` ≤ ``max_mm``, finite). Other keys
    (a writer's ``extra_meta``) are kept as they are.
    """
    path = folder / "mapset.json"
    if not path.is_file():
        return {}
    where = str(path)
    meta = dict(check_object(read_json(path), where))
    if "format" in meta:
        check_string(meta["format"], f"{where}: format", (MAPSET_FORMAT,))
    if "size" in meta:
        size = check_list(meta["size"], f"{where}: size", "two sizes in pixels")
        if len(size) != 2:
            raise MatscanError(f"{where}: size: expected two sizes in pixels, got {short_repr(meta['size'])}")
        for i, v in enumerate(size):
            check_int(v, f"{where}: size[{i}]", 1)
    if "conventions" in meta:
        check_object(meta["conventions"], f"{where}: conventions")
    if "files" in meta:
        for name, entry in check_object(meta["files"], f"{where}: files", dict.fromkeys(SPECS, False)).items():
            check_object(entry, f"{where}: files.{name}", _FILE_KEYS)
            check_file_name(entry["file"], f"{where}: files.{name}.file")
            if check_int(entry["bits"], f"{where}: files.{name}.bits") not in (8, 16, 32):
                raise MatscanError(f"{where}: files.{name}.bits: {entry['bits']} is not one of 8, 16, 32")
    if "height" in meta:
        rng = check_object(meta["height"], f"{where}: height", {"min_mm": True, "max_mm": True})
        lo = check_number(rng["min_mm"], f"{where}: height.min_mm", -MAX_HEIGHT_MM, MAX_HEIGHT_MM)
        hi = check_number(rng["max_mm"], f"{where}: height.max_mm", -MAX_HEIGHT_MM, MAX_HEIGHT_MM)
        if hi < lo:
            raise MatscanError(f"{where}: height: max_mm {hi:g} is below min_mm {lo:g}")
        meta["height"] = {"min_mm": lo, "max_mm": hi}
    return meta


def read_mapset(folder: str | Path) -> MapSet:
    """Read a map set folder (``"@sample"``: the built-in sample's maps); errors name
    the file and the problem."""
    folder = maps_folder(folder)
    if not folder.is_dir():
        raise not_a_folder(folder, "map set folder")
    meta = _read_meta(folder)
    maps: dict[str, Tensor] = {}
    for name in REQUIRED + OPTIONAL:
        path = _find_file(folder, name)
        if path is None:
            if name in REQUIRED:
                present = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in ENDINGS)
                raise input_error(
                    folder,
                    f"no {name} map (expected {name}.png, .tif or .exr; found {', '.join(present) or 'no images'})",
                )
            continue
        maps[name] = _read_map(path, name, meta)
    size = maps["diffuse"].shape[-2:]
    for name, t in maps.items():
        if t.shape[-2:] != size:
            path = _find_file(folder, name)
            raise input_error(
                path or folder,
                f"is {t.shape[-1]}×{t.shape[-2]} pixels but the diffuse map is {size[1]}×{size[0]}",
            )
    return MapSet(**maps)


def write_mapset(
    folder: str | Path,
    maps: MapSet,
    file_format: str = "png",
    overwrite: bool = False,
    extra_meta: dict[str, Any] | None = None,
) -> Path:
    """Write a map set folder (``file_format`` ``png`` or ``exr``), atomically.

    PNG bit depths follow the table above; EXR is float32 and exact.
    """
    with claim_output(folder, "write_mapset", overwrite=overwrite) as claim, claim.folder() as tmp:
        write_maps(tmp, maps, file_format, extra_meta)
    return Path(folder)


def write_maps(
    folder: str | Path, maps: MapSet, file_format: str = "png", extra_meta: dict[str, Any] | None = None
) -> None:
    """Write the map files and ``mapset.json`` into an existing folder, replacing files of
    the same names: every file is written to a temporary first and they replace the old
    ones together once all are written, so a write that fails (a full disk, a bad value)
    leaves the folder as it was. :func:`write_mapset` writes a new folder whole."""
    folder = Path(folder)
    if not folder.is_dir():
        raise input_error(folder, "no such folder (write_maps writes into an existing one; write_mapset makes one)")
    if file_format not in ("png", "exr"):
        raise MatscanError(f"format: {file_format!r} is not one of png, exr")
    maps.check()
    meta: dict[str, Any] = {"format": MAPSET_FORMAT, "size": list(maps.size), "conventions": CONVENTIONS, "files": {}}
    if extra_meta:
        meta.update(extra_meta)
    with ExitStack() as files:  # exits in reverse: the maps replace theirs, then mapset.json
        meta_tmp = files.enter_context(atomic_file(folder / "mapset.json"))
        for name, t in maps.present().items():
            _write_one(folder, name, t, file_format, meta, files)
        meta_tmp.write_text(dumps(meta, "mapset.json"), encoding="utf-8")


def _write_one(folder: Path, name: str, t: Tensor, file_format: str, meta: dict[str, Any], files: ExitStack) -> None:
    """Write one map to a temporary that replaces ``folder``'s file when ``files`` closes."""
    spec = SPECS[name]
    t = t.detach().float()
    if spec.encoding == "normal":
        t = (normalize_normals(t) + 1) / 2
    if file_format == "exr":
        data, bits = t, 32
    else:
        bits = spec.bits
        if spec.encoding == "srgb":
            data = linear_to_srgb(t.clamp(0, 1))
        elif spec.encoding == "height":
            lo, hi = float(t.min()), float(t.max())
            meta["height"] = {"min_mm": lo, "max_mm": hi}
            data = (t - lo) / (hi - lo) if hi > lo else torch.zeros_like(t)
        else:
            data = t
    file = f"{name}.{file_format}"
    tmp = files.enter_context(atomic_file(folder / file))
    if file_format == "exr":  # the file says what it holds, for tools that never see mapset.json
        header = {
            "chromaticities": REC709_CHROMATICITIES,
            "matscanMap": name,
            "matscanConvention": CONVENTIONS.get(name, ""),
            "matscanFrame": CONVENTIONS["frame"],
        }
        write_image(tmp, data.permute(1, 2, 0).numpy(), bits=bits, header=header, atomic=False)
    else:
        colourspace = "srgb" if spec.encoding == "srgb" else "linear"
        write_image(tmp, data.permute(1, 2, 0).numpy(), bits=bits, colourspace=colourspace, atomic=False)
    meta["files"][name] = {"file": file, "bits": bits}
