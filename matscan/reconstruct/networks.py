"""Tiled network inference: the four map networks over a capture of any size.

The photos go into their rig-light slots with presence planes (any subset of
lights); images larger than ``tile`` are processed in overlapping tiles blended
with linear ramps, and the global-skip averages are computed over the whole image
first (summed over tiles), so memory is bounded by the tile size.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from tqdm import tqdm

from matscan.capture import Capture
from matscan.errors import MatscanError
from matscan.mapset import MapSet, normalize_normals
from matscan.nets import MapNets, network_input


def _slots(capture: Capture, n_lights: int, r0: int, c0: int, th: int, tw: int) -> tuple[Tensor, Tensor]:
    """A tile of the photos in their rig-light slots (1, L, 3, th, tw), and the presence (1, L)."""
    photos = torch.zeros(1, n_lights, 3, th, tw)
    present = torch.zeros(1, n_lights)
    region = capture.linear(rows=(r0, r0 + th), cols=(c0, c0 + tw))
    for img, k in zip(region, capture.light_indices, strict=True):
        photos[0, k] = img
        present[0, k] = 1
    return photos, present


def _ramp(n: int, overlap: int, first: bool, last: bool) -> Tensor:
    w = torch.ones(n)
    if overlap > 0:
        r = (torch.arange(overlap, dtype=torch.float32) + 0.5) / overlap
        if not first:
            w[:overlap] = r
        if not last:
            w[-overlap:] = r.flip(0)
    return w


def _starts(size: int, tile: int, overlap: int) -> list[int]:
    if size <= tile:
        return [0]
    step = tile - overlap
    starts = list(range(0, size - tile, step)) + [size - tile]
    return sorted(set(starts))


@torch.no_grad()
def predict_maps(nets: MapNets, capture: Capture, tile: int = 512, overlap: int = 64, progress: bool = False) -> MapSet:
    """The networks' maps for a capture of any size (see module doc, step 2)."""
    if capture.rig.per_image_geometry:
        raise MatscanError(
            f"rig {capture.rig.name!r}: the networks are trained for fixed-light rigs; "
            "use --refine on with --model none"
        )
    if nets.n_lights != len(capture.rig.lights):
        raise MatscanError(
            f"model: trained for {nets.n_lights} lights, but rig {capture.rig.name!r} has {len(capture.rig.lights)}"
        )
    # channels-last convolutions: 2.27 → 1.63 s for the cpu preset at 512² on 2 cores, same maps
    nets.eval().to(memory_format=torch.channels_last)
    h, w = capture.size
    m = nets.multiple
    tile = max(m, tile // m * m)
    overlap = min(overlap, tile // 2)
    full = torch.tensor([[h, w]])

    def encoded(r0: int, c0: int, th: int, tw: int) -> Tensor:
        photos, present = _slots(capture, nets.n_lights, r0, c0, th, tw)
        x = network_input(
            photos,
            present,
            torch.tensor([[r0, c0]]),
            full,
            capture.rig,
            capture.field_mm,
        )
        return x.contiguous(memory_format=torch.channels_last)

    rows, cols = _starts(h, tile, overlap), _starts(w, tile, overlap)
    pooled = None
    if len(rows) * len(cols) > 1:  # global averages over the whole image, from non-overlapping tiles
        totals: dict[str, list[Tensor]] = {}
        for r0 in range(0, h, tile):
            for c0 in range(0, w, tile):
                th, tw = min(tile, h - r0), min(tile, w - c0)
                for name, sums in nets.encoder_sums(encoded(r0, c0, th, tw)).items():
                    acc = totals.setdefault(name, [torch.zeros_like(s) for s in sums])
                    for a, s in zip(acc, sums, strict=True):
                        a += s
        pooled = {}
        for name, sums in totals.items():
            levels = []
            for i, s in enumerate(sums):
                count = math.ceil(h / 2**i) * math.ceil(w / 2**i)
                levels.append(s / count)
            pooled[name] = levels

    out = {
        name: torch.zeros(1, c, h, w)
        for name, c in (("diffuse", 3), ("specular", 3), ("roughness", 1), ("normal", 3))
        if name in nets.maps
    }
    weight = torch.zeros(1, 1, h, w)
    tiles = [(r, c) for r in rows for c in cols]
    for r0, c0 in tqdm(tiles, desc="networks", unit="tile", disable=not progress or len(tiles) == 1, leave=False):
        th, tw = min(tile, h - r0), min(tile, w - c0)
        pred = nets(encoded(r0, c0, th, tw), pooled)
        wr = _ramp(th, overlap, r0 == 0, r0 + th >= h)
        wc = _ramp(tw, overlap, c0 == 0, c0 + tw >= w)
        wt = (wr[:, None] * wc[None, :])[None, None]
        for name, t in pred.items():
            out[name][..., r0 : r0 + th, c0 : c0 + tw] += t * wt
        weight[..., r0 : r0 + th, c0 : c0 + tw] += wt
    maps = {name: t.div_(weight)[0] for name, t in out.items()}  # in place: no second copy at full size
    maps["normal"] = normalize_normals(maps["normal"])
    for name in ("diffuse", "specular", "roughness"):
        maps[name].clamp_(0, 1)
    return MapSet(**maps)
