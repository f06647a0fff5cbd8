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
fluorescent_print; and, since prior v2, leather_embossed, weave_heavy, corrugated
(strong relief), metallic_print, worn, varnished_wood (specular and roughness that
vary over the surface) and dark_glossy; since prior v3, dark_relief (dark and glossy in
deep relief); since prior v5, glossy_coat (bright and glossy).

Priors (``PRIORS``): :func:`random_material` draws a family by the weights of a
prior version. "v1" (the default) holds the first fourteen families and draws, for
every seed, the material it always drew: published numbers (``procedural:N`` in
evaluate, the model card's validation set) are reproduced from those seeds. "v2"
adds the seven later families at 41% of the draws: v1's materials are mostly flat
(a median tilt under 10° in 55% of its draws at training scales, under 15° in 69%)
and most hold one specular value. "v3" adds dark_relief at 2 in 29 (7%): v2's dark
glossy surfaces all lie nearly flat. "v4" draws the same families, the dark glossy ones
(dark_glossy 4, dark_relief 6) at 10 in 35 (29%): after 9,000 steps at v3's share a
network still read such surfaces rougher the more lights it saw (docs/results.md).
"v5" adds glossy_coat (bright glossy paint, glaze, plastic, laminate) at 5 in 40.
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
    smoothstep,
    spectral_noise,
)
from matscan.reconstruct.surface import normals_from_height

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


# --- prior v2: strong relief ------------------------------------------------------
#
# These set relief by slope, not depth: a height of tan(θ) × the feature's width in mm
# tilts the normals alike at every scale training draws (0.04–0.47 mm per pixel), where a
# depth fixed in mm gives walls at the fine end and a nearly flat surface at the coarse end.
# Measured tilt (the angle between the normal and +z) in the docstrings: the median over a
# material's pixels, for 64 materials (seeds 0–63, 128² at scales log-uniform in 0.04–0.47
# mm/px, the training draw), given as the 10th / 50th / 90th percentiles over materials.


def leather_embossed(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Embossed and pebbled leather: domed cells (pebble grain, croc and ostrich scales)
    between grooves, a fine grain on top, the domes' finish glossier than the grooves.

    Ranges: 16–400 cells per tile; each dome rises over 60–100% of the half-pitch from
    its groove, with a wall slope of 40°–65° (a 3 mm cell: 0.8–1.6 mm deep); F0
    0.03–0.05; roughness 0.25–0.6 on the domes, 0.05–0.2 rougher in the grooves;
    browns, black or dyed, grooves darker. Measured median tilt 21° / 27° / 41°
    (lowest 18°); 79% of the surface (mean over materials) tilts more than 15°.
    """
    count = _i(g, 16, 400)
    f1, f2, value = cells(size, g, count)
    pitch = size / math.sqrt(count)  # pixels
    reach = _u(g, 0.6, 1.0) * pitch / 2  # pixels from the groove to the dome's flat top
    dome = torch.sin(math.pi / 2 * ((f2 - f1) / 2 / reach).clamp(max=1))
    slope = math.tan(math.radians(_u(g, 40, 65)))
    depth = slope * reach * mm_per_px * 2 / math.pi  # the sine profile's steepest slope is `slope`
    grain = spectral_noise(size, g, _u(g, 0.004, 0.012))
    height = depth * (dome + 0.03 * grain)
    colour = random_colour(g, (0.2, 0.9), (0.05, 0.6))
    if _u(g, 0, 1) < 0.5:  # classic browns
        colour = srgb_to_linear(torch.tensor([_u(g, 0.3, 0.7), _u(g, 0.15, 0.4), _u(g, 0.05, 0.2)])).view(3, 1, 1)
    diffuse = colour * (0.55 + 0.45 * dome) * (1 + 0.15 * (value - 0.5)) * (1 + 0.05 * grain)
    rough = _u(g, 0.25, 0.6) + _u(g, 0.05, 0.2) * (1 - dome) + 0.02 * grain
    return _finish(size, diffuse, _dielectric_f0(g, 0.03, 0.05), rough, height, mm_per_px)


#: Heavy weave repeats (1 where the warp is on top): basket pairs the yarns.
HEAVY_WEAVES: dict[str, list[list[int]]] = {
    "basket": [[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1], [0, 0, 1, 1]],
    "plain": WEAVES["plain"],
    "twill": WEAVES["twill"],
}


def weave_heavy(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Heavy weaves: canvas, basket weave, jute and sisal, with yarns about as thick as
    they are wide.

    Ranges: 4–16 yarns per tile; yarns 75–95% of the pitch wide, elliptical in section
    with height 0.6–1.1 × the half width (1: round), crimp 10–30%; natural fibre
    (jute, sisal, linen) or dyed; F0 0.02–0.05; roughness 0.6–0.95. Measured median
    tilt 20° / 26° / 32° (lowest 18°); 76% of the surface tilts more than 15°.
    """
    kind = _choice(g, list(HEAVY_WEAVES))
    pattern = torch.tensor(HEAVY_WEAVES[kind], dtype=torch.float32)
    rep = pattern.shape[0]
    n = rep * max(1, _i(g, 4, 16) // rep)
    col, row, fx, fy = grid_coords(size, n, n)
    warp_up = pattern[row % rep, col % rep] > 0
    width = _u(g, 0.75, 0.95)
    crimp = _u(g, 0.1, 0.3)
    h_warp = (1 - ((fx - 0.5) / (width / 2)) ** 2).clamp_min(0).sqrt() * (1 - crimp + crimp * torch.sin(math.pi * fy))
    h_weft = (1 - ((fy - 0.5) / (width / 2)) ** 2).clamp_min(0).sqrt() * (1 - crimp + crimp * torch.sin(math.pi * fx))
    yarn = torch.maximum(torch.where(warp_up, h_warp, h_weft), 0.5 * torch.where(warp_up, h_weft, h_warp))
    # where the warp shows, antialiased; blurring also lets a yarn dive under its neighbour, not step down
    sigma = max(0.7, 0.03 * size / n)
    warp_shows = blur(torch.where(warp_up, h_warp >= 0.5 * h_weft, 0.5 * h_warp > h_weft).float(), sigma)
    yarn = blur(yarn, sigma)
    fibre = torch.lerp(
        spectral_noise(size, g, 0.15 / n, stretch=5, angle=0.0),
        spectral_noise(size, g, 0.15 / n, stretch=5, angle=math.pi / 2),
        warp_shows,
    )
    half_width_mm = width / 2 * size / n * mm_per_px
    height = _u(g, 0.6, 1.1) * half_width_mm * (yarn + 0.05 * fibre)
    if _u(g, 0, 1) < 0.4:  # undyed natural fibre
        warp_colour = srgb_to_linear(torch.tensor([_u(g, 0.55, 0.8), _u(g, 0.45, 0.65), _u(g, 0.25, 0.45)]))
        warp_colour = warp_colour.view(3, 1, 1)
    else:
        warp_colour = random_colour(g, (0.1, 0.9), (0.15, 0.9))
    weft_colour = warp_colour if _u(g, 0, 1) < 0.5 else random_colour(g, (0.1, 0.9), (0.15, 0.9))
    colour = torch.lerp(weft_colour, warp_colour, warp_shows)
    diffuse = colour * (0.45 + 0.55 * yarn) * (1 + 0.1 * fibre)
    rough = _u(g, 0.6, 0.95) + 0.05 * fibre - 0.05 * yarn
    return _finish(size, diffuse, _dielectric_f0(g, 0.02, 0.05), rough, height, mm_per_px)


def corrugated(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Ribbed and corrugated surfaces: corrugated card, ribbed rubber matting, corduroy,
    corrugated plastic sheet.

    Ranges: 3–16 ribs per tile, along an axis or a diagonal; profile by material: sine
    (card, sheet; steepest slope 30°–50°), trapezoid (rubber; flanks of 30°–50° over
    50–90% of the surface) or round wales (corduroy; height 0.6–1.0 × the half width);
    card: browns, roughness 0.7–0.9, F0 0.03–0.04; rubber: albedo 0.02–0.08, roughness
    0.4–0.7, F0 0.04–0.05; corduroy: dyed, roughness 0.75–0.95, F0 0.02–0.04; sheet:
    any colour, roughness 0.15–0.5, F0 0.04–0.05. Measured median tilt 20° / 29° / 36°
    (lowest 15°); 79% of the surface tilts more than 15°.
    """
    kind = _choice(g, ["card", "rubber", "corduroy", "sheet"])
    ribs = _i(g, 3, 16)
    across = _choice(g, [0, 0, _i(g, 1, ribs), -_i(g, 1, ribs)])  # diagonal ribs: another integer wave number
    kx, ky = (ribs, across) if _u(g, 0, 1) < 0.5 else (across, ribs)
    u = (torch.arange(size, dtype=torch.float32) + 0.5) / size
    t = (kx * u[None, :] + ky * u[:, None]) % 1.0  # phase across the ribs, periodic over the tile
    pitch_mm = size * mm_per_px / math.hypot(kx, ky)
    steepest = math.tan(math.radians(_u(g, 30, 50)))
    if kind == "corduroy":  # round wales with a narrow groove between
        half = _u(g, 0.4, 0.48)
        profile = (1 - ((t - 0.5) / half) ** 2).clamp_min(0).sqrt()
        height = _u(g, 0.6, 1.0) * half * pitch_mm * profile
    elif kind == "rubber":  # flat tops and valleys joined by straight flanks
        ramp = _u(g, 0.25, 0.45)  # each flank's share of the period
        profile = smoothstep(0.5 - ramp, 0.5 + ramp, 1 - 2 * (t - 0.5).abs())
        height = steepest * ramp * pitch_mm / 1.5 * profile  # smoothstep's steepest slope is 1.5 / width
    else:
        profile = 0.5 - 0.5 * torch.cos(2 * math.pi * t)
        height = steepest * pitch_mm / math.pi * profile
    detail = spectral_noise(size, g, _u(g, 0.003, 0.01))
    height = height + 0.02 * pitch_mm * detail * (0.3 if kind == "sheet" else 1.0)
    if kind == "card":
        colour = srgb_to_linear(torch.tensor([_u(g, 0.55, 0.8), _u(g, 0.4, 0.6), _u(g, 0.25, 0.4)])).view(3, 1, 1)
        rough, f0 = _u(g, 0.7, 0.9), _dielectric_f0(g, 0.03, 0.04)
    elif kind == "rubber":
        colour = torch.full((3, 1, 1), _u(g, 0.02, 0.08))
        rough, f0 = _u(g, 0.4, 0.7), _dielectric_f0(g, 0.04, 0.05)
    elif kind == "corduroy":
        colour = random_colour(g, (0.2, 0.9), (0.1, 0.8))
        rough, f0 = _u(g, 0.75, 0.95), _dielectric_f0(g, 0.02, 0.04)
    else:
        colour = random_colour(g, (0.0, 1.0), (0.1, 0.95))
        rough, f0 = _u(g, 0.15, 0.5), _dielectric_f0(g, 0.04, 0.05)
    shade = 0.6 + 0.4 * profile if kind in ("corduroy", "card") else torch.ones(1, 1)
    diffuse = colour * shade * (1 + 0.05 * detail)
    return _finish(size, diffuse, f0, rough + 0.03 * detail, height, mm_per_px)


# --- prior v2: specular and roughness that vary over the surface ----------------------


def metallic_print(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Metallic ink and foil printed on coated paper, card or plastic film: halftone
    dots, guilloche lines, solid shapes, or metal flakes in a clear coat.

    In the print: F0 from ``METALS`` (or aluminium tinted, as coloured foils are) times
    a density 0.7–1.0, diffuse 0.01–0.03, roughness 0.1–0.45. Between: F0 0.04–0.05,
    any colour, roughness 0.15–0.8. The print covers 5–95% of the tile, so the F0 map
    always holds both: measured on 64 materials (seeds 0–63, 128²), the 95th − 5th
    percentile of F0 (brightest channel) is at least 0.33 in every one (median 0.66).
    """
    base = random_colour(g, (0.0, 0.9), (0.1, 0.95))
    base_rough = _u(g, 0.15, 0.8)
    kind = _choice(g, ["halftone", "lines", "shapes", "flakes"])
    if kind == "halftone":  # dot size follows a smooth tone
        n = _i(g, 8, 40)
        _, _, fx, fy = grid_coords(size, n, n)
        tone = 0.2 + 0.6 * smoothstep(-1.5, 1.5, spectral_noise(size, g, _u(g, 0.1, 0.3)))
        r = torch.sqrt((fx - 0.5) ** 2 + (fy - 0.5) ** 2)
        edge = n / size  # one pixel in cell units
        mask = 1 - smoothstep(-edge, edge, r - 0.7 * tone.sqrt())
    elif kind == "lines":  # guilloche: wavy bands, periodic over the tile
        u = (torch.arange(size, dtype=torch.float32) + 0.5) / size
        k, m = _i(g, 4, 24), _i(g, 1, 4)
        wave = _u(g, 0.3, 1.5) * torch.sin(2 * math.pi * m * u)[None, :]
        t = (k * u[:, None] + wave) % 1.0
        half = _u(g, 0.2, 0.35)
        mask = 1 - smoothstep(half - 0.05, half + 0.05, (t - 0.5).abs())
    elif kind == "shapes":
        mask = _print_pattern(size, g)
    else:  # flakes: each cell a flake, metallic or not
        _, _, value = cells(size, g, _i(g, 300, 3000))
        mask = (value < _u(g, 0.3, 0.7)).float()
    mask = mask[None]
    f0 = _metal_f0(g)
    if _u(g, 0, 1) < 0.3:  # coloured foil: aluminium under a dyed lacquer
        f0 = torch.tensor(METALS["aluminium"]).view(3, 1, 1) * random_colour(g, (0.3, 0.8), (0.9, 1.0))
    f0 = f0 * _u(g, 0.8, 1.0)
    fibres = spectral_noise(size, g, 0.005)
    height = 0.005 * fibres - _u(g, 0.0, 0.02) * mask  # stamped foil sits a little lower
    return _finish(
        size,
        torch.lerp(base * (1 + 0.03 * fibres), torch.full((3, 1, 1), _u(g, 0.01, 0.03)), mask),
        torch.lerp(_dielectric_f0(g, 0.04, 0.05).expand(3, size, size), f0.expand(3, size, size), mask),
        torch.lerp(torch.full((1, 1, 1), base_rough), torch.full((1, 1, 1), _u(g, 0.1, 0.45)), mask),
        height[0],
        mm_per_px,
    )


def worn(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Worn and polished finishes: paint worn through to the metal beneath, tarnished
    metal rubbed bright, and matte dielectrics (leather, wood, stone) polished glossy
    where hands touch them. Wear follows the high points of a dented relief.

    Ranges: relief 0.005–0.05 mm; worn share 20–70% of the tile. Paint over metal:
    paint F0 0.04–0.05, roughness 0.35–0.75; bare metal F0 from ``METALS``, roughness
    0.12–0.3. Tarnished metal: F0 × 0.2–0.5 and roughness 0.5–0.8 in the tarnish,
    F0 × 0.9–1 and roughness 0.1–0.3 where polished. Polished dielectric: roughness
    0.55–0.9 matte, 0.1–0.3 polished, F0 0.04–0.05. Measured on 64 materials (seeds
    0–63, 128²), roughness's 95th − 5th percentile is at least 0.15 in every one
    (median 0.46); two in three also vary in F0 (metal against paint or tarnish).
    """
    kind = _choice(g, ["paint_on_metal", "tarnished_metal", "polished"])
    relief = fractal_noise(size, g, _u(g, 0.05, 0.2))
    height = _u(g, 0.005, 0.05) * relief
    wear = fractal_noise(size, g, _u(g, 0.03, 0.15)) + _u(g, 0.5, 1.5) * relief
    level = float(torch.quantile(wear.flatten(), 1 - _u(g, 0.2, 0.7)))
    soft = _u(g, 0.05, 0.3)
    mask = smoothstep(level - soft, level + soft, wear)[None]  # 1 where worn or polished
    metal = _metal_f0(g)
    if kind == "paint_on_metal":
        diffuse = torch.lerp(random_colour(g, (0.2, 1.0), (0.1, 0.9)), torch.full((3, 1, 1), 0.01), mask)
        f0 = torch.lerp(_dielectric_f0(g, 0.04, 0.05), metal, mask)
        rough = torch.lerp(torch.full((1, 1, 1), _u(g, 0.35, 0.75)), torch.full((1, 1, 1), _u(g, 0.12, 0.3)), mask)
        height = height - 0.01 * mask[0]  # the paint layer's thickness is gone there
    elif kind == "tarnished_metal":
        oxide = srgb_to_linear(torch.tensor([_u(g, 0.15, 0.4), _u(g, 0.1, 0.3), _u(g, 0.05, 0.2)])).view(3, 1, 1)
        diffuse = torch.lerp(oxide, torch.full((3, 1, 1), 0.01), mask)
        f0 = torch.lerp(metal * _u(g, 0.2, 0.5), metal * _u(g, 0.9, 1.0), mask)
        rough = torch.lerp(torch.full((1, 1, 1), _u(g, 0.5, 0.8)), torch.full((1, 1, 1), _u(g, 0.1, 0.3)), mask)
    else:
        colour = random_colour(g, (0.1, 0.9), (0.1, 0.8))
        diffuse = colour * (1 - _u(g, 0.0, 0.15) * mask)  # rubbed areas darken a little
        f0 = _dielectric_f0(g, 0.04, 0.05)
        rough = torch.lerp(torch.full((1, 1, 1), _u(g, 0.55, 0.9)), torch.full((1, 1, 1), _u(g, 0.1, 0.3)), mask)
    return _finish(size, diffuse, f0, rough + 0.02 * relief, height, mm_per_px)


#: Linear diffuse of woods under a clear finish (sRGB swatches of pine, oak, walnut,
#: mahogany and cherry, decoded).
WOODS: dict[str, tuple[float, float, float]] = {
    "pine": (0.85, 0.68, 0.45),
    "oak": (0.72, 0.53, 0.32),
    "walnut": (0.42, 0.28, 0.18),
    "mahogany": (0.55, 0.25, 0.15),
    "cherry": (0.65, 0.38, 0.24),
}


def varnished_wood(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Wood under varnish: growth rings (late wood darker), open pores along the grain,
    a clear coat glossy or satin, its roughness following the pores and brush marks.

    Ranges: 3–30 rings per tile; late wood 50–80% as bright; pores 0.01–0.04 mm deep;
    diffuse from ``WOODS`` × 0.6–1.1; varnish F0 0.04–0.05 (n ≈ 1.5), roughness
    0.05–0.35 on the wood, 0.1–0.4 rougher in the pores (an open-pore finish) or as
    smooth (filled); brush marks ± 0.03.
    """
    u = (torch.arange(size, dtype=torch.float32) + 0.5) / size
    rings = _i(g, 3, 30)
    along = _choice(g, [0.0, math.pi / 2])  # grain along x or y
    warp = _u(g, 0.3, 2.0) * spectral_noise(size, g, _u(g, 0.1, 0.3), stretch=4, angle=along)
    across = u[:, None].expand(size, size) if along == 0.0 else u[None, :].expand(size, size)
    phase = (rings * across + warp) % 1.0
    late = smoothstep(0.55, 0.8, phase) * (1 - smoothstep(0.9, 1.0, phase))
    pores = smoothstep(1.0, 2.0, spectral_noise(size, g, _u(g, 0.006, 0.012), stretch=8, angle=along))
    colour = torch.tensor(WOODS[_choice(g, list(WOODS))]) * _u(g, 0.85, 1.05)
    colour = srgb_to_linear(colour.clamp(0, 1)).view(3, 1, 1)
    diffuse = colour * (1 - _u(g, 0.2, 0.5) * late) * (1 - 0.4 * pores)
    height = -_u(g, 0.01, 0.04) * pores + 0.002 * warp
    brush = spectral_noise(size, g, 0.02, stretch=10, angle=along)
    open_pores = _u(g, 0, 1) < 0.6
    rough = _u(g, 0.06, 0.35) * (1 + 0.15 * brush) + (_u(g, 0.1, 0.4) * pores if open_pores else 0.0)
    return _finish(size, diffuse, _dielectric_f0(g, 0.04, 0.05), rough, height, mm_per_px)


# --- prior v2: dark and glossy ----------------------------------------------------------


def dark_glossy(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Dark glossy surfaces, where the highlight is nearly all there is to see: black
    leather, dark plastics, lacquer (piano black, urushi, dark tinted).

    Ranges: diffuse albedo (linear, every channel) at most 0.05; F0 0.04–0.05. Black
    leather: albedo 0.01–0.05, grain cells with walls of 10°–25°, roughness 0.2–0.4
    (+ 0.05 in the grain). Dark plastic: albedo 0.005–0.05, smooth or finely textured
    (slope up to 10°), roughness 0.05–0.35. Lacquer: albedo 0.002–0.03, orange peel
    below 3°, roughness 0.03–0.12, with fine scratches 0.1 rougher half the time.
    """
    kind = _choice(g, ["black_leather", "dark_plastic", "lacquer"])
    tint = random_colour(g, (0.0, 0.7), (1.0, 1.0))
    tint = tint / tint.max()
    if kind == "black_leather":
        count = _i(g, 100, 800)
        f1, f2, value = cells(size, g, count)
        pitch = size / math.sqrt(count)
        grain = 1 - torch.exp(-(f2 - f1) / (0.15 * pitch))
        height = math.tan(math.radians(_u(g, 10, 25))) * 0.15 * pitch * mm_per_px * grain
        albedo = _u(g, 0.01, 0.05) * (0.9 + 0.1 * value)
        rough = _u(g, 0.2, 0.4) + 0.05 * (1 - grain)
    elif kind == "dark_plastic":
        feature = _u(g, 0.003, 0.02)  # of the tile
        texture = spectral_noise(size, g, feature) * (_u(g, 0, 1) < 0.5)
        slope = math.tan(math.radians(_u(g, 0, 10)))
        height = slope * feature * size * mm_per_px / 4 * texture
        albedo = torch.full((1, 1), _u(g, 0.005, 0.05))
        rough = torch.full((1, 1), _u(g, 0.05, 0.35))
    else:
        feature = _u(g, 0.02, 0.06)
        peel = spectral_noise(size, g, feature)
        height = math.tan(math.radians(_u(g, 0.5, 3))) * feature * size * mm_per_px / 4 * peel
        albedo = torch.full((1, 1), _u(g, 0.002, 0.03))
        scratches = smoothstep(0.97, 1.0, 1 - spectral_noise(size, g, 0.005, stretch=30, angle=_u(g, 0, math.pi)).abs())
        rough = _u(g, 0.03, 0.12) + 0.1 * scratches * (_u(g, 0, 1) < 0.5)
    diffuse = (tint * albedo).clamp(max=DARK_ALBEDO_MAX)
    return _finish(size, diffuse, _dielectric_f0(g, 0.04, 0.05), rough, height, mm_per_px)


#: The most diffuse albedo (linear) :func:`dark_glossy` draws, in any channel.
DARK_ALBEDO_MAX = 0.05


# --- prior v3: dark, glossy and deep ----------------------------------------------------


def _to_median_tilt(shape: Tensor, degrees: float, mm_per_px: float) -> Tensor:
    """``shape`` (any units) scaled into a height field (mm) whose normals' median tilt
    is ``degrees``: the tilt is atan of the slope :func:`normals_from_height` takes
    (central differences), so scaling the height scales every slope by the same factor."""
    dx = (torch.roll(shape, -1, -1) - torch.roll(shape, 1, -1)) / 2
    dy = (torch.roll(shape, -1, -2) - torch.roll(shape, 1, -2)) / 2
    slope = (dx * dx + dy * dy).sqrt().median().clamp_min(1e-9)
    return shape * (math.tan(math.radians(degrees)) / slope * mm_per_px)


def dark_relief(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Dark glossy surfaces in deep relief, where the highlight breaks up over the slopes:
    deep-grained and pebbled black leather, textured black rubber, embossed dark plastic.
    :func:`dark_glossy` holds the shallow ones (walls of 10°–25°); here a grazing light
    lights only some slopes and every light finds a highlight somewhere, so a glossy
    surface can look rough to an eye that counts highlights.

    Ranges: diffuse albedo (linear, every channel) at most 0.05 (0.005–0.05, 10% lower in
    the hollows); F0 0.04–0.05; roughness 0.15–0.45 on the tops, 0–0.15 rougher in the
    hollows (polished tops, dust and wear below). Relief: cells (domed pebbles or a
    creased grain, 60–900 per tile) or band-limited noise (feature 0.01–0.04 of the
    tile, two octaves), scaled so that the normals' median tilt is 18°–40° at any scale.
    """
    kind = _choice(g, ["pebbled", "creased", "noise"])
    if kind == "noise":
        shape = fractal_noise(size, g, _u(g, 0.01, 0.04), octaves=2)
        shape = (shape - shape.min()) / (shape.max() - shape.min()).clamp_min(1e-9)
    else:
        count = _i(g, 60, 900)
        f1, f2, _ = cells(size, g, count)
        # walls are likelier near the jittered grid's lines, which meet the tile's edges:
        # a random shift (tiling is kept) puts the edges anywhere in a cell
        shift = (_i(g, 0, size - 1), _i(g, 0, size - 1))
        f1, f2 = torch.roll(f1, shift, (0, 1)), torch.roll(f2, shift, (0, 1))
        pitch = size / math.sqrt(count)
        if kind == "pebbled":  # rounded domes between narrow grooves
            shape = torch.sin(math.pi / 2 * ((f2 - f1) / (_u(g, 0.3, 0.5) * pitch)).clamp(max=1))
        else:  # sharp creases between flat-topped cells
            shape = 1 - torch.exp(-(f2 - f1) / (_u(g, 0.05, 0.15) * pitch))
        shape = shape + 0.05 * spectral_noise(size, g, _u(g, 0.004, 0.01))
    height = _to_median_tilt(shape, _u(g, 18, 40), mm_per_px)
    top = (shape - shape.min()) / (shape.max() - shape.min()).clamp_min(1e-9)  # 1 on the tops
    tint = random_colour(g, (0.0, 0.6), (1.0, 1.0))
    tint = tint / tint.max()
    albedo = _u(g, 0.005, 0.05) * (0.9 + 0.1 * top)
    diffuse = (tint * albedo).clamp(max=DARK_ALBEDO_MAX)
    rough = _u(g, 0.15, 0.45) + _u(g, 0.0, 0.15) * (1 - top)
    return _finish(size, diffuse, _dielectric_f0(g, 0.04, 0.05), rough, height, mm_per_px)


# --- prior v5: bright and glossy -----------------------------------------------------------


def glossy_coat(size: int, g: torch.Generator, mm_per_px: float) -> MapSet:
    """Bright glossy surfaces, where a light's highlight is a small sharp spot on a bright
    diffuse base and everywhere else the surface looks matte: gloss paint and enamel,
    glazed tile, glossy plastic, laminate, photo paper and clear-coated prints. Their
    roughness shows only in the spots and in the sheen a rougher finish would add
    around them, which is absent.

    Ranges: diffuse any colour (HSV saturation 0–0.9, value 0.3–0.95 in sRGB), a second
    colour printed in a motif 40% of the time; F0 0.04–0.05; roughness 0.03–0.25, ±0.02
    with the relief, and fine scratches 0.1 rougher 30% of the time. Relief: orange peel
    or brush marks (band-limited noise, feature 0.01–0.05 of the tile) scaled so that the
    normals' median tilt is 0.5°–4° at any scale.
    """
    if _u(g, 0, 1) < 0.5:
        shape = spectral_noise(size, g, _u(g, 0.01, 0.05))
    else:
        shape = spectral_noise(size, g, _u(g, 0.01, 0.04), stretch=_u(g, 3, 10), angle=_u(g, 0, math.pi))
    height = _to_median_tilt(shape, _u(g, 0.5, 4), mm_per_px)
    colour = random_colour(g, (0.0, 0.9), (0.3, 0.95))
    if _u(g, 0, 1) < 0.4:
        colour = torch.lerp(colour, random_colour(g, (0.0, 0.9), (0.3, 0.95)), _print_pattern(size, g))
    scratches = smoothstep(0.97, 1.0, 1 - spectral_noise(size, g, 0.005, stretch=30, angle=_u(g, 0, math.pi)).abs())
    bump = shape / shape.abs().max().clamp_min(1e-9)
    rough = _u(g, 0.03, 0.25) + 0.02 * bump + 0.1 * scratches * (_u(g, 0, 1) < 0.3)
    return _finish(size, colour, _dielectric_f0(g, 0.04, 0.05), rough.clamp_min(0.02), height, mm_per_px)


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
    "leather_embossed": leather_embossed,
    "weave_heavy": weave_heavy,
    "corrugated": corrugated,
    "metallic_print": metallic_print,
    "worn": worn,
    "varnished_wood": varnished_wood,
    "dark_glossy": dark_glossy,
    "dark_relief": dark_relief,
    "glossy_coat": glossy_coat,
}
FAMILIES = tuple(GENERATORS)

#: How often each family is drawn by :func:`random_material` under prior v1 (relative
#: weights): fabrics and leathers dominate, as in the paper's data and our users' swatches.
#: The v1 families and this order are frozen: published numbers are reproduced from their seeds.
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


#: Prior v2: v1's families at v1's weights, and the families v1 lacks (strong relief,
#: varying specular and roughness, dark gloss) drawn 11 times in 27 (41%).
WEIGHTS_V2: dict[str, float] = {
    **WEIGHTS,
    "leather_embossed": 2.0,
    "weave_heavy": 1.5,
    "corrugated": 1.0,
    "metallic_print": 1.5,
    "worn": 1.5,
    "varnished_wood": 1.5,
    "dark_glossy": 2.0,
}

#: Prior v3: v2, and dark glossy surfaces in deep relief (:func:`dark_relief`) drawn as
#: often as the shallow ones: the networks trained on v2 read a deep-grained black leather
#: (artist-black-leather, docs/results.md) rougher the more lights they see.
WEIGHTS_V3: dict[str, float] = {**WEIGHTS_V2, "dark_relief": 2.0}

#: Prior v4: v3's families, the dark glossy ones drawn 10 times in 35 (29%) instead of 4
#: in 29 (14%): their roughness lies in the highlights alone (the diffuse part is a few
#: percent), and v3's share left the networks guessing it from the light count.
WEIGHTS_V4: dict[str, float] = {**WEIGHTS_V3, "dark_glossy": 4.0, "dark_relief": 6.0}

#: Prior v5: v4's families, and bright glossy surfaces (:func:`glossy_coat`) drawn 5 times
#: in 40 (12.5%): under v4 (where smooth bright dielectrics are a few plastics and
#: varnished woods, about 3% of the draws) the networks read roughness 0.09–0.16 plastic
#: and varnish as 0.6–0.75 from any number of lights (docs/results.md, "Smooth dielectrics").
WEIGHTS_V5: dict[str, float] = {**WEIGHTS_V4, "glossy_coat": 5.0}

#: The material priors :func:`random_material` draws from, by version: family → weight.
#: A version, once published, never changes (its seeds must keep drawing the same materials).
PRIORS: dict[str, dict[str, float]] = {
    "v1": WEIGHTS,
    "v2": WEIGHTS_V2,
    "v3": WEIGHTS_V3,
    "v4": WEIGHTS_V4,
    "v5": WEIGHTS_V5,
}


def check_prior(prior: str) -> str:
    """``prior`` if it names a version of :data:`PRIORS`; else a MatscanError listing them."""
    if prior not in PRIORS:
        raise MatscanError(f"prior: {prior!r} is not one of {', '.join(PRIORS)}")
    return prior


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


def random_material(
    size: int = 256, seed: int = 0, mm_per_px: float | None = None, prior: str = "v1"
) -> tuple[str, MapSet]:
    """A map set of a family drawn by the weights of ``prior`` (a key of :data:`PRIORS`);
    returns (family, maps). Prior v1, the default, draws what every earlier version
    drew for the same seed."""
    weights = PRIORS[check_prior(prior)]
    names = tuple(weights)
    g = torch.Generator().manual_seed((int(seed) * 7919 + 17) % 2**63)
    family = names[int(torch.multinomial(torch.tensor([weights[f] for f in names]), 1, generator=g))]
    return family, generate(family, size, int(torch.randint(0, 2**40, (), generator=g)), mm_per_px)
