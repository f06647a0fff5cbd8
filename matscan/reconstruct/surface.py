"""Surface maps beyond the four (paper §4.5): alpha from backlight photos, height
from normals, and normals from height (its inverse, which the material generators use)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from matscan.errors import MatscanError


def alpha_from_backlight(backlight: dict[str, Tensor]) -> Tensor:
    """Alpha by triangulation matting (Smith & Blinn 1996; the paper's Eq. 12).

    With the sample over the green and the blue stage, C_k = F + (1 − α) B_k, and the
    empty stage photographed as B_k: C_g − C_b = (1 − α)(B_g − B_b), solved for
    (1 − α) in least squares over RGB. Returns (1, H, W) in [0, 1].
    """
    missing = [k for k in ("green", "blue", "green_empty", "blue_empty") if k not in backlight]
    if missing:
        raise MatscanError(f"backlight: alpha needs the {', '.join(missing)} photo(s)")
    dc = backlight["green"] - backlight["blue"]
    db = backlight["green_empty"] - backlight["blue_empty"]
    transparency = (dc * db).sum(0, keepdim=True) / (db * db).sum(0, keepdim=True).clamp_min(1e-6)
    return (1 - transparency).clamp(0, 1)


def height_from_normals(normal: Tensor, mm_per_px: tuple[float, float]) -> Tensor:
    """Height (1, H, W) in mm, zero mean, integrated from unit normals (3, H, W).

    Frankot & Chellappa 1988: the least-squares surface whose gradient best matches
    (∂h/∂x, ∂h/∂y) = (−n_x/n_z, −n_y/n_z), found in the Fourier domain (periodic
    boundary). x grows with columns, y with −rows (design.md).
    """
    nz = normal[2].clamp_min(0.05)
    p = -normal[0] / nz  # ∂h/∂x, per mm
    q = -normal[1] / nz  # ∂h/∂y
    h, w = p.shape
    dx, dy = mm_per_px
    # in pixel steps along columns (j) and rows (i): ∂h/∂j = p·dx, ∂h/∂i = −q·dy
    gj, gi = p * dx, -q * dy
    wj = 2 * math.pi * torch.fft.fftfreq(w, dtype=torch.float64)[None, :]
    wi = 2 * math.pi * torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    gj_f = torch.fft.fft2(gj.double())
    gi_f = torch.fft.fft2(gi.double())
    denom = wj**2 + wi**2
    denom[0, 0] = 1
    hf = (-1j * wj * gj_f - 1j * wi * gi_f) / denom
    hf[0, 0] = 0
    return torch.fft.ifft2(hf).real.float()[None]


def normals_from_height(height_mm: Tensor, mm_per_px: float) -> Tensor:
    """Unit normals (3, S, S) of a tileable height field (mm), by central differences.

    Tangent frame of design.md: +x right (columns), +y up (rows grow with −y).
    """
    dhdx = (torch.roll(height_mm, -1, -1) - torch.roll(height_mm, 1, -1)) / (2 * mm_per_px)
    dhdy = -(torch.roll(height_mm, -1, -2) - torch.roll(height_mm, 1, -2)) / (2 * mm_per_px)
    inv = torch.rsqrt(dhdx * dhdx + dhdy * dhdy + 1)
    return torch.stack([-dhdx * inv, -dhdy * inv, inv])
