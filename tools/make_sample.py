"""Build the built-in sample map set (matscan/samples/sample/maps) and its capture.

Deterministic: the same files on every run. A procedural swatch of grained
leather with a hot-stamped gold foil ring, 256 × 256 over the dome24 field:

* leather grain: a tileable Worley (cellular) height field, cell walls raised,
  plus fine pores; normals from the height gradient at the field's mm per pixel;
* leather colour: dyed brown with low-frequency mottling, F0 0.04, roughness
  0.45–0.65 (polished cell tops smoother than the valleys);
* foil: a ring where the surface is flattened, with gold F0 (1.0, 0.78, 0.34)
  (linear), near-zero diffuse and roughness 0.22.

Run: .venv/bin/python tools/make_sample.py
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from matscan.capture.virtual import CameraModel, simulate
from matscan.mapset import MapSet, read_mapset, write_mapset
from matscan.rig import builtin_rig
from matscan.samples import sample_capture_path, sample_maps_path

SIZE = 256


def tileable_noise(rng: np.random.Generator, size: int, cutoff: float) -> np.ndarray:
    """Band-limited periodic noise (Gaussian spectrum), zero mean, unit std."""
    f = np.fft.fftfreq(size)
    r = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    spec = np.exp(-((r / cutoff) ** 2)) * (rng.normal(size=(size, size)) + 1j * rng.normal(size=(size, size)))
    n = np.fft.ifft2(spec).real
    return (n - n.mean()) / n.std()


def worley(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Tileable F2 − F1 cellular distance (small on cell walls), in pixels."""
    pts = rng.uniform(0, size, size=(cells, 2))
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    d = np.full((2, size, size), np.inf)
    for py, px in pts:
        dy = np.abs(yy - py)
        dx = np.abs(xx - px)
        dist = np.sqrt(np.minimum(dy, size - dy) ** 2 + np.minimum(dx, size - dx) ** 2)
        new1 = np.minimum(d[0], dist)
        d[1] = np.minimum(d[1], np.maximum(d[0], dist))
        d[0] = new1
    return d[1] - d[0]


def build() -> MapSet:
    rng = np.random.default_rng(20261122)
    mm_per_px = 120.0 / SIZE
    walls = worley(rng, SIZE, 90)
    grain = np.exp(-walls / 2.5)  # 1 on cell walls (creases), 0 in cell centres
    pores = np.clip(tileable_noise(rng, SIZE, 0.25), 1.5, None) - 1.5
    height = 0.12 * (1 - grain) - 0.02 * pores + 0.03 * tileable_noise(rng, SIZE, 0.02)  # mm

    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    r = np.hypot(yy - SIZE / 2 + 0.5, xx - SIZE / 2 + 0.5) * mm_per_px
    foil = np.clip((r - 24.0) / 1.0, 0, 1) * np.clip((34.0 - r) / 1.0, 0, 1)  # ring, 24–34 mm radius
    height = height * (1 - foil) + foil * (height.mean() - 0.05)

    # normals from height (central differences, wrapping): +x right, +y up (rows grow with -y)
    dhdx = (np.roll(height, -1, 1) - np.roll(height, 1, 1)) / (2 * mm_per_px)
    dhdy = -(np.roll(height, -1, 0) - np.roll(height, 1, 0)) / (2 * mm_per_px)
    normal = np.stack([-dhdx, -dhdy, np.ones_like(height)])
    normal /= np.linalg.norm(normal, axis=0, keepdims=True)

    mottle = tileable_noise(rng, SIZE, 0.01)
    brown = np.array([0.30, 0.13, 0.055])[:, None, None]
    diffuse = brown * (1 + 0.18 * mottle) * (1 - 0.35 * grain)
    gold = np.array([1.0, 0.78, 0.34])[:, None, None]
    diffuse = diffuse * (1 - foil) + 0.01 * foil
    specular = 0.04 * (1 - foil) + gold * foil
    rough = np.clip(0.5 + 0.12 * grain + 0.04 * tileable_noise(rng, SIZE, 0.05), 0.3, 0.75)
    rough = rough * (1 - foil) + 0.22 * foil

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return MapSet(
        diffuse=t(np.clip(diffuse, 0, 1)),
        specular=t(np.broadcast_to(specular, (3, SIZE, SIZE))),
        roughness=t(rough[None]),
        normal=t(normal),
        height=t(height[None]),
    )


def main() -> int:
    maps = build()
    write_mapset(sample_maps_path(), maps, overwrite=True)
    stored = read_mapset(sample_maps_path())  # simulate what the files hold, as users will
    simulate(
        stored,
        builtin_rig("dome24"),
        sample_capture_path(),
        camera=CameraModel(read_noise=0.002),
        seed=0,
        overwrite=True,
    )
    print(f"wrote {sample_maps_path()} and {sample_capture_path()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
