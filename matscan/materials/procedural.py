"""Procedural SVBRDF generators for the material families a scanner meets.

Each generator makes a tileable map set of any square size, deterministic from a
``torch.Generator``, with parameters drawn from ranges plausible for the real
material (stated in each docstring). Heights are in millimetres and normals come
from them at the given ``mm_per_px``, so a tile has a physical scale.

Reflectance ranges used throughout: dielectric F0 0.02–0.06 (refractive index
1.33–1.65, F0 = ((n − 1)/(n + 1))²); metal F0 from measured linear RGB values
(Real-Time Rendering, 4th ed., Table 9.2) with near-zero diffuse.

Families (``FAMILIES``): woven_plain, woven_twill, woven_satin, knit, leather,
paper, painted, plastic, metal_brushed, metal_embossed, foil_print, mesh, lace,
fluorescent_print.
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Callable

import torch
from torch import Tensor

from matscan.color import srgb_to_linear
from matscan.errors import MatscanError
from matscan.mapset import MapSet
from matscan.materials.noise import (
    blur,
    cells,
    fractal_noise,
    grid_coords,
    normals_from_height,
    smoothstep,
    spectral_noise,
)

#: Linear F0 of metals (Real-Time Rendering, 4th ed., Table 9.2).
METALS: dict[str, tuple[float, float, float]] = {
    "gold": (1.000, 0.766, 0.336),
    "silver": (0.972, 0.960, 0.915),
    "aluminium": (0.913, 0.922, 0.924),
    "copper": (0.955, 0.638, 0.538),
    "iron": (0.562, 0.565, 0.578),
    "chromium": (0.549, 0.556, 0.554),
    "titanium": (0.542, 0.497, 0.449),
    "nickel": (0.660, 0.609, 0.526),
    "brass": (0.910, 0.778, 0.423),
}


# --- helpers -------------------------------------------------------------------


def _u(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=g))


def _i(g: torch.Generator, lo: int, hi: int) -> int:
    """Integer in [lo, hi]."""
    return int(torch.randint(lo, hi + 1, (), generator=g))


def _choice(g: torch.Generator, options: list | tuple):
    return options[_i(g, 0, len(options) - 1)]


def random_colour(g: torch.Generator, sat: tuple[float, float], val: tuple[float, float]) -> Tensor:
    """A linear RGB colour (3, 1, 1) drawn in HSV over the sRGB-encoded cube."""
    rgb = colorsys.hsv_to_rgb(_u(g, 0, 1), _u(g, *sat), _u(g, *val))
    return srgb_to_linear(torch.tensor(rgb, dtype=torch.float32)).view(3, 1, 1)


def _dielectric_f0(g: torch.Generator, lo: float = 0.02, hi: float = 0.06) -> Tensor:
    return torch.full((3, 1, 1), _u(g, lo, hi))


def _finish(
    size: int,
    diffuse: Tensor,
    specular: Tensor,
    roughness: Tensor,
    height_mm: Tensor,
    mm_per_px: float,
    alpha: Tensor | None = None,
    emissive: Tensor | None = None,
) -> MapSet:
    def full(t: Tensor, c: int) -> Tensor:
        return t.expand(c, size, size).clamp(0, 1).contiguous().float()

    h = height_mm.expand(size, size).float()
    return MapSet(
        diffuse=full(diffuse, 3),
        specular=full(specular, 3),
        roughness=full(roughness, 1),
        normal=normals_from_height(h, mm_per_px),
        alpha=None if alpha is None else full(alpha, 1),
        emissive=None if emissive is None else full(emissive, 3),
        height=(h - h.mean())[None].contiguous(),
    )


def _print_pattern(size: int, g: torch.Generator) -> Tensor:
    """A printed/dyed motif mask in [0, 1]: blobs, stripes, checks, dots or rings."""
    kind = _choice(g, ["blobs", "stripes", "checks", "dots", "rings"])
    if kind == "blobs":
        return smoothstep(-0.05, 0.05, spectral_noise(size, g, _u(g, 0.04, 0.15)) - _u(g, -0.5, 0.8))
    n = 2 * _i(g, 1, 6)  # even: checks alternate across the tile's wrap-around too
    col, row, fx, fy = grid_coords(size, n, n)
    if kind == "stripes":
        return smoothstep(0.45, 0.55, fx) if _u(g, 0, 1) < 0.5 else smoothstep(0.45, 0.55, fy)
    if kind == "checks":
        return ((col + row) % 2).float()
    r = torch.sqrt((fx - 0.5) ** 2 + (fy - 0.5) ** 2)
    if kind == "dots":
        rad = _u(g, 0.15, 0.4)
        return 1 - smoothstep(rad - 0.04, rad + 0.04, r)
    rad = _u(g, 0.25, 0.4)
    return 1 - smoothstep(0.03, 0.07, (r - rad).abs())


# --- woven and knitted fabrics -------------------------------------------------

#: Weave repeats: 1 where the warp (vertical yarn) is on top.
WEAVES: dict[str, list[list[int]]] = {
    "plain": [[1, 0], [0, 1]],
    "twill": [[1, 1, 0, 0], [0, 1, 1, 0], [0, 0, 1, 1], [1, 0, 0, 1]],
    "satin": [[1, 0, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 0, 1], [0, 1, 0, 0, 0], [0, 0, 0, 1, 0]],
}


def woven(size: int, g: torch.Generator, mm_per_px: float, weave: str = "plain") -> MapSet:
    """Woven cloth: yarn-level height, fibre texture, yarn-dyed or printed colour.

    Ranges: 12–48 threads per tile; yarn height 0.05–0.25 mm; F0 0.02–0.05;
    roughness 0.55–0.9 (plain, twill), 0.3–0.55 (satin: long floats, sheen).
    """
    pattern = torch.tensor(WEAVES[weave], dtype=torch.float32)
    rep = pattern.shape[0]
    n = rep * max(1, _i(g, 12, 48) // rep)
    col, row, fx, fy = grid_coords(size, n, n)
    warp_up = pattern[row % rep, col % rep]
    width = _u(g, 0.7, 0.95)
    # yarn cross-sections (cylinders) and arching along the yarn where it floats
    across_warp = (1 - ((fx - 0.5) / (width / 2)) ** 2).clamp_min(0).sqrt()
    across_weft = (1 - ((fy - 0.5) / (width / 2)) ** 2).clamp_min(0).sqrt()
    arch_warp = 0.6 + 0.4 * torch.sin(math.pi * fy)
    arch_weft = 0.6 + 0.4 * torch.sin(math.pi * fx)
    h_warp = across_warp * arch_warp
    h_weft = across_weft * arch_weft
    top = torch.where(warp_up > 0, h_warp, h_weft)
    under = torch.where(warp_up > 0, h_weft, h_warp) * 0.5
    yarn = torch.maximum(top, under)
    amp = _u(g, 0.05, 0.25)
    fibre_v = spectral_noise(size, g, 0.3 / n, stretch=6, angle=math.pi / 2)
    fibre_h = spectral_noise(size, g, 0.3 / n, stretch=6, angle=0.0)
    fibre = torch.where(warp_up > 0, fibre_v, fibre_h)
    height = amp * (yarn + 0.08 * fibre)

    warp_colour = random_colour(g, (0.1, 0.9), (0.15, 0.95))
    weft_colour = warp_colour if _u(g, 0, 1) < 0.5 else random_colour(g, (0.1, 0.9), (0.15, 0.95))
    on_top_warp = (h_warp >= h_weft) == (warp_up > 0)
    colour = torch.where(on_top_warp, warp_colour, weft_colour)
    if _u(g, 0, 1) < 0.4:  # printed motif over the weave
        ink = random_colour(g, (0.3, 1.0), (0.05, 0.8))
        colour = torch.lerp(colour, ink, _print_pattern(size, g) * _u(g, 0.6, 1.0))
    shade = 0.55 + 0.45 * yarn  # fibres in the valleys are darker (self-shadowing, denser dye)
    diffuse = colour * shade * (1 + 0.08 * fibre)
    lo, hi = (0.3, 0.55) if weave == "satin" else (0.55, 0.9)
    rough = _u(g, lo, hi) + 0.05 * fibre - 0.05 * yarn
    return _finish(size, diffuse, _dielectric_f0(g, 0.02, 0.05), rough, height, mm_per_px)


def knit(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Jersey knit: rows of V-shaped loops (two tilted legs per stitch).

    Ranges: 8–32 wales per tile; loop height 0.1–0.4 mm; F0 0.02–0.05;
    roughness 0.6–0.95; dyed, with course stripes half the time.
    """
    wales = _i(g, 8, 32)
    courses = max(2, round(wales * _u(g, 1.0, 1.6)))
    col, row, fx, fy = grid_coords(size, wales, courses)
    tilt = _u(g, 0.25, 0.45)
    legs = []
    for centre, sign in ((0.3, 1.0), (0.7, -1.0)):
        x = fx - centre - sign * tilt * (fy - 0.5)
        legs.append((1 - (x / 0.2) ** 2).clamp_min(0).sqrt() * (0.7 + 0.3 * torch.sin(math.pi * fy)))
    loop = torch.maximum(*legs)
    fibre = spectral_noise(size, g, 0.25 / wales, stretch=4, angle=math.pi / 2)
    height = _u(g, 0.1, 0.4) * (loop + 0.1 * fibre)
    colour = random_colour(g, (0.1, 0.9), (0.1, 0.9))
    if _u(g, 0, 1) < 0.5:
        other = random_colour(g, (0.1, 0.9), (0.1, 0.9))
        period = _i(g, 2, 6)
        colour = torch.where((row // period) % 2 == 0, colour, other)
    diffuse = colour * (0.5 + 0.5 * loop) * (1 + 0.08 * fibre)
    rough = _u(g, 0.6, 0.95) + 0.04 * fibre
    return _finish(size, diffuse, _dielectric_f0(g, 0.02, 0.05), rough, height, mm_per_px)


# --- leather, paper, paint, plastic ---------------------------------------------


def leather(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Grained leather: cellular grain, pores, creases, finish gloss.

    Ranges: 40–600 grain cells per tile (large for embossed croc); grain depth
    0.03–0.25 mm; F0 0.03–0.05; roughness 0.3–0.7 (tops smoother when polished).
    """
    count = _i(g, 40, 600)
    f1, f2, value = cells(size, g, count)
    wall = float(size) / math.sqrt(count) * _u(g, 0.04, 0.12)
    grain = torch.exp(-(f2 - f1) / wall)
    pores = (spectral_noise(size, g, 0.004) - 1.6).clamp_min(0)
    creases = smoothstep(0.9, 1.0, 1 - spectral_noise(size, g, 0.08, stretch=4, angle=_u(g, 0, math.pi)).abs())
    depth = _u(g, 0.03, 0.25)
    height = depth * (1 - grain) - 0.3 * depth * pores - 0.4 * depth * creases
    height = height + 0.2 * depth * spectral_noise(size, g, 0.1)
    colour = random_colour(g, (0.2, 0.9), (0.08, 0.7))
    if _u(g, 0, 1) < 0.5:  # classic browns
        colour = srgb_to_linear(torch.tensor([_u(g, 0.3, 0.7), _u(g, 0.15, 0.4), _u(g, 0.05, 0.2)])).view(3, 1, 1)
    mottle = fractal_noise(size, g, 0.2)
    diffuse = colour * (1 + 0.15 * mottle) * (1 - 0.4 * grain) * (1 + 0.1 * (value - 0.5))
    base = _u(g, 0.3, 0.7)
    rough = base + 0.15 * grain + 0.1 * pores - 0.05 * (1 - grain)
    return _finish(size, diffuse, _dielectric_f0(g, 0.03, 0.05), rough, height, mm_per_px)


def paper(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Paper and card: fibre texture, optional print (halftone or solid ink), coated or not.

    Ranges: fibre relief 0.005–0.03 mm; F0 0.03–0.045; roughness 0.65–0.95
    (uncoated), 0.2–0.45 (coated card).
    """
    fibres = sum(spectral_noise(size, g, _u(g, 0.003, 0.01), stretch=5, angle=_u(g, 0, math.pi)) for _ in range(3))
    fibres = fibres / 3
    height = _u(g, 0.005, 0.03) * fibres + 0.01 * spectral_noise(size, g, 0.1)
    white = _u(g, 0.6, 0.9)
    base = torch.tensor([white, white, white * _u(g, 0.85, 1.0)]).view(3, 1, 1)
    if _u(g, 0, 1) < 0.3:
        base = random_colour(g, (0.1, 0.8), (0.3, 0.9))
    diffuse = base * (1 + 0.04 * fibres)
    coated = _u(g, 0, 1) < 0.3
    rough = torch.full((1, 1), _u(g, 0.2, 0.45) if coated else _u(g, 0.65, 0.95)) + 0.03 * fibres
    if _u(g, 0, 1) < 0.7:
        mask = _print_pattern(size, g)
        if _u(g, 0, 1) < 0.5:  # halftone: ink coverage becomes dot size
            cells_n = _i(g, 20, 80)
            _, _, fx, fy = grid_coords(size, cells_n, cells_n)
            r = torch.sqrt((fx - 0.5) ** 2 + (fy - 0.5) ** 2)
            mask = (r < 0.7 * mask.sqrt()).float()
        ink = random_colour(g, (0.4, 1.0), (0.05, 0.7))
        diffuse = torch.lerp(diffuse, diffuse * ink / ink.max().clamp_min(1e-3), mask)
        rough = rough - mask * _u(g, 0.0, 0.25)
    return _finish(size, diffuse, _dielectric_f0(g, 0.03, 0.045), rough, height, mm_per_px)


def painted(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Painted surfaces: brush strokes or orange peel, scratches, gloss to matte.

    Ranges: relief 0.005–0.05 mm; F0 0.04–0.05; roughness 0.08–0.7.
    """
    strokes = spectral_noise(size, g, _u(g, 0.01, 0.04), stretch=_u(g, 3, 10), angle=_u(g, 0, math.pi))
    peel = spectral_noise(size, g, _u(g, 0.01, 0.03))
    relief = strokes if _u(g, 0, 1) < 0.5 else peel
    height = _u(g, 0.005, 0.05) * relief
    colour = random_colour(g, (0.2, 1.0), (0.1, 0.95))
    if _u(g, 0, 1) < 0.4:
        colour = torch.lerp(colour, random_colour(g, (0.2, 1.0), (0.1, 0.95)), _print_pattern(size, g))
    scratches = smoothstep(0.97, 1.0, 1 - spectral_noise(size, g, 0.005, stretch=30, angle=_u(g, 0, math.pi)).abs())
    height = height - 0.01 * scratches
    rough = _u(g, 0.08, 0.7) + 0.2 * scratches + 0.02 * relief
    diffuse = colour * (1 + 0.05 * relief) * (1 - 0.3 * scratches)
    return _finish(size, diffuse, _dielectric_f0(g, 0.04, 0.05), rough, height, mm_per_px)


def plastic(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Moulded plastic: smooth or textured (leather-like or sand-blast grain).

    Ranges: texture 0.005–0.06 mm; F0 0.04–0.05; roughness 0.05–0.6.
    """
    if _u(g, 0, 1) < 0.5:
        f1, f2, _ = cells(size, g, _i(g, 100, 1500))
        relief = torch.exp(-(f2 - f1) / 2.0)
    else:
        relief = spectral_noise(size, g, _u(g, 0.002, 0.01))
    height = _u(g, 0.005, 0.06) * relief
    colour = random_colour(g, (0.0, 1.0), (0.03, 0.95))
    rough = _u(g, 0.05, 0.6) + 0.05 * relief
    return _finish(size, colour * (1 + 0.03 * relief), _dielectric_f0(g, 0.04, 0.05), rough, height, mm_per_px)


# --- metals and foil -------------------------------------------------------------


def _metal_f0(g: torch.Generator) -> Tensor:
    f0 = torch.tensor(METALS[_choice(g, list(METALS))]).view(3, 1, 1)
    return (f0 * _u(g, 0.85, 1.0)).clamp(0, 1)


def metal_brushed(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Brushed metal: fine grooves along one direction.

    Ranges: groove depth 0.002–0.015 mm; F0 from ``METALS``; diffuse 0–0.02;
    roughness 0.15–0.5.
    """
    angle = _choice(g, [0.0, math.pi / 2, _u(g, 0, math.pi)])
    grooves = spectral_noise(size, g, _u(g, 0.002, 0.006), stretch=_u(g, 20, 60), angle=angle)
    height = _u(g, 0.002, 0.015) * grooves
    f0 = _metal_f0(g) * (1 + 0.03 * grooves)
    rough = _u(g, 0.15, 0.5) + 0.03 * grooves
    return _finish(size, torch.full((3, 1, 1), _u(g, 0, 0.02)), f0, rough, height, mm_per_px)


def metal_embossed(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Embossed or hammered metal: dimples, diamonds or ribs, with wear.

    Ranges: relief 0.05–0.4 mm; F0 from ``METALS``; roughness 0.1–0.45.
    """
    kind = _choice(g, ["hammered", "diamond", "ribs"])
    if kind == "hammered":
        f1, _, _ = cells(size, g, _i(g, 20, 200))
        relief = -(1 - (f1 / f1.max()) ** 2)
    else:
        n = _i(g, 4, 20)
        _, _, fx, fy = grid_coords(size, n, n)
        relief = (
            1 - 2 * torch.maximum((fx - 0.5).abs(), (fy - 0.5).abs()) if kind == "diamond" else torch.sin(math.pi * fx)
        )
        relief = blur(relief, 1.0)
    height = _u(g, 0.05, 0.4) * relief
    wear = fractal_noise(size, g, 0.1)
    f0 = _metal_f0(g)
    rough = _u(g, 0.1, 0.45) + 0.05 * wear
    diffuse = torch.full((3, 1, 1), _u(g, 0, 0.02)) * (1 + 0.5 * wear.clamp_min(0))
    return _finish(size, diffuse, f0, rough, height, mm_per_px)


def _base(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    family = _choice(g, ["paper", "leather", "woven_plain", "plastic"])
    return GENERATORS[family](size, g, mm_per_px)


def foil_print(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Hot-stamped metallic foil on paper, leather, cloth or plastic.

    The foil is flat (stamped), metallic (F0 from ``METALS``, diffuse ≈ 0.01) and
    smooth (roughness 0.1–0.35), over a dielectric base from another family.
    """
    base = _base(size, g, mm_per_px)
    mask = _print_pattern(size, g)[None]
    f0 = _metal_f0(g)
    height = base.height * (1 - mask) + mask * (float(base.height.mean()) - _u(g, 0.0, 0.05))
    return _finish(
        size,
        torch.lerp(base.diffuse, torch.full((3, 1, 1), 0.01), mask),
        torch.lerp(base.specular, f0.expand(3, size, size), mask),
        torch.lerp(base.roughness, torch.full((1, 1, 1), _u(g, 0.1, 0.35)), mask),
        height[0],
        mm_per_px,
    )


# --- special materials: holes and emission --------------------------------------


def mesh(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Mesh fabric or perforated sheet: a regular grid of round or square holes (alpha).

    Ranges: 4–24 holes per tile side; hole size 30–70% of the pitch.
    """
    n = _i(g, 4, 24)
    _, _, fx, fy = grid_coords(size, n, n)
    radius = _u(g, 0.15, 0.35)
    if _u(g, 0, 1) < 0.5:
        dist = torch.sqrt((fx - 0.5) ** 2 + (fy - 0.5) ** 2)
    else:
        dist = torch.maximum((fx - 0.5).abs(), (fy - 0.5).abs())
    edge = 1.5 * n / size
    alpha = smoothstep(radius - edge, radius + edge, dist)
    body = _choice(g, ["woven_plain", "plastic", "metal_brushed"])
    base = GENERATORS[body](size, g, mm_per_px)
    rim = smoothstep(radius, radius + 0.15, dist)
    height = base.height[0] + _u(g, 0.05, 0.2) * rim
    return _finish(size, base.diffuse, base.specular, base.roughness, height, mm_per_px, alpha=alpha)


def lace(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Lace: an irregular net of threads (cell walls) with holes between them.

    Ranges: 10–120 cells per tile; thread width 5–15% of a cell; white, cream,
    black or dyed.
    """
    count = _i(g, 10, 120)
    f1, f2, _ = cells(size, g, count)
    pitch = size / math.sqrt(count)
    width = pitch * _u(g, 0.05, 0.15)
    walls = 1 - smoothstep(width * 0.6, width * 1.4, f2 - f1)
    motif = smoothstep(0.4, 0.6, spectral_noise(size, g, _u(g, 0.05, 0.12)))
    alpha = torch.maximum(walls, motif * (_u(g, 0, 1) < 0.5))
    thread = spectral_noise(size, g, 0.01, stretch=4)
    colour = _choice(
        g,
        [torch.full((3, 1, 1), 0.8), torch.tensor([0.75, 0.65, 0.45]).view(3, 1, 1), torch.full((3, 1, 1), 0.02)],
    )
    if _u(g, 0, 1) < 0.3:
        colour = random_colour(g, (0.3, 0.9), (0.2, 0.9))
    height = _u(g, 0.05, 0.2) * (alpha + 0.1 * thread)
    rough = _u(g, 0.5, 0.9) + 0.03 * thread
    return _finish(
        size, colour * (1 + 0.05 * thread), _dielectric_f0(g, 0.02, 0.05), rough, height, mm_per_px, alpha=alpha
    )


def fluorescent_print(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Fluorescent ink on paper or cloth: bright ink whose emission adds under any light.

    Ranges: emission 0.05–0.3 of full scale in the ink's colour; ink diffuse
    saturated and bright.
    """
    base = _base(size, g, mm_per_px)
    mask = _print_pattern(size, g)[None]
    hue = _choice(g, [(1.0, 0.1, 0.6), (0.2, 1.0, 0.1), (1.0, 0.5, 0.0), (1.0, 1.0, 0.1), (0.1, 0.5, 1.0)])
    ink = srgb_to_linear(torch.tensor(hue)).view(3, 1, 1)
    emissive = mask * ink * _u(g, 0.05, 0.3)
    return _finish(
        size,
        torch.lerp(base.diffuse, ink * _u(g, 0.7, 1.0), mask),
        base.specular,
        base.roughness,
        base.height[0],
        mm_per_px,
        alpha=base.alpha,
        emissive=emissive,
    )


Generator = Callable[[int, torch.Generator, float], MapSet]

GENERATORS: dict[str, Generator] = {
    "woven_plain": lambda s, g, m: woven(s, g, m, "plain"),
    "woven_twill": lambda s, g, m: woven(s, g, m, "twill"),
    "woven_satin": lambda s, g, m: woven(s, g, m, "satin"),
    "knit": knit,
    "leather": leather,
    "paper": paper,
    "painted": painted,
    "plastic": plastic,
    "metal_brushed": metal_brushed,
    "metal_embossed": metal_embossed,
    "foil_print": foil_print,
    "mesh": mesh,
    "lace": lace,
    "fluorescent_print": fluorescent_print,
}
FAMILIES = tuple(GENERATORS)

#: How often each family is drawn by :func:`random_material` (relative weights):
#: fabrics and leathers dominate, as in the paper's data and our users' swatches.
WEIGHTS: dict[str, float] = {
    "woven_plain": 2.0,
    "woven_twill": 1.5,
    "woven_satin": 1.0,
    "knit": 1.0,
    "leather": 2.5,
    "paper": 1.0,
    "painted": 1.0,
    "plastic": 1.0,
    "metal_brushed": 1.0,
    "metal_embossed": 1.0,
    "foil_print": 1.5,
    "mesh": 0.5,
    "lace": 0.5,
    "fluorescent_print": 0.5,
}


def generate(family: str, size: int = 256, seed: int = 0, mm_per_px: float | None = None) -> MapSet:
    """One map set of a family, deterministic from ``seed``.

    ``mm_per_px`` defaults to a tile of 120 mm (the dome24 field) across ``size`` pixels.
    """
    if family not in GENERATORS:
        raise MatscanError(f"family: {family!r} is not one of {', '.join(FAMILIES)}")
    if size < 8:
        raise MatscanError(f"size: {size} is too small (at least 8 pixels)")
    g = torch.Generator().manual_seed(int(seed))
    return GENERATORS[family](size, g, mm_per_px if mm_per_px is not None else 120.0 / size)


def random_material(size: int = 256, seed: int = 0, mm_per_px: float | None = None) -> tuple[str, MapSet]:
    """A map set of a family drawn by ``WEIGHTS``; returns (family, maps)."""
    g = torch.Generator().manual_seed((int(seed) * 7919 + 17) % 2**63)
    weights = torch.tensor([WEIGHTS[f] for f in FAMILIES])
    family = FAMILIES[int(torch.multinomial(weights, 1, generator=g))]
    return family, generate(family, size, int(torch.randint(0, 2**40, (), generator=g)), mm_per_px)
