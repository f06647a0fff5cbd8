"""Hemispherical harmonics (HSH) relighting: the RTI field's per-pixel curve fit, as a baseline.

RTI software (RTIBuilder, relight) fits every pixel and channel with a function of the
light direction and relights by evaluating it at a new direction. HSH of order 2 (nine
coefficients) is the field's usual choice (Gautron et al., "A novel hemispherical basis
for accurate and efficient rendering", EGSR 2004). The HSH are the real spherical
harmonics of the hemisphere stretched over the sphere: with l = (lx, ly, lz), cos θ = lz
becomes cos θ' = 2 lz − 1, so in terms of

    z' = 2 lz − 1,  s' = sin θ' = 2 √(lz − lz²),  x' = s' cos φ,  y' = s' sin φ

the nine functions span the polynomials {1, x', y', z', x'y', y'z', 3z'² − 1, x'z',
x'² − y'²} of the remapped direction. A least-squares fit depends only on the span, so
the normalisation constants of the published basis are left out.

The fit is in the photos' display encoding (sRGB-encoded values in [0, 1]), as RTI tools
fit the stored 8-bit values; predictions are clipped to [0, 1].
"""

from __future__ import annotations

import torch
from torch import Tensor

from matscan.errors import MatscanError

#: Coefficients per pixel and channel.
HSH_TERMS = 9


def hsh_basis(directions: Tensor) -> Tensor:
    """The nine order-2 HSH of unit light directions (K, 3) with lz > 0: (K, 9)."""
    d = torch.as_tensor(directions, dtype=torch.float64)
    lz = d[:, 2].clamp(0, 1)
    phi = torch.atan2(d[:, 1], d[:, 0])
    z = 2 * lz - 1
    s = 2 * (lz - lz * lz).clamp_min(0).sqrt()
    x, y = s * torch.cos(phi), s * torch.sin(phi)
    return torch.stack([torch.ones_like(z), x, y, z, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y], dim=1)


def fit_hsh(images: Tensor, directions: Tensor) -> Tensor:
    """Least-squares HSH coefficients (9, C, H, W) of images (K, C, H, W) under lights
    from ``directions`` (K, 3). Needs at least nine photos with distinct directions."""
    k = images.shape[0]
    if k < HSH_TERMS:
        raise MatscanError(f"HSH: a fit of {HSH_TERMS} coefficients needs at least {HSH_TERMS} photos, got {k}")
    basis = hsh_basis(directions)
    pinv = torch.linalg.pinv(basis)  # (9, K)
    flat = images.reshape(k, -1).double()
    return (pinv @ flat).float().reshape(HSH_TERMS, *images.shape[1:])


def relight_hsh(coefficients: Tensor, directions: Tensor) -> Tensor:
    """Images (K, C, H, W) of fitted coefficients (9, C, H, W) under ``directions``
    (K, 3), clipped to [0, 1]."""
    basis = hsh_basis(directions).float()
    flat = coefficients.reshape(HSH_TERMS, -1)
    return (basis @ flat).reshape(len(basis), *coefficients.shape[1:]).clamp(0, 1)
