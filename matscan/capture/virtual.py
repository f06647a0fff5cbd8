"""The virtual rig: photographs of a map set, rendered through a rig and a camera model.

What a real camera adds to the rendered radiance (in this order):

1. exposure: radiance × ``exposure`` (1.0 keeps the design's scale, where a white
   Lambertian sample lit head-on at distance R images to 1.0);
2. Poisson–Gaussian noise (heteroscedastic Gaussian form): photon shot noise with
   ``full_well`` electrons at full scale, plus Gaussian read noise of standard deviation ``read_noise`` (a
   fraction of full scale); both off when ``read_noise`` is 0;
3. saturation: values clip to [0, 1] (not for 32-bit float files);
4. quantisation: 8 or 16 bits after the ``encoding``'s transfer function.

With ``read_noise=0``, ``encoding="linear"`` and ``bits=32`` the stored images
are the image formation model exactly.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from matscan.capture.folder import ENCODINGS, write_capture
from matscan.color import linear_to_srgb, srgb_to_linear
from matscan.errors import MatscanError
from matscan.mapset import MapSet, normalize_normals
from matscan.render import render_maps
from matscan.rig import Light, LightSet, Rig

#: Backlight colours (linear RGB radiance) of the stage, and the dim room light on
#: the sample's front while only the backlight is on.
BACKLIGHT = {"green": (0.04, 0.75, 0.10), "blue": (0.04, 0.12, 0.80)}
ROOM_LIGHT = 0.03


@dataclass(frozen=True)
class CameraModel:
    """How the virtual camera turns radiance into stored code values (see module doc)."""

    exposure: float = 1.0
    read_noise: float = 0.0
    full_well: float = 20000.0
    encoding: str = "srgb"
    bits: int = 8

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise MatscanError(f"encoding: {self.encoding!r} is not one of {', '.join(ENCODINGS)}")
        if self.bits not in (8, 16, 32):
            raise MatscanError(f"bits: {self.bits} is not one of 8, 16, 32")
        if self.bits == 32 and self.encoding != "linear":
            raise MatscanError("bits: 32-bit float files are linear; use encoding linear")
        if not self.exposure > 0:
            raise MatscanError(f"exposure: must be positive, got {self.exposure}")
        if self.read_noise < 0:
            raise MatscanError(f"noise: must not be negative, got {self.read_noise}")
        if not self.full_well > 0:
            raise MatscanError(f"full_well: must be positive, got {self.full_well}")


def apply_camera(
    radiance: Tensor, camera: CameraModel, generator: torch.Generator | None = None, compile: bool = False
) -> Tensor:
    """Expose, add noise, saturate and quantise; return the stored values, decoded to linear.

    ``radiance`` is linear, any shape. Noise is the Poisson–Gaussian model in its
    heteroscedastic Gaussian form (Foi et al. 2008, "Practical Poissonian-Gaussian
    noise modeling and fitting for single-image raw-data"): variance
    x / full_well + read_noise², accurate for the photon counts of a camera
    (thousands of electrons at full scale). The result is what reading the written
    file back gives (quantised in the encoding's domain), so in-memory training
    data and files on disk agree: sRGB codes are round(srgb(x) · (2^bits − 1)),
    computed in float32, so a value within float32 rounding of a code boundary can
    land one code off (a few in a million at 8 bits, about 0.3% at 16), far below
    the noise. ``compile`` fuses the arithmetic into one kernel (for training data).
    """
    noisy = camera.read_noise > 0
    z = torch.randn(radiance.shape, generator=generator, dtype=radiance.dtype) if noisy else radiance
    # numbers as tensors, so the compiled kernel is not specialised to each value
    # (the top code too: some torch versions cannot trace 1 << bits once bits is symbolic)
    top = float((1 << camera.bits) - 1) if camera.bits != 32 else 1.0
    scalars = torch.tensor([camera.exposure, camera.read_noise, camera.full_well, top], dtype=radiance.dtype)
    srgb = camera.encoding == "srgb" and camera.bits != 32
    levels = _srgb_levels(camera.bits, radiance.dtype) if srgb else scalars
    args = (radiance, z, scalars, levels, noisy, camera.bits, srgb)
    if compile:
        if not _SENSOR:
            _SENSOR.append(torch.compile(_sensor))
        return _SENSOR[0](*args)
    return _sensor(*args)


_SENSOR: list = []


@functools.cache
def _srgb_levels(bits: int, dtype: torch.dtype) -> Tensor:
    """The linear value of every sRGB code of a bit depth."""
    top = (1 << bits) - 1
    return srgb_to_linear(torch.arange(top + 1, dtype=torch.float64) / top).to(dtype)


def _sensor(radiance: Tensor, z: Tensor, scalars: Tensor, levels: Tensor, noisy: bool, bits: int, srgb: bool) -> Tensor:
    exposure, read_noise, full_well, top = scalars[0], scalars[1], scalars[2], scalars[3]
    x = radiance * exposure
    if noisy:
        x = x + torch.sqrt(x.clamp_min(0) / full_well + read_noise**2) * z
    if bits == 32:
        return x
    x = x.clamp(0, 1)
    if srgb:
        return levels[torch.round(linear_to_srgb(x.float()) * top).long()]
    return torch.round(x * top) / top


def default_flash_geometry(height_mm: float = 273.0, spread_mm: float = 30.0) -> list[tuple[tuple, tuple]]:
    """Nine phone positions (3 × 3 grid, flash beside lens) for simulating ``flash`` captures."""
    poses = []
    for dy in (spread_mm, 0.0, -spread_mm):
        for dx in (-spread_mm, 0.0, spread_mm):
            pos = (dx, dy, height_mm)
            poses.append((pos, pos))
    return poses


def resize_maps(maps: MapSet, size: int) -> MapSet:
    """Resample every map to size × size (area-weighted; normals renormalised)."""
    out = {}
    for name, t in maps.present().items():
        r = F.interpolate(t[None], size=(size, size), mode="bilinear", antialias=True, align_corners=False)[0]
        out[name] = normalize_normals(r) if name == "normal" else r
    return MapSet(**out)


def simulate_images(
    maps: MapSet,
    lights: LightSet,
    field_mm: Sequence[float],
    camera: CameraModel,
    seed: int = 0,
    progress: bool = False,
) -> Tensor:
    """Photographs (N, 3, H, W) of ``maps`` under each light, as the camera stores them.

    Holes (alpha < 1) show a black stage; the emissive map adds to every photo.
    """
    gen = torch.Generator().manual_seed(seed)
    images = []
    for k in tqdm(range(len(lights)), desc="render", unit="light", disable=not progress, leave=False):
        rad = render_maps(maps, lights.select([k]), field_mm)[0]
        images.append(apply_camera(rad, camera, gen))
    return torch.stack(images)


def simulate_backlight(maps: MapSet, camera: CameraModel, seed: int = 0) -> dict[str, Tensor]:
    """Backlight photos: the sample over a green, then a blue stage, and both stages empty.

    The composite is C = F + (1 − α)·B (the matting equation, Smith & Blinn
    1996), with F = α·ρ·room light: a dim front view of the sample.
    """
    gen = torch.Generator().manual_seed(seed + 7919)
    alpha = maps.alpha if maps.alpha is not None else torch.ones(1, *maps.size)
    front = alpha * maps.diffuse * ROOM_LIGHT
    out = {}
    for key, rgb in BACKLIGHT.items():
        stage = torch.tensor(rgb).view(3, 1, 1).expand(3, *maps.size)
        out[key] = apply_camera(front + (1 - alpha) * stage, camera, gen)
        out[f"{key}_empty"] = apply_camera(stage.clone(), camera, gen)
    return out


def simulate(
    maps: MapSet,
    rig: Rig,
    out: str | Path,
    lights: Sequence[int] | None = None,
    camera: CameraModel = CameraModel(),
    seed: int = 0,
    size: int | None = None,
    geometry: Sequence[tuple[Sequence[float], Sequence[float]]] | None = None,
    overwrite: bool = False,
    progress: bool = False,
    inputs: Sequence[str | Path] = (),
    overwrite_any: bool = False,
) -> Path:
    """Render a capture folder of ``maps`` through ``rig`` (``matscan simulate``).

    ``lights`` picks rig lights (all by default). A rig with per-image geometry
    takes ``geometry`` (light, camera positions per photo; a 3 × 3 grid of phone
    positions by default). Backlight photos are added when the rig has a
    backlight and the maps have alpha. ``out`` is checked and locked before the
    rendering (:func:`matscan.outputs.claim_output`; never one of ``inputs``).
    """
    from matscan.outputs import claim_output

    if lights is not None and not rig.per_image_geometry:
        rig.subset(lights)  # the lights checked before the output is claimed
    with claim_output(out, "simulate", inputs, overwrite=overwrite, overwrite_any=overwrite_any):
        return _simulate(maps, rig, out, lights, camera, seed, size, geometry, overwrite, progress)


def _simulate(
    maps: MapSet,
    rig: Rig,
    out: str | Path,
    lights: Sequence[int] | None,
    camera: CameraModel,
    seed: int,
    size: int | None,
    geometry: Sequence[tuple[Sequence[float], Sequence[float]]] | None,
    overwrite: bool,
    progress: bool,
) -> Path:
    maps.check()
    if size is not None:
        if size < 8:
            raise MatscanError(f"size: {size} is too small (at least 8 pixels)")
        maps = resize_maps(maps, size)
    if rig.per_image_geometry:
        geometry = list(geometry) if geometry is not None else default_flash_geometry()
        template = rig.lights[0]
        light_set = LightSet.from_lights(
            [Light(tuple(g[0]), template.intensity, template.exponent, template.aim_mm) for g in geometry],
            [tuple(g[1]) for g in geometry],
            rig.reference_distance_mm,
        )
        indices = None
    else:
        indices = list(rig.subset(lights))
        light_set = rig.light_set(indices)
    images = simulate_images(maps, light_set, rig.field_mm, camera, seed, progress)
    backlight = simulate_backlight(maps, camera, seed) if rig.backlight and maps.alpha is not None else None
    record = {
        "simulation": {
            "exposure": camera.exposure,
            "read_noise": camera.read_noise,
            "full_well": camera.full_well,
            "bits": camera.bits,
            "seed": seed,
        }
    }
    return write_capture(
        out,
        images,
        rig,
        light_indices=indices,
        geometry=geometry,
        encoding=camera.encoding,
        bits=camera.bits,
        backlight=backlight,
        field_mm=rig.field_mm if rig.per_image_geometry else None,
        extra=record,
        overwrite=overwrite,
    )
