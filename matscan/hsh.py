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

:func:`fit_hsh` is the field's fit: one direction per photo, in the photos' display
encoding (sRGB-encoded values in [0, 1]), as RTI tools fit the stored 8-bit values;
predictions are clipped to [0, 1] (``reconstruct --validate`` scores it beside matscan's
maps). :func:`fit_hsh_field` is the same basis fitted per pixel to linear photos with each
light's own direction and falloff at that pixel divided out, so that it can relight under
near lights at other distances (``matscan evaluate --methods hsh`` on dome24).
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


def fit_hsh_field(
    images: Tensor, irradiance: Tensor, directions: Tensor, weights: Tensor | None = None, rows: int = 32
) -> Tensor:
    """Per-pixel HSH coefficients (9, C, H, W) for lights whose direction and irradiance
    change over the field (near lights): least squares of

        images[k, c, p] ≈ irradiance[k, c, p] · Σ_j coefficient[j, c, p] · b_j(directions[k, p])

    with ``images`` (K, C, H, W) linear, ``irradiance`` (K, C, H, W) what a flat white
    Lambertian surface receives from each light at each pixel (falloff, lobe, cosine and
    intensity: :func:`matscan.render.flat_irradiance`), ``directions`` (K, H, W, 3) the
    unit direction toward each light from each pixel. Dividing the lights' falloff out
    of the fit ("light falloff correction" in RTI software) lets it relight under a light
    at another distance; a flat Lambertian surface is fitted exactly by the constant term.
    ``weights`` (K, 1 or C, H, W): each sample's weight in the fit (0 leaves a saturated
    pixel out). Worked ``rows`` image rows at a time; needs at least nine photos."""
    k, c, h, w = images.shape
    if k < HSH_TERMS:
        raise MatscanError(f"HSH: a fit of {HSH_TERMS} coefficients needs at least {HSH_TERMS} photos, got {k}")
    out = torch.empty(HSH_TERMS, c, h, w)
    eye = torch.eye(HSH_TERMS, dtype=torch.float64)
    ridge = eye.clone()
    ridge[0, 0] = 0
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        b = hsh_basis(directions[:, r0:r1].reshape(-1, 3)).view(k, -1, HSH_TERMS)  # (K, P, 9)
        e = irradiance[:, :, r0:r1].double().expand(k, c, r1 - r0, w).reshape(k, c, -1)  # (K, C, P)
        y = images[:, :, r0:r1].double().reshape(k, c, -1)
        wt = 1.0 if weights is None else weights[:, :, r0:r1].double().expand(k, c, r1 - r0, w).reshape(k, c, -1)
        ata = torch.einsum("kcp,kpi,kpj->cpij", wt * e * e, b, b)
        aty = torch.einsum("kcp,kpi->cpi", wt * e * y, b)
        # where the lights leave a term undetermined (a symmetric subset, seen from a pixel
        # on the field's diagonal), a touch of ridge on every term but the constant keeps
        # the fit to the one that varies least with the light; the constant's own, far
        # smaller, keeps a pixel that no light reaches solvable (all zero)
        trace = ata.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
        ata = ata + 1e-6 * trace * ridge + (1e-12 * trace + 1e-30) * eye
        coef = torch.linalg.solve(ata, aty)  # (C, P, 9)
        out[:, :, r0:r1] = coef.permute(2, 0, 1).reshape(HSH_TERMS, c, r1 - r0, w).float()
    return out


def relight_hsh_field(coefficients: Tensor, irradiance: Tensor, directions: Tensor) -> Tensor:
    """Linear images (K, C, H, W) of per-pixel coefficients (:func:`fit_hsh_field`) under
    lights of the given irradiance (K, C, H, W) and directions (K, H, W, 3), clipped to
    [0, 1] as a photo is."""
    k, h, w = directions.shape[:3]
    b = hsh_basis(directions.reshape(-1, 3)).float().view(k, h, w, HSH_TERMS)
    shape = torch.einsum("khwj,jchw->kchw", b, coefficients)
    return (irradiance * shape).clamp(0, 1)
