"""Colour transfer functions.

Images and maps are linear in memory (shared/design.md, "Tensors"); files that
say ``srgb`` hold values encoded with the sRGB transfer function.
"""

from __future__ import annotations

import torch
from torch import Tensor


def srgb_to_linear(x: Tensor) -> Tensor:
    """Decode sRGB-encoded values to linear.

    Reference: IEC 61966-2-1:1999, the sRGB electro-optical transfer function.

    ========  ==========  ==========
    domain    [0, 1]      sRGB-encoded
    range     [0, 1]      linear
    ========  ==========  ==========

    Values outside [0, 1] are extended by odd symmetry.
    """
    a = x.abs()
    lin = torch.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)
    return torch.sign(x) * lin


def linear_to_srgb(x: Tensor) -> Tensor:
    """Encode linear values with the sRGB transfer function.

    Reference: IEC 61966-2-1:1999, the inverse of :func:`srgb_to_linear`.

    ========  ==========  ==========
    domain    [0, 1]      linear
    range     [0, 1]      sRGB-encoded
    ========  ==========  ==========
    """
    a = x.abs()
    enc = torch.where(a <= 0.0031308, a * 12.92, 1.055 * a.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
    return torch.sign(x) * enc
