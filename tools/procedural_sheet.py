"""Contact sheet of the families prior v2 adds: docs/procedural-materials-v2.png.

One row per family (``NEW_FAMILIES``), three materials a row (seeds 0, 1, 2 at 256²
over the dome24 field, as ``matscan synth`` draws them), five tiles a material: the
material under dome24 light 18 (ring 2, 67.5° elevation, the light ``synth``'s sheet
shows), under light 4 (ring 0, 22.5°: grazing, so relief casts its shading), the
normal map ((n + 1)/2), F0 (sRGB-encoded) and roughness (grey, black = 0).

Deterministic: the same PNG on every run. Run: .venv/bin/python tools/procedural_sheet_v2.py [OUT]
"""

from __future__ import annotations

import sys
from pathlib import Path

from matscan.materials.procedural import PRIORS, generate
from matscan.render import render, surface_points
from matscan.report.sheet import contact_sheet, save_sheet, to_display
from matscan.rig import builtin_rig

#: The families v2 has and v1 has not, in the order of their weights table.
NEW_FAMILIES = [f for f in PRIORS["v2"] if f not in PRIORS["v1"]]
SEEDS = (0, 1, 2)
SIZE = 256
LIGHTS = {"light 18": 18, "grazing 4": 4}


def main(out: Path) -> Path:
    rig = builtin_rig("dome24")
    points = surface_points(rig.field_mm, (SIZE, SIZE))
    tiles = []
    for family in NEW_FAMILIES:
        for seed in SEEDS:
            maps = generate(family, SIZE, seed)
            photos = render(
                maps.diffuse,
                maps.specular,
                maps.roughness,
                maps.normal,
                rig.light_set(list(LIGHTS.values())),
                points,
                compile=False,
            )
            for (label, _), photo in zip(LIGHTS.items(), photos, strict=True):
                tiles.append((f"{family} {seed}" if label == "light 18" else label, to_display(photo)))
            tiles.append(("normal", to_display(maps.normal, "normal")))
            tiles.append(("F0", to_display(maps.specular)))
            tiles.append(("roughness", to_display(maps.roughness, "grey")))
    save_sheet(out, contact_sheet(tiles, columns=5 * len(SEEDS), tile_size=128))
    return out


if __name__ == "__main__":
    path = main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/procedural-materials-v2.png"))
    print(f"wrote {path}")
