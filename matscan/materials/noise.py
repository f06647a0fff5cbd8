"""Tileable noise and pattern primitives for procedural materials.

Everything here is periodic over the tile (so materials wrap without seams), works
on square tiles of any size, and draws randomness only from the given
``torch.Generator`` (same seed, same pattern). Tensors are float32 (S, S) unless
said otherwise.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _frequencies(size: int) -> tuple[Tensor, Tensor]:
    f = torch.fft.fftfreq(size)
    return f[:, None].expand(size, size), f[None, :].expand(size, size)


def spectral_noise(
    size: int,
    g: torch.Generator,
    scale: float,
    stretch: float = 1.0,
    angle: float = 0.0,
) -> Tensor:
    """Band-limited periodic noise: zero mean, unit standard deviation.

    ``scale`` is the feature size as a fraction of the tile (0.02: fine grain,
    0.3: large blotches). ``stretch`` > 1 elongates features along ``angle``
    (radians from +x), for fibres and brushing.
    """
    fy, fx = _frequencies(size)
    c, s = math.cos(angle), math.sin(angle)
    along = fx * c - fy * s
    across = fx * s + fy * c
    r2 = (along * stretch) ** 2 + across**2
    amp = torch.exp(-r2 * (scale * size * math.pi) ** 2)  # features of about scale·size pixels
    white = torch.randn(size, size, generator=g) + 1j * torch.randn(size, size, generator=g)
    n = torch.fft.ifft2(white * amp).real
    n = n - n.mean()
    return (n / n.std().clamp_min(1e-12)).float()


def fractal_noise(size: int, g: torch.Generator, scale: float, octaves: int = 4, gain: float = 0.5) -> Tensor:
    """Sum of spectral noise octaves (feature size halving, amplitude × ``gain``), unit std."""
    total = torch.zeros(size, size)
    for k in range(octaves):
        total += gain**k * spectral_noise(size, g, scale / 2**k)
    return total / total.std().clamp_min(1e-12)


def cells(size: int, g: torch.Generator, count: int) -> tuple[Tensor, Tensor, Tensor]:
    """Tileable Worley cells on a jittered grid of about ``count`` cells.

    Returns (F1, F2, cell value): distances in pixels to the nearest and second
    nearest feature point, and a random value in [0, 1) per cell (for colouring
    cells). F2 − F1 is small on cell walls.
    """
    n = max(1, round(math.sqrt(count)))
    cell = size / n
    pts = torch.rand(n, n, 2, generator=g) * cell  # offset inside each grid cell
    value = torch.rand(n, n, generator=g)
    yy = torch.arange(size, dtype=torch.float32)[:, None].expand(size, size) + 0.5
    xx = torch.arange(size, dtype=torch.float32)[None, :].expand(size, size) + 0.5
    ci = (yy / cell).floor().long().clamp(max=n - 1)
    cj = (xx / cell).floor().long().clamp(max=n - 1)
    f1 = torch.full((size, size), float("inf"))
    f2 = torch.full((size, size), float("inf"))
    v1 = torch.zeros(size, size)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            ni, nj = ci + di, cj + dj
            wi, wj = ni % n, nj % n
            py = ni.float() * cell + pts[wi, wj, 0]
            px = nj.float() * cell + pts[wi, wj, 1]
            d = torch.sqrt((yy - py) ** 2 + (xx - px) ** 2)
            closer = d < f1
            f2 = torch.where(closer, f1, torch.minimum(f2, d))
            v1 = torch.where(closer, value[wi, wj], v1)
            f1 = torch.where(closer, d, f1)
    return f1, f2, v1


def grid_coords(size: int, count_x: int, count_y: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Periodic cell coordinates for a pattern of count_x × count_y cells per tile.

    Returns (col index, row index, fraction across, fraction down), fractions in [0, 1).
    """
    u = (torch.arange(size, dtype=torch.float32) + 0.5) / size
    x = u[None, :].expand(size, size) * count_x
    y = u[:, None].expand(size, size) * count_y
    return x.floor().long(), y.floor().long(), x - x.floor(), y - y.floor()


def smoothstep(e0: float, e1: float, x: Tensor) -> Tensor:
    """Hermite step from 0 at e0 to 1 at e1."""
    t = ((x - e0) / (e1 - e0)).clamp(0, 1)
    return t * t * (3 - 2 * t)


def blur(x: Tensor, sigma_px: float) -> Tensor:
    """Periodic Gaussian blur of an (…, S, S) tensor (FFT), sigma in pixels."""
    size = x.shape[-1]
    fy, fx = _frequencies(size)
    kernel = torch.exp(-2 * (math.pi * sigma_px) ** 2 * (fx**2 + fy**2))
    return torch.fft.ifft2(torch.fft.fft2(x) * kernel).real.float()
