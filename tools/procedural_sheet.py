"""Contact sheet of the families a material prior adds to the one before it:
docs/procedural-materials-v2.png (v2 over v1), docs/procedural-materials-v3.png (v3 over v2),
docs/procedural-materials-v5.png (v5 over v4).

One row per family (:func:`new_families`; two rows when there is one), three materials a
row (seeds 0, 1, 2, … at 256² over the dome24 field, as ``matscan synth`` draws them),
five tiles a material: the
material under dome24 light 18 (ring 2, 67.5° elevation, the light ``synth``'s sheet
shows), under light 4 (ring 0, 22.5°: grazing, so relief casts its shading), the
normal map ((n + 1)/2), F0 (sRGB-encoded) and roughness (grey, black = 0).

Deterministic: the same PNG on every run.
Run: .venv/bin/python tools/procedural_sheet.py PRIOR [OUT]   (PRIOR v2, v3 or v5; OUT default as above)
"""

from __future__ import annotations

import sys
from pathlib import Path

from matscan.materials.procedural import PRIORS, generate
from matscan.render import render, surface_points
from matscan.report.sheet import contact_sheet, save_sheet, to_display
from matscan.rig import builtin_rig


def new_families(prior: str) -> list[str]:
    """The families ``prior`` has and the version before it has not, in the order of its
    weights table."""
    versions = list(PRIORS)
    before = PRIORS[versions[versions.index(prior) - 1]]
    return [f for f in PRIORS[prior] if f not in before]


SEEDS = (0, 1, 2)
SIZE = 256
LIGHTS = {"light 18": 18, "grazing 4": 4}


def main(prior: str, out: Path) -> Path:
    rig = builtin_rig("dome24")
    points = surface_points(rig.field_mm, (SIZE, SIZE))
    tiles = []
    families = new_families(prior)
    seeds = range(max(len(SEEDS), 6 // len(families)))  # six materials at least, in rows of three
    for family in families:
        for seed in seeds:
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
    prior = sys.argv[1] if len(sys.argv) > 1 else "v2"
    if prior not in list(PRIORS)[1:]:
        sys.exit(f"prior: {prior!r} is not one of {', '.join(list(PRIORS)[1:])}")
    path = main(prior, Path(sys.argv[2]) if len(sys.argv) > 2 else Path(f"docs/procedural-materials-{prior}.png"))
    print(f"wrote {path}")
