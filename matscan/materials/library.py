"""Readers for map libraries users already own, converted to matscan's conventions.

Three layouts, detected by :func:`read_any`:

* **matscan map set**: a folder with ``diffuse``, ``specular``, ``roughness``,
  ``normal`` files (:func:`matscan.mapset.read_mapset`).
* **folder of maps** (public PBR libraries): one file per map, matched by words in
  the file name (``Fabric030_2K_NormalGL.png``, ``brick_rough.jpg``,
  ``oak_diff_2k.png``; see ``KEYWORDS``). Base colour / albedo with metalness is
  the metallic workflow and is converted to diffuse + specular (glTF rules);
  diffuse with a specular colour map is read as is. Glossiness becomes
  roughness = 1 − g. DirectX normal maps (``NormalDX``, ``nor_dx``, or
  ``normal_convention="directx"``) have their green channel flipped to OpenGL.
  Opacity becomes alpha. Ambient occlusion, previews and the like are ignored.
* **Deschaintre et al. 2018 panels**: one image of 4 (normal | diffuse |
  roughness | specular) or 5 (photo | normal | diffuse | roughness | specular)
  square panels side by side; colour panels sRGB-encoded, roughness linear,
  normals (n + 1)/2 with +y up.

A folder that fits none of these gets a message listing what was found and what
is expected.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from matscan.brdf import metallic_to_specular
from matscan.color import srgb_to_linear
from matscan.errors import MatscanError, input_error
from matscan.imagefile import READABLE, read_image
from matscan.mapset import MapSet, check_float_map, drop_alpha, normalize_normals, read_mapset

#: Words in a file name that identify a map (after splitting on separators and case changes).
KEYWORDS: dict[str, tuple[str, ...]] = {
    "basecolor": ("basecolor", "basecolour", "albedo", "color", "colour", "col", "base"),
    "diffuse": ("diffuse", "diff", "dif"),
    "normal": ("normal", "normals", "nrm", "nor", "norm"),
    "roughness": ("roughness", "rough", "rgh"),
    "glossiness": ("glossiness", "gloss", "gls"),
    "metalness": ("metalness", "metallic", "metal", "met", "mtl"),
    "specular": ("specular", "spec", "spc", "reflection", "refl"),
    "opacity": ("opacity", "alpha", "transparency", "mask"),
    "height": ("height", "displacement", "disp", "bump"),
    "ignore": (
        "ao",
        "ambientocclusion",
        "occlusion",
        "preview",
        "thumb",
        "thumbnail",
        "render",
        "sphere",
        "arm",
        "orm",
    ),
}
DIRECTX_WORDS = ("dx", "directx")
OPENGL_WORDS = ("gl", "opengl")


def tokens(stem: str) -> list[str]:
    """Lower-case words of a file stem, split at separators, digits and case changes."""
    spaced = re.sub(r"([a-z])([A-Z])", r"\1 \2", stem)
    spaced = re.sub(r"([A-Z]+)([A-Z][a-z])", r"\1 \2", spaced)
    return [t for t in re.split(r"[^A-Za-z]+", spaced.lower()) if t]


def classify(path: Path) -> str | None:
    """Which map a file holds, by its name (None when nothing matches)."""
    words = tokens(path.stem)
    if "ambient" in words and "occlusion" in words:
        return "ignore"
    for word in reversed(words):  # the last matching word wins: "Fabric_Base_Color" → color
        for kind, names in KEYWORDS.items():
            if word in names:
                return kind
    return None


def _image(path: Path, name: str = "diffuse") -> tuple[np.ndarray, str]:
    """A map file's pixels (alpha dropped) and kind; a float file's values checked as a
    ``name`` map's (:func:`matscan.mapset.check_float_map`)."""
    img = read_image(path)
    px = drop_alpha(img.pixels, path, name)
    if img.kind == "float":
        px = check_float_map(torch.from_numpy(np.ascontiguousarray(px)), path, name).numpy()
    return px, img.kind


def _colour(path: Path, name: str) -> Tensor:
    px, kind = _image(path, name)
    if px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    t = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).float()
    return t if kind == "float" else srgb_to_linear(t)


def _grey(path: Path, name: str) -> Tensor:
    px, _ = _image(path, name)  # a fraction: roughness, glossiness, metalness, opacity
    return torch.from_numpy(np.ascontiguousarray(px.mean(axis=2, keepdims=True))).permute(2, 0, 1).float()


def _normal(path: Path, directx: bool) -> Tensor:
    px, _ = _image(path, "normal")
    n = torch.from_numpy(np.ascontiguousarray(px)).permute(2, 0, 1).float() * 2 - 1
    if directx:
        n[1] = -n[1]
    return normalize_normals(n)


#: How a library folder's normal map may be encoded (:func:`read_map_folder`).
NORMAL_CONVENTIONS = ("auto", "opengl", "directx")


def check_normal_convention(value: str) -> str:
    """``value`` if it is one of :data:`NORMAL_CONVENTIONS`; else a MatscanError."""
    if value not in NORMAL_CONVENTIONS:
        raise MatscanError(f"normal_convention: {value!r} is not one of {', '.join(NORMAL_CONVENTIONS)}")
    return value


def read_map_folder(folder: str | Path, normal_convention: str = "auto") -> MapSet:
    """Read a folder of maps from a public PBR library (see module doc).

    ``normal_convention``: ``"auto"`` (OpenGL unless the file name says DX),
    ``"opengl"`` or ``"directx"``.
    """
    folder = Path(folder)
    check_normal_convention(normal_convention)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in READABLE)
    found: dict[str, list[Path]] = {}
    for p in files:
        kind = classify(p)
        if kind is not None and kind != "ignore":
            found.setdefault(kind, []).append(p)

    colour_kind = "diffuse" if "diffuse" in found else "basecolor" if "basecolor" in found else None
    if colour_kind is None or "normal" not in found or not ({"roughness", "glossiness"} & set(found)):
        names = ", ".join(p.name for p in files) or "no images"
        raise input_error(
            folder,
            "not a map folder this reader knows: expected a base colour/albedo/diffuse map, a normal map and a "
            f"roughness or glossiness map named so (found {names})",
        )

    def pick(kind: str) -> Path:
        options = found[kind]
        if kind == "normal" and len(options) > 1:
            want = DIRECTX_WORDS if normal_convention == "directx" else OPENGL_WORDS
            preferred = [p for p in options if set(tokens(p.stem)) & set(want)]
            if preferred:
                return preferred[0]
        return options[0]

    normal_path = pick("normal")
    directx = normal_convention == "directx" or (
        normal_convention == "auto" and bool(set(tokens(normal_path.stem)) & set(DIRECTX_WORDS))
    )
    colour = _colour(pick(colour_kind), colour_kind)
    if "roughness" in found:
        roughness = _grey(pick("roughness"), "roughness")
    else:
        roughness = 1 - _grey(pick("glossiness"), "glossiness")
    normal = _normal(normal_path, directx)
    if "specular" in found and "metalness" not in found:
        diffuse, specular = colour, _colour(pick("specular"), "specular")
    else:
        metallic = _grey(pick("metalness"), "metalness") if "metalness" in found else torch.zeros_like(roughness)
        diffuse, specular = metallic_to_specular(colour, metallic)
    alpha = _grey(pick("opacity"), "opacity") if "opacity" in found else None
    maps = {"diffuse": diffuse, "specular": specular, "roughness": roughness, "normal": normal, "alpha": alpha}
    size = diffuse.shape[-2:]
    for name, t in maps.items():
        if t is not None and t.shape[-2:] != size:
            raise input_error(
                folder, f"the {name} map is {t.shape[-1]}×{t.shape[-2]} but the colour map is {size[1]}×{size[0]}"
            )
    return MapSet(**maps)


def read_deschaintre(path: str | Path) -> MapSet:
    """Read a Deschaintre et al. 2018 panel image (see module doc)."""
    path = Path(path)
    px, kind = _image(path)
    h, w = px.shape[:2]
    if w not in (4 * h, 5 * h):
        raise input_error(path, f"a panel image is 4 or 5 square panels side by side; this one is {w}×{h}")
    panels = [px[:, i * h : (i + 1) * h] for i in range(w // h)][-4:]
    t = [torch.from_numpy(np.ascontiguousarray(p)).permute(2, 0, 1).float() for p in panels]
    if t[0].shape[0] != 3:
        raise input_error(path, "panel images need 3 channels")
    decode = (lambda x: x) if kind == "float" else srgb_to_linear
    return MapSet(
        diffuse=decode(t[1]),
        specular=decode(t[3]),
        roughness=t[2].mean(0, keepdim=True),
        normal=normalize_normals(t[0] * 2 - 1),
    )


def read_any(path: str | Path, normal_convention: str = "auto") -> MapSet:
    """Read a map set in any layout this module knows (see module doc)."""
    check_normal_convention(normal_convention)
    path = Path(path)
    if path.is_file():
        return read_deschaintre(path)
    if not path.is_dir():
        raise input_error(path, "no such map folder or panel image")
    names = {p.stem for p in path.iterdir()}
    if (path / "mapset.json").is_file() or {"diffuse", "specular", "roughness", "normal"} <= names:
        return read_mapset(path)  # a matscan map set, even with a map missing (read_mapset names it)
    return read_map_folder(path, normal_convention)


__all__ = ["KEYWORDS", "classify", "read_any", "read_deschaintre", "read_map_folder", "tokens"]
