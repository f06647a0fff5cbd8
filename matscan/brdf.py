"""The reflectance model and map conventions.

The model is the paper's Eq. 1 (Cook–Torrance with GGX, uncorrelated Smith and
Schlick), exactly as shared/design.md writes it, with h = normalize(l + v):

    f_r = ρ/π + D·G·F / (4 (n·l)(n·v))
    D   = α² / (π ((n·h)²(α² − 1) + 1)²)                     GGX, α = max(r², 1e-3)
    G   = G1(n·l) G1(n·v),  G1(c) = 2c / (c + sqrt(α² + (1 − α²) c²))
    F   = F0 + (1 − F0)(1 − v·h)^5

Each term is its own function of cosines, so the renderer and the tests use the
same code. Every function is differentiable and works in float32 and float64.

Map conventions (design.md, "Maps"): diffuse ρ and specular F0 are linear RGB in
[0, 1]; roughness r is perceptual (α = r², glossiness g = 1 − r); normals are
unit vectors in the tangent frame (+x right, +y up, +z out of the surface).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: Lower bound on GGX α (design.md): keeps D finite for a perfect mirror.
ALPHA_MIN = 1e-3
#: glTF's F0 for dielectrics (glTF 2.0 specification, Appendix B).
DIELECTRIC_F0 = 0.04


def ggx_alpha(roughness: Tensor) -> Tensor:
    """GGX α from perceptual roughness: α = max(r², 1e-3)."""
    return (roughness * roughness).clamp_min(ALPHA_MIN)


def ggx_distribution(n_dot_h: Tensor, alpha: Tensor) -> Tensor:
    """GGX normal distribution D (Walter et al. 2007, Eq. 33; design.md Eq. 1).

    Normalised so that ∫ D(h) (n·h) dω_h = 1 over the hemisphere.
    """
    a2 = alpha * alpha
    denom = n_dot_h * n_dot_h * (a2 - 1) + 1
    return a2 / (math.pi * denom * denom)


def smith_g1(cos: Tensor, alpha: Tensor) -> Tensor:
    """Smith masking G1 for GGX (Walter et al. 2007, Eq. 34, in the form of design.md).

    G1(c) = 2c / (c + sqrt(α² + (1 − α²) c²)), for c = n·l or n·v in [0, 1].
    """
    a2 = alpha * alpha
    return 2 * cos / (cos + torch.sqrt(a2 + (1 - a2) * cos * cos))


def smith_g(n_dot_l: Tensor, n_dot_v: Tensor, alpha: Tensor) -> Tensor:
    """Uncorrelated Smith shadowing-masking G = G1(n·l) G1(n·v)."""
    return smith_g1(n_dot_l, alpha) * smith_g1(n_dot_v, alpha)


def fresnel_schlick(f0: Tensor, v_dot_h: Tensor) -> Tensor:
    """Schlick's Fresnel approximation F = F0 + (1 − F0)(1 − v·h)^5 (Schlick 1994)."""
    return f0 + (1 - f0) * (1 - v_dot_h).clamp_min(0) ** 5


def lambert(diffuse: Tensor) -> Tensor:
    """The diffuse lobe ρ/π."""
    return diffuse / math.pi


def _dot(a: Tensor, b: Tensor, dim: int) -> Tensor:
    return (a * b).sum(dim=dim, keepdim=True)


def cook_torrance(
    normal: Tensor,
    light: Tensor,
    view: Tensor,
    diffuse: Tensor,
    specular: Tensor,
    roughness: Tensor,
    dim: int = -3,
) -> Tensor:
    """Evaluate f_r (design.md Eq. 1) for unit directions.

    Args:
        normal, light, view: unit vectors, size 3 along ``dim``, in one frame.
            ``light`` and ``view`` point away from the surface.
        diffuse, specular: ρ and F0, size 3 (RGB) along ``dim``; linear, [0, 1].
        roughness: r, size 1 along ``dim``; [0, 1].
        dim: the vector/channel dimension (default: the C of (…, C, H, W)).

    Returns:
        f_r, RGB along ``dim``, in 1/sr. Where n·l ≤ 0 or n·v ≤ 0 the specular
        term is 0 (the lobe is below the surface); the diffuse term is returned
        as is, since the caller multiplies by max(n·l, 0).
    """
    half = light + view
    half = half / half.norm(dim=dim, keepdim=True).clamp_min(1e-12)
    n_l = _dot(normal, light, dim)
    n_v = _dot(normal, view, dim)
    n_h = _dot(normal, half, dim).clamp_min(0)
    v_h = _dot(view, half, dim).clamp(0, 1)
    alpha = ggx_alpha(roughness)
    lit = (n_l > 0) & (n_v > 0)
    n_l_c = n_l.clamp_min(1e-7)
    n_v_c = n_v.clamp_min(1e-7)
    spec = (
        ggx_distribution(n_h, alpha)
        * smith_g(n_l_c, n_v_c, alpha)
        * fresnel_schlick(specular, v_h)
        / (4 * n_l_c * n_v_c)
    )
    return lambert(diffuse) + torch.where(lit, spec, torch.zeros_like(spec))


# --- conversions between map conventions ---------------------------------------


def roughness_to_glossiness(roughness: Tensor) -> Tensor:
    """Glossiness g = 1 − r (the paper's G_g predicts g)."""
    return 1 - roughness


def glossiness_to_roughness(glossiness: Tensor) -> Tensor:
    """Roughness r = 1 − g."""
    return 1 - glossiness


def metallic_to_specular(basecolor: Tensor, metallic: Tensor) -> tuple[Tensor, Tensor]:
    """glTF metal/rough maps → (diffuse ρ, specular F0).

    glTF 2.0 specification, Appendix B (BRDF implementation):
    c_diff = lerp(baseColor, black, metallic), F0 = lerp(0.04, baseColor, metallic).

    ========  ===============================  ==========
    domain    basecolor (…, 3, H, W) linear    [0, 1]
              metallic  (…, 1, H, W)           [0, 1]
    range     diffuse, specular (…, 3, H, W)   [0, 1] linear
    ========  ===============================  ==========
    """
    diffuse = basecolor * (1 - metallic)
    specular = DIELECTRIC_F0 * (1 - metallic) + basecolor * metallic
    return diffuse, specular


def specular_to_metallic(diffuse: Tensor, specular: Tensor, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """(diffuse ρ, specular F0) → glTF (basecolor, metallic), inverse of :func:`metallic_to_specular`.

    With u = 1 − metallic, mean diffuse d and mean specular s, the forward model
    gives s·u = 0.04·u² + d·(1 − u); metallic is the root of this quadratic in
    [0, 1], and 0 where s ≤ 0.04 (a dielectric). Basecolor blends the two
    per-channel inversions, ρ/u and (F0 − 0.04·u)/m, weighted by m² (as the
    Khronos specular-glossiness converter does), so it is exact for grey maps and
    for pure dielectrics and metals. Specular colours that no metal/rough
    material can produce (F0 < 0.04 with colour, say) are approximated.

    ========  ===============================  ==========
    domain    diffuse, specular (…, 3, H, W)   [0, 1] linear
    range     basecolor (…, 3, H, W)           [0, 1] linear
              metallic (…, 1, H, W)            [0, 1]
    ========  ===============================  ==========
    """
    d = diffuse.mean(dim=-3, keepdim=True)
    s = specular.mean(dim=-3, keepdim=True)
    a = DIELECTRIC_F0
    b = s + d
    disc = (b * b - 4 * a * d).clamp_min(0)
    u = ((b - torch.sqrt(disc)) / (2 * a)).clamp(0, 1)
    metallic = torch.where(s > a, 1 - u, torch.zeros_like(u))
    u = 1 - metallic
    from_diffuse = diffuse / u.clamp_min(eps)
    from_specular = (specular - a * u) / metallic.clamp_min(eps)
    w = metallic * metallic
    basecolor = (from_diffuse * (1 - w) + from_specular * w).clamp(0, 1)
    return basecolor, metallic
