"""Map sets built from photographs of real surfaces: scikit-image's (evaluation data
only) and any colour photo (:func:`maps_from_photo`; tools/photo_library.py builds
training map sets with it from licensed photos).

scikit-image carries three 512 × 512 greyscale texture photographs in its wheel
(``skimage.data.brick``, ``grass``, ``gravel``), so no download is needed. Each
becomes a map set by rules written here, so that the study has materials whose
spatial structure comes from the real world rather than from our generators:

* diffuse: the photo's luminance, decoded from sRGB, scaled to albedo 0.05–0.75, times
  the photo's own colour (a colour photo) or a tint (scikit-image's greyscale ones:
  brick red-brown, grass green, gravel warm grey);
* height: the photo blurred (σ 1.5 px) as relief, 0.4 mm from darkest to lightest,
  over a 120 mm field (dark crevices low); normals from it;
* roughness: 0.45 + 0.4 × (1 − relief), crevices rougher;
* specular: F0 0.04 (dielectric).

scikit-image's sets need the ``eval`` extra.
"""

from __future__ import annotations

from types import ModuleType

import torch
import torch.nn.functional as F
from torch import Tensor

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
    return maps_from_photo(img.expand(3, -1, -1), TINTS[name])


def maps_from_photo(photo: Tensor, tint: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> MapSet:
    """A map set from a photograph of a surface (3, H, W), sRGB-encoded in [0, 1], by the
    rules of the module doc: the diffuse keeps the photo's colour (times ``tint``), its
    luminance stretched to albedo 0.05–0.75 between the 1st and 99th percentiles; the
    luminance blurred is the relief. Square or not, the map set covers ``FIELD_MM`` across
    its width."""
    if photo.ndim != 3 or photo.shape[0] != 3:
        raise MatscanError(f"maps_from_photo: expected a (3, H, W) photo, got {tuple(photo.shape)}")
    h, w = photo.shape[-2:]
    img = (0.2126 * photo[0] + 0.7152 * photo[1] + 0.0722 * photo[2]).clamp(0, 1)  # sRGB-encoded luminance
    lin = srgb_to_linear(img)
    lo, hi = float(lin.quantile(0.01)), float(lin.quantile(0.99))
    albedo = 0.05 + 0.7 * ((lin - lo) / max(hi - lo, 1e-6)).clamp(0, 1)
    colour = srgb_to_linear(photo.clamp(0, 1))
    chroma = colour / lin.clamp_min(1e-4)[None]  # the photo's colour at unit luminance
    if bool((photo == photo[:1]).all()):
        chroma = torch.ones_like(colour)  # a grey photo: exactly the tint
    tint_t = torch.tensor(tint, dtype=photo.dtype).view(3, 1, 1)
    relief = blur(img, 1.5 * w / 512)
    relief = (relief - relief.min()) / (relief.max() - relief.min()).clamp_min(1e-6)
    height = relief * RELIEF_MM
    normal = normals_from_height(height, FIELD_MM / w)
    return MapSet(
        diffuse=(albedo[None] * chroma * tint_t).clamp(0, 1),
        specular=torch.full((3, h, w), 0.04),
        roughness=(0.45 + 0.4 * (1 - relief))[None],
        normal=normal,
        height=(height - height.mean())[None],
    )
