"""Contact sheet of the artist-style evaluation map sets: docs/artist-materials.png.

One row per set (:data:`matscan.materials.artist.ARTIST_NAMES`, at 256² over the dome24
field, as ``matscan evaluate ... artist`` builds them), six tiles a row: diffuse
(sRGB-encoded, the tile labelled with the set's name), F0 (sRGB-encoded), roughness (grey, black = 0), the normal map
((n + 1)/2), and the material photographed by the virtual dome24 in 8-bit sRGB under
light 18 (ring 2, 67.5° elevation: the lacquer's highlights saturate) and under light 4
(ring 0, 22.5°: grazing, so relief casts its shading).

Deterministic: the same PNG on every run. Run: .venv/bin/python tools/artist_sheet.py [OUT]
"""

from __future__ import annotations

import sys
from pathlib import Path

from matscan.capture.virtual import CameraModel, simulate_images
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.report.sheet import contact_sheet, save_sheet, to_display
from matscan.rig import builtin_rig

SIZE = 256
LIGHTS = {"light 18": 18, "grazing 4": 4}


def main(out: Path) -> Path:
    rig = builtin_rig("dome24")
    camera = CameraModel(encoding="srgb", bits=8)
    tiles = []
    for name in ARTIST_NAMES:
        maps = artist_material(name, SIZE)
        tiles.append((name, to_display(maps.diffuse)))
        tiles.append(("F0", to_display(maps.specular)))
        tiles.append(("roughness", to_display(maps.roughness, "grey")))
        tiles.append(("normal", to_display(maps.normal, "normal")))
        photos = simulate_images(maps, rig.light_set(list(LIGHTS.values())), rig.field_mm, camera)
        tiles += [(label, to_display(photo)) for label, photo in zip(LIGHTS, photos, strict=True)]
    save_sheet(out, contact_sheet(tiles, columns=6, tile_size=128))
    return out


if __name__ == "__main__":
    path = main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/artist-materials.png"))
    print(f"wrote {path}")
