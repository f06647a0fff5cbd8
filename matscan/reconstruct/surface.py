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

    The least-squares surface whose differences between neighbouring pixels best match
    the slopes (∂h/∂x, ∂h/∂y) = (−n_x/n_z, −n_y/n_z) averaged over each pair, with the
    field's edges free (:func:`integrate_differences`): a tilted plane comes back a plane
    (the periodic Frankot & Chellappa integral used before dropped the mean slope, so a
    sample tilted by atan 0.1 came back flat). x grows with columns, y with −rows
    (design.md).
    """
    nz = normal[2].clamp_min(0.05)
    sx, sy = normal[0] / nz, normal[1] / nz  # float32: half the memory at 3072² (1e-5 mm of 10 mm)
    dx, dy = mm_per_px
    along_x = -(sx[:, 1:] + sx[:, :-1]) / 2 * dx  # h[i, j + 1] − h[i, j], mm
    along_rows = (sy[1:] + sy[:-1]) / 2 * dy  # h[i + 1, j] − h[i, j] (rows run down, y up)
    return integrate_differences(along_x, along_rows)[None]


def integrate_differences(along_x: Tensor, along_rows: Tensor) -> Tensor:
    """The field (H, W), zero mean, whose differences between neighbouring pixels best fit
    ``along_x`` (H, W − 1: h[i, j + 1] − h[i, j]) and ``along_rows`` (H − 1, W: h[i + 1, j] −
    h[i, j]) in least squares: the normal equations are the grid's Laplacian with the
    edges free (Neumann), solved exactly in the cosine basis, here by the real Fourier
    transform of the right-hand side mirrored at the field's edges, in the differences'
    dtype."""
    rows, cols = along_x.shape[0], along_rows.shape[1]
    dtype = along_x.dtype
    rhs = torch.zeros(rows, cols, dtype=dtype)  # the differences' transpose applied
    rhs[:, 1:] += along_x
    rhs[:, :-1] -= along_x
    rhs[1:] += along_rows
    rhs[:-1] -= along_rows
    mirrored = torch.cat([rhs, rhs.flip(0)], 0)
    mirrored = torch.cat([mirrored, mirrored.flip(1)], 1)
    del rhs
    wi = 2 - 2 * torch.cos(math.pi * torch.arange(2 * rows, dtype=torch.float64) / rows)
    wj = 2 - 2 * torch.cos(math.pi * torch.arange(cols + 1, dtype=torch.float64) / cols)
    eigen = (wi[:, None] + wj[None, :]).to(dtype)
    eigen[0, 0] = 1.0
    spectrum = torch.fft.rfft2(mirrored)
    del mirrored
    spectrum /= eigen
    spectrum[0, 0] = 0.0
    field = torch.fft.irfft2(spectrum, s=(2 * rows, 2 * cols))[:rows, :cols]
    return field - field.mean()


def normals_from_height(height_mm: Tensor, mm_per_px: float) -> Tensor:
    """Unit normals (3, S, S) of a tileable height field (mm), by central differences.

    Tangent frame of design.md: +x right (columns), +y up (rows grow with −y).
    """
    dhdx = (torch.roll(height_mm, -1, -1) - torch.roll(height_mm, 1, -1)) / (2 * mm_per_px)
    dhdy = -(torch.roll(height_mm, -1, -2) - torch.roll(height_mm, 1, -2)) / (2 * mm_per_px)
    inv = torch.rsqrt(dhdx * dhdx + dhdy * dhdy + 1)
    return torch.stack([-dhdx * inv, -dhdy * inv, inv])
