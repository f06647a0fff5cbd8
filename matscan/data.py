"""Training samples: a material → augmented → rendered through the rig with a camera's flaws.

:class:`SvbrdfDataset` yields, for index i, a dict of

=========  ====================  ==============================================
inputs     (L, 3, H, W) float32  linear photos in every rig light's slot; 0 where absent
present    (L,) float32          1 for the lights photographed, 0 for absent ones
diffuse    (3, H, W)             ground-truth maps (design.md conventions)
specular   (3, H, W)
roughness  (1, H, W)
normal     (3, H, W)
offset     (2,) int64            crop position (rows, cols) in the virtual full map
full_size  (2,) int64            size of that virtual full map covering the rig field
index      () int64              the sample's index
=========  ====================  ==============================================

How a sample is made (all randomness from (seed, i), so any worker gives the
same sample for the same index):

1. a material: procedural (:mod:`matscan.materials.procedural`, from the material
   prior ``prior``: "v1", the default, draws the samples every earlier run drew;
   "v2" adds strong relief, varying specular and roughness, and dark gloss) or from
   map sets on disk; with probability ``mix_prob`` two are mixed as in Deschaintre
   et al. 2018 (maps blended, here either by one weight or by a smooth noise mask);
2. a physical scale (mm per pixel, log-uniform in ``mm_per_px``) and a place:
   the crop sits anywhere in the rig's sample field and is rendered at its true
   world position, so it sees the rig's real light and view directions there;
3. a random flip and 90° turn (normals transformed with the pixels);
4. holes (alpha) composited over the dark stage; emission added to every photo;
5. a light subset: a named subset of the rig (the paper's Table 4 for dome24)
   half the time, else a random one of 1 to L lights;
6. calibration errors: exposure (log-normal, ``exposure_jitter``), white balance
   (per channel, ``white_balance_jitter``), per-LED intensity (``led_jitter``);
7. the camera: Poisson–Gaussian noise, saturation, and either 8-bit sRGB or
   16-bit linear quantisation (:func:`matscan.capture.virtual.apply_camera`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import Dataset

from matscan.capture.virtual import CameraModel, apply_camera
from matscan.mapset import MapSet, normalize_normals
from matscan.materials.noise import smoothstep, spectral_noise
from matscan.materials.procedural import check_prior, random_material
from matscan.render import render_maps, surface_points
from matscan.rig import Rig, resolve_rig

#: The stage under the sample, seen through holes: dark, rough, flat.
STAGE = {"diffuse": 0.02, "specular": 0.02, "roughness": 0.9}


@dataclass(frozen=True)
class DataConfig:
    """How training samples are drawn (see the module doc for each step)."""

    rig: str = "dome24"
    crop: int = 128
    mm_per_px: tuple[float, float] = (0.04, 0.47)
    mix_prob: float = 0.3
    library: tuple[str, ...] = ()
    library_prob: float = 0.5
    library_metal_prob: float = 0.0
    subsets: str = "random"  # "random", or a subset name / list like "6" or "0,4,8" for every sample
    named_subset_prob: float = 0.5
    exposure_jitter: float = 0.05
    white_balance_jitter: float = 0.03
    led_jitter: float = 0.03
    read_noise: tuple[float, float] = (0.0005, 0.005)
    full_well: tuple[float, float] = (5000.0, 50000.0)
    srgb_prob: float = 0.7
    augment: bool = True
    seed: int = 0
    compile: bool = True  # render with the fused kernel (built once per worker process)
    prior: str = "v1"  # the procedural material prior's version (matscan.materials.procedural.PRIORS)

    def __post_init__(self) -> None:
        check_prior(self.prior)


def _log_uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * float(torch.rand((), generator=g)))


def _u(g: torch.Generator) -> float:
    return float(torch.rand((), generator=g))


def mix_materials(a: MapSet, b: MapSet, g: torch.Generator) -> MapSet:
    """Blend two map sets (Deschaintre et al. 2018 material mixing): one weight in
    [0.2, 0.8], or a smooth tileable noise mask, half the time each."""
    size = a.size[0]
    if _u(g) < 0.5:
        w = torch.full((1, size, size), 0.2 + 0.6 * _u(g))
    else:
        w = smoothstep(-0.1, 0.1, spectral_noise(size, g, 0.05 + 0.2 * _u(g)))[None]
    out = {}
    for name in ("diffuse", "specular", "roughness", "normal"):
        out[name] = torch.lerp(getattr(a, name), getattr(b, name), w)
    out["normal"] = normalize_normals(out["normal"])
    for name in ("alpha", "emissive"):
        ta, tb = getattr(a, name), getattr(b, name)
        if ta is not None or tb is not None:
            c = 1 if name == "alpha" else 3
            default = torch.ones(c, size, size) if name == "alpha" else torch.zeros(c, size, size)
            out[name] = torch.lerp(ta if ta is not None else default, tb if tb is not None else default, w)
    return MapSet(**out)


#: Metal colours, linear F0 at normal incidence (Hoffman, "Physics and Math of Shading",
#: SIGGRAPH 2013): gold, silver, aluminium, iron, copper, chromium, nickel, titanium.
METAL_F0 = (
    (1.000, 0.766, 0.336),
    (0.972, 0.960, 0.915),
    (0.913, 0.922, 0.924),
    (0.562, 0.565, 0.578),
    (0.955, 0.638, 0.538),
    (0.550, 0.556, 0.554),
    (0.660, 0.609, 0.526),
    (0.542, 0.497, 0.449),
)


def metallize(maps: MapSet, g: torch.Generator) -> MapSet:
    """A map set mixed, through a smooth noise mask m, with a fully metallic version of
    itself (foil, print, bare patches): there diffuse is black and F0 a tabled metal's
    colour times 0.6–1 of the map's albedo structure (glTF's metallic = 1,
    ``matscan.brdf.metallic_to_specular``), and roughness is scaled by 0.25–0.8
    (polished); each map is lerp(map, metal map, m), as :func:`mix_materials` blends.
    Normals, alpha and emission are kept. A fifth of the time the whole crop is metal;
    else the mask covers 20–80 % of it.

    Photo-built map sets (``tools/photo_library.py``) are all dielectric (F0 0.04);
    without this a network trained on them learns to predict 0.04 on metals too."""
    from matscan.brdf import metallic_to_specular

    size = maps.size[0]
    if _u(g) < 0.2:
        m = torch.ones(1, *maps.size)
    else:
        n = spectral_noise(size, g, 0.03 + 0.2 * _u(g))
        t = float(torch.quantile(n.flatten(), 0.2 + 0.6 * _u(g)))
        m = smoothstep(t - 0.1, t + 0.1, n)[None]
    metal = torch.tensor(METAL_F0[int(torch.randint(len(METAL_F0), (), generator=g))])[:, None, None]
    lum = maps.diffuse.mean(0, keepdim=True)
    structure = 0.6 + 0.4 * lum / lum.amax().clamp_min(1e-6)
    metal_diffuse, metal_specular = metallic_to_specular((metal * structure).clamp(0, 1), torch.ones_like(lum))
    roughness = (maps.roughness * (0.25 + 0.55 * _u(g))).clamp(0.05, 1)
    return MapSet(
        diffuse=torch.lerp(maps.diffuse, metal_diffuse, m),
        specular=torch.lerp(maps.specular, metal_specular, m),
        roughness=torch.lerp(maps.roughness, roughness, m),
        normal=maps.normal,
        alpha=maps.alpha,
        emissive=maps.emissive,
    )


def random_crop(maps: MapSet, g: torch.Generator, size: int) -> MapSet:
    """A ``size``² crop of ``maps`` at a place drawn from ``g`` (tiled first where the
    map set is smaller than that)."""
    h, w = maps.size
    if h < size or w < size:
        reps = (math.ceil(size / h), math.ceil(size / w))
        maps = MapSet(**{n: t.repeat(1, *reps) for n, t in maps.present().items()})
        h, w = maps.size
    top = int(torch.randint(0, h - size + 1, (), generator=g))
    left = int(torch.randint(0, w - size + 1, (), generator=g))
    return maps.crop(top, left, size, size)


def composite_over_stage(maps: MapSet) -> MapSet:
    """Maps as the camera sees them where alpha < 1: the dark stage shows through."""
    if maps.alpha is None:
        return maps
    a = maps.alpha
    flat = torch.zeros_like(maps.normal)
    flat[2] = 1
    return MapSet(
        diffuse=torch.lerp(torch.full_like(maps.diffuse, STAGE["diffuse"]), maps.diffuse, a),
        specular=torch.lerp(torch.full_like(maps.specular, STAGE["specular"]), maps.specular, a),
        roughness=torch.lerp(torch.full_like(maps.roughness, STAGE["roughness"]), maps.roughness, a),
        normal=normalize_normals(torch.lerp(flat, maps.normal, a)),
        emissive=None if maps.emissive is None else maps.emissive * a,
    )


@dataclass
class SvbrdfDataset(Dataset):
    """Procedural (and optionally on-disk) materials rendered through a rig, on the fly.

    ``length`` is nominal: any index gives a sample, deterministic per (seed, index).
    """

    config: DataConfig = field(default_factory=DataConfig)
    length: int = 100_000

    def __post_init__(self) -> None:
        self.rig: Rig = resolve_rig(self.config.rig)
        self.subset_names = sorted(self.rig.subsets, key=lambda k: len(self.rig.subsets[k]))
        self.library = [Path(p) for p in self.config.library]
        self._library_cache: dict[int, MapSet] = {}

    def __len__(self) -> int:
        return self.length

    # --- pieces, each a function of the sample's generator ---

    def _material(self, g: torch.Generator, size: int, mm_per_px: float) -> MapSet:
        if self.library and _u(g) < self.config.library_prob:
            k = int(torch.randint(len(self.library), (), generator=g))
            maps = self._library_crop(k, g, size)
            if self.config.library_metal_prob > 0 and _u(g) < self.config.library_metal_prob:
                maps = metallize(maps, g)
            return maps
        seed = int(torch.randint(0, 2**40, (), generator=g))
        return random_material(size, seed, mm_per_px, self.config.prior)[1]

    def _library_crop(self, k: int, g: torch.Generator, size: int) -> MapSet:
        from matscan.materials.library import read_any

        if k not in self._library_cache:
            self._library_cache[k] = read_any(self.library[k])
        return random_crop(self._library_cache[k], g, size)

    def light_subset(self, g: torch.Generator) -> list[int]:
        """The lights photographed for one sample (see module doc, step 5)."""
        n = len(self.rig.lights)
        if self.config.subsets != "random":
            return list(self.rig.subset(self.config.subsets))
        if self.subset_names and _u(g) < self.config.named_subset_prob:
            name = self.subset_names[int(torch.randint(len(self.subset_names), (), generator=g))]
            return list(self.rig.subsets[name])
        count = int(torch.randint(1, n + 1, (), generator=g))
        return sorted(torch.randperm(n, generator=g)[:count].tolist())

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        cfg = self.config
        g = torch.Generator().manual_seed((cfg.seed * 1_000_003 + int(index)) % (2**63))
        size = cfg.crop
        mm_per_px = _log_uniform(g, *cfg.mm_per_px)
        maps = self._material(g, size, mm_per_px)
        if _u(g) < cfg.mix_prob:
            maps = mix_materials(maps, self._material(g, size, mm_per_px), g)
        if cfg.augment:
            maps = maps.transformed(int(torch.randint(4, (), generator=g)), _u(g) < 0.5)
        maps = composite_over_stage(maps)

        field_w, field_h = self.rig.field_mm
        full = (max(size, round(field_h / mm_per_px)), max(size, round(field_w / mm_per_px)))
        offset = (
            int(torch.randint(0, full[0] - size + 1, (), generator=g)),
            int(torch.randint(0, full[1] - size + 1, (), generator=g)),
        )
        points = surface_points(self.rig.field_mm, (size, size), offset, full)

        subset = self.light_subset(g)
        n = len(self.rig.lights)
        # every light is rendered, so the fused kernel sees one shape whatever the subset
        lights = self.rig.light_set()
        gains = 1 + cfg.led_jitter * torch.randn(n, 1, generator=g)
        wb = 1 + cfg.white_balance_jitter * torch.randn(1, 3, generator=g)
        exposure = math.exp(cfg.exposure_jitter * float(torch.randn((), generator=g)))
        lights = lights.with_intensity(lights.intensity * gains * wb * exposure)
        with torch.no_grad():  # maps are already composited over the stage: no alpha left
            photos = render_maps(maps, lights, self.rig.field_mm, compile=cfg.compile, points=points, emission=exposure)
        srgb = _u(g) < cfg.srgb_prob
        camera = CameraModel(
            read_noise=cfg.read_noise[0] + (cfg.read_noise[1] - cfg.read_noise[0]) * _u(g),
            full_well=_log_uniform(g, *cfg.full_well),
            encoding="srgb" if srgb else "linear",
            bits=8 if srgb else 16,
        )
        inputs = apply_camera(photos, camera, g, compile=cfg.compile)

        present = torch.zeros(n)
        present[subset] = 1
        inputs[present == 0] = 0
        return {
            "inputs": inputs,
            "present": present,
            "diffuse": maps.diffuse,
            "specular": maps.specular,
            "roughness": maps.roughness,
            "normal": maps.normal,
            "offset": torch.tensor(offset),
            "index": torch.tensor(int(index)),
            "full_size": torch.tensor(full),
        }


def fixed_validation_set(
    count: int,
    crop: int = 128,
    rig: str = "dome24",
    seed: int = 1_000_000,
    subsets: str = "random",
    prior: str = "v1",
) -> list[dict[str, Tensor]]:
    """A fixed procedural set never drawn in training.

    Sample i of config seed s is drawn from generator seed s·1,000,003 + i; this set
    uses s = 1,000,000, i.e. seeds from 1.000003e12 up, which training with seed 0
    (or any small seed) never reaches. ``prior`` "v1" (the default) is the set every
    published validation number was measured on.
    """
    ds = SvbrdfDataset(DataConfig(rig=rig, crop=crop, seed=seed, subsets=subsets, compile=False, prior=prior))
    return [ds[i] for i in range(count)]


def synthesize(
    out: str | Path,
    count: int,
    size: int = 256,
    seed: int = 0,
    family: str | None = None,
    rig: str = "dome24",
    lights: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
    overwrite_any: bool = False,
) -> Path:
    """Write ``count`` procedural map sets with their simulated captures (``matscan synth``).

    Layout: ``out/NNN_family/maps`` (a map set folder), ``out/NNN_family/capture``
    (a capture folder through ``rig``, 8-bit sRGB with mild noise), and
    ``out/contact_sheet.png`` showing each material under one light and its normals.
    """
    from tqdm import tqdm

    from matscan.capture.virtual import simulate
    from matscan.errors import MatscanError
    from matscan.mapset import write_mapset
    from matscan.materials.procedural import generate
    from matscan.outputs import claim_output
    from matscan.report.sheet import contact_sheet, save_sheet, to_display

    if count < 1:
        raise MatscanError(f"count: must be at least 1, got {count}")
    the_rig = resolve_rig(rig)
    indices = the_rig.subset(lights)
    show = indices[min(len(indices) - 1, len(indices) * 3 // 4)]
    tiles = []
    inputs = [Path(rig)] if str(rig).endswith(".json") else []  # a rig file is an input, never overwritten
    with (
        claim_output(out, "synth", inputs, overwrite=overwrite, overwrite_any=overwrite_any) as claim,
        claim.folder() as tmp,
    ):
        for i in tqdm(range(count), desc="synth", unit="material", disable=not progress):
            if family is None:
                fam, maps = random_material(size, seed * 100_003 + i)
            else:
                fam, maps = family, generate(family, size, seed * 100_003 + i)
            folder = tmp / f"{i:03d}_{fam}"
            write_mapset(folder / "maps", maps)
            simulate(maps, the_rig, folder / "capture", lights=indices, camera=CameraModel(read_noise=0.002), seed=i)
            photo = render_maps(maps, the_rig.light_set([show]), the_rig.field_mm)[0]
            tiles.append((f"{i:03d} {fam}", to_display(photo)))
            tiles.append(("normal", to_display(maps.normal, "normal")))
        save_sheet(tmp / "contact_sheet.png", contact_sheet(tiles, columns=8, tile_size=128))
    return Path(out)
