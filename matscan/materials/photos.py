"""Map sets built from real texture photographs that scikit-image ships (evaluation data).

scikit-image carries three 512 × 512 greyscale texture photographs in its wheel
(``skimage.data.brick``, ``grass``, ``gravel``), so no download is needed. Each
becomes a map set by rules written here, so that the study has materials whose
spatial structure comes from the real world rather than from our generators:

* diffuse: the photo's values, decoded from sRGB, scaled to albedo 0.05–0.75 and
  tinted (brick: red-brown; grass: green; gravel: warm grey);
* height: the photo blurred (σ 1.5 px) as relief, 0.4 mm from darkest to lightest,
  over a 120 mm field (dark crevices low); normals from it;
* roughness: 0.45 + 0.4 × (1 − relief), crevices rougher;
* specular: F0 0.04 (dielectric).

Needs the ``eval`` extra (scikit-image).
"""

from __future__ import annotations

from types import ModuleType

import torch
import torch.nn.functional as F

from matscan.color import srgb_to_linear
from matscan.errors import MatscanError
from matscan.mapset import MapSet
from matscan.materials.noise import blur
from matscan.reconstruct.surface import normals_from_height

TINTS = {"brick": (1.0, 0.62, 0.48), "grass": (0.55, 1.0, 0.45), "gravel": (1.0, 0.93, 0.85)}
FIELD_MM = 120.0
RELIEF_MM = 0.4


def skimage_data(what: str) -> ModuleType:
    """``skimage.data`` (the photos scikit-image ships); a MatscanError saying that ``what``
    needs it where scikit-image is missing."""
    try:
        import skimage.data
    except ImportError:
        raise MatscanError(f"{what} need scikit-image: pip install 'matscan[eval]'") from None
    return skimage.data


def photo_material(name: str, size: int = 256) -> MapSet:
    """The map set built from scikit-image's ``name`` texture (see module doc), at ``size``²."""
    if name not in TINTS:
        raise MatscanError(f"photo material: {name!r} is not one of {', '.join(TINTS)}")
    img = torch.from_numpy(getattr(skimage_data("photo materials"), name)()).float() / 255
    img = F.interpolate(img[None, None], size=(size, size), mode="area")[0, 0]
    lin = srgb_to_linear(img)
    lo, hi = float(lin.quantile(0.01)), float(lin.quantile(0.99))
    albedo = 0.05 + 0.7 * ((lin - lo) / max(hi - lo, 1e-6)).clamp(0, 1)
    tint = torch.tensor(TINTS[name]).view(3, 1, 1)
    relief = blur(img, 1.5 * size / 512)
    relief = (relief - relief.min()) / (relief.max() - relief.min()).clamp_min(1e-6)
    height = relief * RELIEF_MM
    normal = normals_from_height(height, FIELD_MM / size)
    return MapSet(
        diffuse=(albedo[None] * tint).clamp(0, 1),
        specular=torch.full((3, size, size), 0.04),
        roughness=(0.45 + 0.4 * (1 - relief))[None],
        normal=normal,
        height=(height - height.mean())[None],
    )
