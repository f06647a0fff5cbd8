"""Build training map sets from photographs of real surfaces with clear licences.

The photos come from one package of the Debian archive, ``supertuxkart-data`` (its
``copyright`` file gives the licence of every file, machine-readable). ``PHOTOS`` lists
the ones used: photographs of real surfaces, each CC0 or public domain there, chosen by
eye from the package's textures (painted game art, objects and texture atlases left out).
Each becomes a matscan map set folder by :func:`matscan.materials.photos.maps_from_photo`
(albedo from the photo, relief from its luminance, roughness from the relief, F0 0.04),
at ``--size``² over 120 mm, and ``SOURCES.md`` beside them names every file's origin and
licence and the package's SHA-256.

The map sets are training data: name them in a training config's ``library`` (data.py
mixes them with the procedural prior). Nothing is copied into the package, and nothing
downloads at run time: this script runs by hand, before training.

``--selection`` builds ``SELECTION`` instead: six more photographs of the package, kept
out of training, on which to choose among networks (snapshots of a run) so that the
evaluation sets are not used to choose.

Run: .venv/bin/python tools/photo_library.py OUT [--deb supertuxkart-data_*.deb] [--size 512] [--sheet PNG]
[--selection]
(without ``--deb``, ``apt-get download supertuxkart-data`` fetches the package, 628 MB).
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from matscan.errors import MatscanError
from matscan.imagefile import read_image
from matscan.mapset import write_mapset
from matscan.materials.photos import maps_from_photo

PACKAGE = "supertuxkart-data"
ROOT = "./usr/share/games/supertuxkart/"
#: name: (path in the package under ROOT, licence in its copyright file, what it shows)
PHOTOS: dict[str, tuple[str, str, str]] = {
    "granite": ("data/textures/Tizeta_grey1.png", "public-domain", "grey granite"),
    "black-rock": ("data/textures/black_rockMountain.jpg", "public-domain", "dark rock face"),
    "black-rock-2": ("data/textures/blackrock.jpg", "public-domain", "dark fractured rock"),
    "bumpy-plaster": ("data/textures/bumpy_surface.png", "CC0", "bumpy cream plaster"),
    "orange-plaster": ("data/textures/ceramic.jpg", "public-domain", "cracked orange plaster"),
    "stone-paving": ("data/textures/hacienda_ground.jpg", "public-domain", "stone paving"),
    "old-wood": ("data/textures/oldWood.png", "public-domain", "weathered wooden planks"),
    "rock": ("data/textures/rockMountain.jpg", "public-domain", "grey rock face"),
    "stone-wall": ("data/textures/rockwall.jpg", "public-domain", "rubble stone wall"),
    "rock-slab": ("data/textures/rock_mountain.jpg", "public-domain", "smooth rock slab"),
    "snow-rock": ("data/textures/snowrock.jpg", "public-domain", "layered rock"),
    "old-brick": (
        "data/tracks/ancient_colosseum_labyrinth/3td_BrickOldRound_01.jpg",
        "CC0",
        "old rounded bricks (3TD)",
    ),
    "ice": ("data/tracks/ancient_colosseum_labyrinth/Ice03_col.jpg", "CC0", "ice (ambientCG Ice003)"),
    "sand": ("data/tracks/sandtrack/sand.png", "CC0", "rippled sand"),
    "ground": ("data/tracks/cave/Ground010_1K_Color.png", "CC0", "bare ground (ambientCG Ground010)"),
    "forest-floor": ("data/tracks/black_forest/forest_floor.jpg", "CC0", "dry leaves on a forest floor"),
    "mossy-rock": ("data/tracks/black_forest/rock_gray.jpg", "CC0-1.0", "grey rock with moss"),
    "painted-metal": ("data/tracks/stk_enterprise/bomber_metal1b.jpg", "CC0", "painted sheet metal"),
    "concrete": ("data/tracks/stk_enterprise/img_0572.png", "CC0", "stained concrete (BurningWell)"),
    "rusty-metal": ("data/tracks/endcutscene/metal.jpg", "public-domain", "rusted metal"),
}

#: Photographs of the same package kept out of training, for choosing among networks
#: (a run's snapshots, ``tools/nets_unlike.py --mapsets``) without touching the evaluation
#: sets: ``--selection`` builds these instead of PHOTOS. Never name them in a training
#: config's ``library``. Same format as PHOTOS; no file of one is in the other.
SELECTION: dict[str, tuple[str, str, str]] = {
    "carpet": ("data/tracks/endcutscene/carpet.jpg", "public-domain", "knotted carpet"),
    "plaster-wall": ("data/textures/cottage_wall3.jpg", "public-domain", "rendered plaster wall"),
    "wood-planks": ("data/textures/wood_planks1.jpg", "public-domain", "vertical wooden planks"),
    "rock-wall": ("data/textures/rockwaterfall.jpg", "public-domain", "wet grey rock face"),
    "bridge-wood": ("data/textures/woodBridge.jpg", "public-domain", "weathered dark planks"),
    "red-wood": ("data/textures/japanRedWood.png", "public-domain", "red-painted wood"),
}


def fetch(workdir: Path) -> Path:
    """``apt-get download`` the package into workdir; the .deb's path."""
    try:
        subprocess.run(["apt-get", "download", PACKAGE], cwd=workdir, check=True, capture_output=True, text=True)
    except (OSError, subprocess.CalledProcessError) as e:
        detail = getattr(e, "stderr", "") or str(e)
        raise MatscanError(f"apt-get download {PACKAGE}: {detail.strip().splitlines()[-1] if detail else e}") from None
    debs = sorted(workdir.glob(f"{PACKAGE}_*.deb"))
    if not debs:
        raise MatscanError(f"apt-get download {PACKAGE}: no .deb appeared in {workdir}")
    return debs[-1]


def extract(deb: Path, into: Path, photos: dict[str, tuple[str, str, str]] = PHOTOS) -> dict[str, Path]:
    """The listed photos out of the .deb (streamed through ``dpkg-deb --fsys-tarfile``)."""
    wanted = {ROOT + path: name for name, (path, _, _) in photos.items()}
    found: dict[str, Path] = {}
    with subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE) as proc:
        assert proc.stdout is not None
        with tarfile.open(fileobj=proc.stdout, mode="r|") as tar:
            for member in tar:
                name = wanted.get(member.name)
                if name is None or not member.isfile():
                    continue
                data = tar.extractfile(member)
                assert data is not None
                out = into / f"{name}{Path(member.name).suffix}"
                out.write_bytes(data.read())
                found[name] = out
    if proc.returncode:
        raise MatscanError(f"{deb}: dpkg-deb could not read it (exit {proc.returncode})")
    missing = sorted(set(photos) - set(found))
    if missing:
        raise MatscanError(f"{deb}: lacks {', '.join(photos[m][0] for m in missing)} (another version of {PACKAGE}?)")
    return found


def photo_tensor(path: Path, size: int) -> torch.Tensor:
    """A photo as (3, size, size) sRGB-encoded values in [0, 1]: its central square, area-resampled."""
    img = read_image(path).pixels[..., :3]
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    h, w = img.shape[:2]
    s = min(h, w)
    top, left = (h - s) // 2, (w - s) // 2
    t = torch.from_numpy(np.ascontiguousarray(img[top : top + s, left : left + s])).permute(2, 0, 1).float()
    return F.interpolate(t[None], size=(size, size), mode="area")[0].clamp(0, 1)


def build(deb: Path, out: Path, size: int, sheet: Path | None = None, selection: bool = False) -> list[Path]:
    """Map set folders out/NAME and out/SOURCES.md from the .deb (of SELECTION where
    ``selection``, else of PHOTOS); returns the folders."""
    chosen = SELECTION if selection else PHOTOS
    if out.exists() and any(out.iterdir()):
        raise MatscanError(f"{out}: exists and is not empty; choose another folder")
    digest = hashlib.sha256(deb.read_bytes()).hexdigest()
    out.mkdir(parents=True, exist_ok=True)
    folders, tiles = [], []
    with tempfile.TemporaryDirectory() as tmp:
        photos = extract(deb, Path(tmp), chosen)
        for name in chosen:
            maps = maps_from_photo(photo_tensor(photos[name], size))
            folders.append(write_mapset(out / name, maps, extra_meta={"source": f"{PACKAGE}: {chosen[name][0]}"}))
            if sheet is not None:
                from matscan.report.sheet import to_display

                tiles += [(name, to_display(maps.diffuse)), ("normal", to_display(maps.normal, "normal"))]
    lines = [
        f"# Selection map sets from {PACKAGE} (never for training)"
        if selection
        else f"# Training map sets from {PACKAGE}",
        "",
        f"Built by tools/photo_library.py from `{deb.name}` (SHA-256 {digest}).",
        f"Licences as the package's `usr/share/doc/{PACKAGE}/copyright` gives them.",
        "",
        "| map set | file in the package | licence | shows |",
        "|---|---|---|---|",
    ]
    lines += [f"| {n} | `{p}` | {lic} | {what} |" for n, (p, lic, what) in chosen.items()]
    (out / "SOURCES.md").write_text("\n".join(lines) + "\n")
    if sheet is not None:
        from matscan.report.sheet import contact_sheet, save_sheet

        save_sheet(sheet, contact_sheet(tiles, columns=8, tile_size=112))
    return folders


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--deb", type=Path, help=f"a downloaded {PACKAGE} .deb (default: apt-get download it)")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--sheet", type=Path, help="also write a contact sheet (diffuse and normal of each)")
    ap.add_argument("--selection", action="store_true", help="build the selection sets (SELECTION), not training ones")
    args = ap.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            deb = args.deb if args.deb is not None else fetch(Path(tmp))
            if not deb.is_file():
                raise MatscanError(f"{deb}: no such file")
            folders = build(deb, args.out, args.size, args.sheet, args.selection)
    except MatscanError as e:
        print(f"photo_library: {e}", file=sys.stderr)
        return 1
    print(f"wrote {len(folders)} map sets and SOURCES.md to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
