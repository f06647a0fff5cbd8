"""Contact sheets: many images in one labelled PNG a person can look at."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from matscan.color import linear_to_srgb
from matscan.imagefile import write_image

LABEL_HEIGHT = 18


def to_display(img: Tensor, kind: str = "srgb") -> np.ndarray:
    """A (C, H, W) linear image or map as (H, W, 3) display values in [0, 1].

    ``kind``: ``"srgb"`` encodes linear colour; ``"grey"`` shows values as is;
    ``"normal"`` shows (n + 1)/2.
    """
    t = img.detach().float()
    if kind == "normal":
        t = (t + 1) / 2
    elif kind == "srgb":
        t = linear_to_srgb(t.clamp(0, 1))
    if t.shape[0] == 1:
        t = t.expand(3, *t.shape[1:])
    return t.clamp(0, 1).permute(1, 2, 0).numpy()


def contact_sheet(
    tiles: Sequence[tuple[str, np.ndarray]],
    columns: int | None = None,
    tile_size: int = 160,
    gap: int = 4,
) -> np.ndarray:
    """Lay out (label, (H, W, 3) display image in [0, 1]) tiles in a grid; returns (H, W, 3)."""
    if not tiles:
        raise ValueError("contact_sheet: no tiles")
    columns = columns or math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / columns)
    cell_h = tile_size + LABEL_HEIGHT
    sheet = np.full((rows * (cell_h + gap) + gap, columns * (tile_size + gap) + gap, 3), 0.12, np.float32)
    for n, (label, img) in enumerate(tiles):
        r, c = divmod(n, columns)
        y0 = gap + r * (cell_h + gap)
        x0 = gap + c * (tile_size + gap)
        h, w = img.shape[:2]
        scale = tile_size / max(h, w)
        small = cv2.resize(
            img.astype(np.float32),
            (max(1, round(w * scale)), max(1, round(h * scale))),
            interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST,
        )
        sheet[y0 : y0 + small.shape[0], x0 : x0 + small.shape[1]] = small[..., :3]
        cv2.putText(
            sheet,
            label[:24],
            (x0 + 2, y0 + tile_size + 13),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0.9, 0.9, 0.9),
            1,
            cv2.LINE_AA,
        )
    return sheet


def save_sheet(path: str | Path, sheet: np.ndarray) -> None:
    """Write a contact sheet as an 8-bit PNG (atomically)."""
    write_image(Path(path), np.clip(sheet, 0, 1), bits=8)


def capture_tiles(images: Iterable[Tensor], labels: Sequence[str]) -> list[tuple[str, np.ndarray]]:
    """Tiles for the photos of a capture (linear (3, H, W) each)."""
    return [(lab, to_display(img)) for lab, img in zip(labels, images, strict=True)]


def map_tiles(maps: dict[str, Tensor]) -> list[tuple[str, np.ndarray]]:
    """Tiles for a map set's maps, each shown in its natural encoding."""
    kinds = {"diffuse": "srgb", "specular": "srgb", "basecolor": "srgb", "emissive": "srgb", "normal": "normal"}
    tiles = []
    for name, t in maps.items():
        if name == "height":
            lo, hi = float(t.min()), float(t.max())
            t = (t - lo) / (hi - lo) if hi > lo else torch.zeros_like(t)
        tiles.append((name, to_display(t, kinds.get(name, "grey"))))
    return tiles
