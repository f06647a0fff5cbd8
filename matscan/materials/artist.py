"""Artist-style map sets for evaluation only: materials unlike the procedural training ones.

An artist paints a material's maps from photographs and drawn shapes; these sets are
made the same way, from the sample photographs scikit-image ships in its wheel
(``skimage.data``; no download) and closed-form shapes, never from
:mod:`matscan.materials.procedural`, and training never draws them. They bring what
the training families rarely hold: metal patterns on a dielectric, strong relief,
near-mirror gloss that saturates an 8-bit photo, bare metal under worn paint.
``docs/artist-materials.png`` shows them (``tools/artist_sheet.py``).

Common rules. A map covers the dome24 sample field, 120 × 120 mm. A photo is cropped to
the square named below (rows, columns in the photo's own pixels; "whole" where it is
square already), turned grey (Rec. 709 weights on the codes, in [0, 1]) and resampled
to size² (bilinear, antialiased). Blurs are Gaussian with σ in millimetres, the photo
mirrored at its edges (photos do not tile), so a set looks the same at every size.
"Normalised" maps a value linearly from its 1st/99th percentile to 0/1 and clamps.
Heights are in mm (stored with mean zero); normals come from them by central
differences (:func:`matscan.reconstruct.surface.normals_from_height`, edges mirrored).
Metal F0: gold (1.000, 0.766, 0.336) and iron (0.560, 0.570, 0.580) from the Unreal
Engine 4 documentation ("Physically Based Materials"), brass (0.910, 0.778, 0.423) from
physicallybased.info; dielectrics 0.04 (:data:`matscan.brdf.DIELECTRIC_F0`).

* ``foil-print``: gold foil stamped on printed paper. Foil f: where the scikit-image
  logo (``logo``, whole) is orange (red − green code > 40 of 255, alpha > 0.5). Foil:
  F0 gold, diffuse 0, roughness 0.2 − 0.08 × the logo's normalised brightness
  (0.12–0.2), standing 0.03 mm proud (f blurred σ 0.4 mm). Paper: p = ``page`` (rows and
  columns 0–191) decoded from sRGB, normalised; diffuse (0.06 + 0.74 p) × warm white
  (1, 0.96, 0.9), F0 0.04, roughness 0.6 + 0.1 p (0.6 on the ink, 0.7 on bare paper).
* ``black-leather``: dark glossy pebble-grain leather. Relief r: ``gravel`` (rows and
  columns 0–256: pebbles of 8–15 mm) blurred σ 1 mm, normalised; height 5.5 r mm, which
  tilts the normals 20–40° (median, at 96² to 256²) over nearly the whole image; diffuse
  (0.017 + 0.033 r) × (1, 0.95, 0.9): 0.015–0.05, crevices darkest; F0 0.04 + 0.01 r;
  roughness 0.4 − 0.2 r (crevices 0.4, pebble tops 0.2).
* ``embossed-coins``: a brass sheet embossed (repoussé) with coins, on a dark
  lacquered ground. Coin mask c: ``coins`` (rows 0–303, columns 40–343) blurred σ
  0.5 mm, smoothstep from 0.30 to 0.45, blurred σ 1 mm; detail d: the photo blurred
  σ 1.2 mm, normalised. Height 7 c (0.55 + 0.45 d) mm (coins 16 mm across: walls and
  faces tilted 20–40°, median). Coins: F0 brass × (0.6 + 0.4 d) (patina in the hollows),
  diffuse 0.02, roughness 0.45 − 0.25 d (high points polished to 0.2); ground: diffuse
  0.06, F0 0.04, roughness 0.7. Mixed by c, so the sheet is partly metallic.
* ``lacquer``: black and red lacquer polished to near mirror. Pattern q: ``camera``
  (whole) decoded from sRGB, normalised; diffuse from 0.01 (black) to (0.30, 0.04, 0.03)
  (red) by q; F0 0.04; roughness 0.05 on the light squares of ``checkerboard`` (whole)
  and 0.09 on the dark ones; brush marks, height 0.02 sin(2π (x/15 + 0.3 sin(2π y/40)))
  mm (x, y in mm), tilts under 0.5°. The ring-2 lights of dome24 (67.5°) mirror in the
  field, 44.8 mm from its centre, and saturate an 8-bit sRGB photo there.
* ``worn-metal``: painted steel tread plate, the paint worn through. Lozenges: in each
  20 mm cell a raised bar with elliptical footprint 14 × 4 mm, along +45° or −45° by
  cell parity, profile b = smoothstep(0, 1, 1 − (s/7)² − (t/2)²) (s, t in mm along and
  across), 0.5 b mm high; their tops (smoothstep 0.4–0.6 of b) are bare. Chips: k =
  local contrast of ``moon`` (whole; the photo minus itself blurred σ 4 mm, blurred
  σ 0.4 mm, normalised; craters dark), bare where k < 0.48, the mask then blurred
  σ 0.3 mm and cut at smoothstep 0.5–0.7 (an erosion: specks and slivers go). Bare
  steel: F0 iron, diffuse 0, roughness 0.2 + 0.15 k (burnished by wear); paint: diffuse
  blue-green (0.05, 0.16, 0.20), F0 0.04, roughness 0.55 + 0.15 k; paint 0.08 mm thick.

Needs the ``eval`` extra (scikit-image).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from matscan.brdf import DIELECTRIC_F0
from matscan.color import srgb_to_linear
from matscan.jsonfile import check_int, check_string
from matscan.mapset import MapSet
from matscan.materials.noise import blur, smoothstep
from matscan.materials.photos import FIELD_MM, skimage_data
from matscan.reconstruct.surface import normals_from_height

#: Metal F0, linear RGB (module doc gives the sources).
GOLD = (1.000, 0.766, 0.336)
IRON = (0.560, 0.570, 0.580)
BRASS = (0.910, 0.778, 0.423)
#: Rec. 709 luma weights, to turn a colour photo grey.
LUMA = (0.2126, 0.7152, 0.0722)

#: A square crop of a photo: (top row, left column, side) in the photo's pixels.
Box = tuple[int, int, int]


def _photo(name: str, size: int, box: Box | None = None) -> Tensor:
    """scikit-image's photo ``name``, cropped to ``box``, grey codes in [0, 1], (size, size)."""
    img = torch.from_numpy(getattr(skimage_data("artist materials"), name)()).float() / 255
    if img.ndim == 3:
        img = img[..., :3] @ torch.tensor(LUMA)
    if box is not None:
        top, left, side = box
        img = img[top : top + side, left : left + side]
    return _resample(img, size)


def _resample(img: Tensor, size: int) -> Tensor:
    assert img.shape[0] == img.shape[1], img.shape
    return F.interpolate(img[None, None], size=(size, size), mode="bilinear", antialias=True)[0, 0]


def _normalised(x: Tensor) -> Tensor:
    lo, hi = float(x.quantile(0.01)), float(x.quantile(0.99))
    return ((x - lo) / max(hi - lo, 1e-6)).clamp(0, 1)


def _mirrored(x: Tensor) -> Tensor:
    """An (S, S) map beside its mirror images, (2S, 2S): periodic with no seam."""
    x = torch.cat([x, x.flip(-1)], -1)
    return torch.cat([x, x.flip(-2)], -2)


def _blur(x: Tensor, sigma_mm: float) -> Tensor:
    size = x.shape[-1]
    return blur(_mirrored(x), sigma_mm * size / FIELD_MM)[:size, :size]


def _rgb(value: tuple[float, float, float] | float) -> Tensor:
    return torch.tensor(value if isinstance(value, tuple) else (value,) * 3).view(3, 1, 1)


def _mix(a: Tensor, b: Tensor, t: Tensor) -> Tensor:
    """a where t = 0, b where t = 1 (broadcast)."""
    return a + (b - a) * t


def _coords_mm(size: int) -> tuple[Tensor, Tensor]:
    """x, y (mm) of each pixel centre, (size, size) each, as design.md places them (row 0 at +y)."""
    u = (torch.arange(size, dtype=torch.float32) + 0.5) / size * FIELD_MM - FIELD_MM / 2
    return u[None, :].expand(size, size), -u[:, None].expand(size, size)


def _maps(diffuse: Tensor, specular: Tensor, roughness: Tensor, height: Tensor) -> MapSet:
    """A map set from diffuse and F0 (3 or broadcastable, S, S), roughness and height (S, S)."""
    size = height.shape[-1]
    normal = normals_from_height(_mirrored(height), FIELD_MM / size)[:, :size, :size]
    return MapSet(
        diffuse=diffuse.expand(3, size, size).clamp(0, 1).contiguous(),
        specular=specular.expand(3, size, size).clamp(0, 1).contiguous(),
        roughness=roughness.clamp(0, 1)[None].contiguous(),
        normal=normal.contiguous(),
        height=(height - height.mean())[None],
    )


def foil_print(size: int) -> MapSet:
    logo = torch.from_numpy(skimage_data("artist materials").logo()).float() / 255  # (500, 500, RGBA)
    orange = ((logo[..., 0] - logo[..., 1] > 40 / 255) & (logo[..., 3] > 0.5)).float()
    foil = _resample(orange, size)
    shine = _normalised(_resample(logo[..., :3].mean(-1) * logo[..., 3], size))
    paper = _normalised(srgb_to_linear(_photo("page", size, (0, 0, 191))))
    diffuse = _mix((0.06 + 0.74 * paper) * _rgb((1.0, 0.96, 0.9)), _rgb(0.0), foil)
    specular = _mix(_rgb(DIELECTRIC_F0), _rgb(GOLD), foil)
    roughness = _mix(0.6 + 0.1 * paper, 0.2 - 0.08 * shine, foil)
    return _maps(diffuse, specular, roughness, 0.03 * _blur(foil, 0.4))


def black_leather(size: int) -> MapSet:
    relief = _normalised(_blur(_photo("gravel", size, (0, 0, 256)), 1.0))
    diffuse = (0.017 + 0.033 * relief) * _rgb((1.0, 0.95, 0.9))
    specular = (0.04 + 0.01 * relief).expand(3, size, size)
    return _maps(diffuse, specular, 0.4 - 0.2 * relief, 5.5 * relief)


def embossed_coins(size: int) -> MapSet:
    photo = _photo("coins", size, (0, 40, 303))
    coin = _blur(smoothstep(0.30, 0.45, _blur(photo, 0.5)), 1.0).clamp(0, 1)
    detail = _normalised(_blur(photo, 1.2))
    diffuse = _mix(_rgb(0.06), _rgb(0.02), coin)
    specular = _mix(_rgb(DIELECTRIC_F0), _rgb(BRASS) * (0.6 + 0.4 * detail), coin)
    roughness = _mix(torch.full_like(coin, 0.7), 0.45 - 0.25 * detail, coin)
    return _maps(diffuse, specular, roughness, 7.0 * coin * (0.55 + 0.45 * detail))


def lacquer(size: int) -> MapSet:
    pattern = _normalised(srgb_to_linear(_photo("camera", size)))
    diffuse = _mix(_rgb(0.01), _rgb((0.30, 0.04, 0.03)), pattern)
    light_squares = (_photo("checkerboard", size) > 0.5).float()
    x, y = _coords_mm(size)
    brush = 0.02 * torch.sin(2 * math.pi * (x / 15 + 0.3 * torch.sin(2 * math.pi * y / 40)))
    return _maps(diffuse, _rgb(DIELECTRIC_F0), 0.09 - 0.04 * light_squares, brush)


def worn_metal(size: int) -> MapSet:
    x, y = _coords_mm(size)
    cx, cy = torch.floor(x / 20), torch.floor(y / 20)  # 20 mm cells, one lozenge each
    u, v = x - (cx + 0.5) * 20, y - (cy + 0.5) * 20  # from the cell's centre
    turn = 1 - 2 * ((cx + cy) % 2)  # +1: along +45°, −1: along −45°
    along, across = (u + turn * v) / math.sqrt(2), (u - turn * v) / math.sqrt(2)
    bar = smoothstep(0, 1, 1 - (along / 7) ** 2 - (across / 2) ** 2)
    moon = _photo("moon", size)
    craters = _normalised(_blur(moon - _blur(moon, 4.0), 0.4))
    chips = smoothstep(0.5, 0.7, _blur((craters < 0.48).float(), 0.3))
    paint = 1 - torch.maximum(chips, smoothstep(0.4, 0.6, bar))
    diffuse = _mix(_rgb(0.0), _rgb((0.05, 0.16, 0.20)), paint)
    specular = _mix(_rgb(IRON), _rgb(DIELECTRIC_F0), paint)
    roughness = _mix(0.2 + 0.15 * craters, 0.55 + 0.15 * craters, paint)
    return _maps(diffuse, specular, roughness, 0.5 * bar + 0.08 * paint)


#: The sets by name (module doc: the rules of each).
BUILDERS: dict[str, Callable[[int], MapSet]] = {
    "foil-print": foil_print,
    "black-leather": black_leather,
    "embossed-coins": embossed_coins,
    "lacquer": lacquer,
    "worn-metal": worn_metal,
}
ARTIST_NAMES = tuple(BUILDERS)


def artist_material(name: str, size: int = 256) -> MapSet:
    """The artist-style map set ``name`` (one of :data:`ARTIST_NAMES`; rules in the module
    doc) at ``size``² pixels over the 120 mm dome24 field.

    Maps as in :mod:`matscan.mapset` (diffuse and F0 linear RGB in [0, 1], perceptual
    roughness, unit normals with z > 0, height in mm). Deterministic: the same maps on
    every call. Raises MatscanError for an unknown name, a size under 8, or where
    scikit-image is missing.
    """
    check_string(name, "artist material", ARTIST_NAMES)
    check_int(size, "artist material: size", 8)
    return BUILDERS[name](size)
