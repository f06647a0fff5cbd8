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
from matscan.rig import Rig


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


#: The mirrors of an image, each a sequence of array operations applied in order: "t"
#: swaps rows and columns, "r" reverses the rows (top–bottom), "c" the columns
#: (left–right). Together the eight symmetries of a square.
MIRRORS: tuple[tuple[str, ...], ...] = ((), ("r",), ("c",), ("r", "c"), ("t",), ("t", "r"), ("t", "c"), ("t", "r", "c"))

#: For each operation, M with p = M p' taking a point p' of the mirrored image (x to the
#: right, y up, from the centre; design.md) to the point p of the sample it shows.
_OP_FRAME = {"r": ((1.0, 0.0), (0.0, -1.0)), "c": ((-1.0, 0.0), (0.0, 1.0)), "t": ((0.0, -1.0), (-1.0, 0.0))}


def mirror_frame(ops: tuple[str, ...]) -> Tensor:
    """The 2 × 2 map from the mirrored image's (x, y) to the original's (see _OP_FRAME)."""
    m = torch.eye(2, dtype=torch.float64)
    for op in ops:
        m = m @ torch.tensor(_OP_FRAME[op], dtype=torch.float64)
    return m


def _same(a, b, tol: float) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(abs(float(x) - float(y)) <= tol * max(1.0, abs(float(y))) for x, y in zip(a, b, strict=True))


def rig_mirror(rig: Rig, ops: tuple[str, ...], tol: float = 1e-5) -> list[int] | None:
    """Where each of the rig's lights goes when the image is mirrored by ``ops``: light k
    of the original lights the mirrored sample as light ``perm[k]`` does. None when the
    mirror is not a symmetry of the rig (a light maps onto none that is equal in every
    respect: place, aim, direction, lobe, intensity; or the camera is off the axis)."""
    mt = mirror_frame(ops).T.tolist()  # the inverse: original to mirrored

    def moved(v):
        if v is None:
            return None
        return (mt[0][0] * v[0] + mt[0][1] * v[1], mt[1][0] * v[0] + mt[1][1] * v[1], v[2])

    cam = rig.camera.position_mm if rig.camera.position_mm is not None else rig.camera.direction
    if not _same(moved(cam), cam, tol):
        return None
    perm = []
    for light in rig.lights:
        image = (moved(light.position_mm), moved(light.aim_mm), moved(light.direction))
        match = [
            k
            for k, other in enumerate(rig.lights)
            if _same(image[0], other.position_mm, tol)
            and _same(image[1], other.aim_mm, tol)
            and _same(image[2], other.direction, tol)
            and _same((light.exponent,), (other.exponent,), tol)
            and _same(light.intensity, other.intensity, tol)
        ]
        if len(match) != 1:
            return None
        perm.append(match[0])
    return perm if sorted(perm) == list(range(len(rig.lights))) else None


def capture_mirrors(capture: Capture) -> list[tuple[tuple[str, ...], list[int]]]:
    """The mirrors (:data:`MIRRORS`, with their light maps) under which the capture is a
    capture of the mirrored sample with the same lights lit: symmetries of the rig that
    take the lit lights onto themselves. Swapping rows and columns needs a square image
    of a square field. The identity is always first."""
    h, w = capture.size
    square = h == w and abs(capture.field_mm[0] - capture.field_mm[1]) <= 1e-6 * capture.field_mm[0]
    lit = set(capture.light_indices)
    found = []
    for ops in MIRRORS:
        if "t" in ops and not square:
            continue
        perm = rig_mirror(capture.rig, ops)
        if perm is not None and {perm[k] for k in lit} == lit:
            found.append((ops, perm))
    return found


def _mirror_array(x: Tensor, ops: tuple[str, ...]) -> Tensor:
    for op in ops:
        x = x.transpose(-1, -2) if op == "t" else x.flip(-2 if op == "r" else -1)
    return x


def _unmirror_array(x: Tensor, ops: tuple[str, ...]) -> Tensor:
    return _mirror_array(x, tuple(reversed(ops)))  # each operation is its own inverse


class _MirroredCapture:
    """A capture seen in a mirror (:func:`capture_mirrors`): what :func:`_predict`
    reads of it, the photos mirrored and each put in the slot of its mirrored light."""

    def __init__(self, capture: Capture, ops: tuple[str, ...], perm: list[int]) -> None:
        self.capture, self.ops, self.rig = capture, ops, capture.rig
        h, w = capture.size
        swap = ops.count("t") % 2 == 1
        self.size = (w, h) if swap else (h, w)
        self.field_mm = tuple(reversed(capture.field_mm)) if swap else tuple(capture.field_mm)
        self.light_indices = tuple(perm[k] for k in capture.light_indices)

    def linear(self, rows: tuple[int, int], cols: tuple[int, int]) -> Tensor:
        h, w = self.size
        for op in reversed(self.ops):  # the region, back through each operation
            if op == "t":
                rows, cols, h, w = cols, rows, w, h
            elif op == "r":
                rows = (h - rows[1], h - rows[0])
            else:
                cols = (w - cols[1], w - cols[0])
        return _mirror_array(self.capture.linear(rows=rows, cols=cols), self.ops)


@torch.no_grad()
def predict_maps(
    nets: MapNets,
    capture: Capture,
    tile: int = 512,
    overlap: int = 64,
    progress: bool = False,
    symmetric: bool = False,
) -> MapSet:
    """The networks' maps for a capture of any size (see module doc, step 2). With
    ``symmetric``, their mean over the capture's mirrors (:func:`capture_mirrors`), each
    mapped back and its normals turned back."""
    if capture.rig.per_image_geometry:
        raise MatscanError(
            f"rig {capture.rig.name!r}: the networks are trained for fixed-light rigs; "
            "use --refine on with --model none"
        )
    if nets.n_lights != len(capture.rig.lights):
        raise MatscanError(
            f"model: trained for {nets.n_lights} lights, but rig {capture.rig.name!r} has {len(capture.rig.lights)}"
        )
    mirrors = capture_mirrors(capture) if symmetric else [((), [])]
    total: dict[str, Tensor] = {}
    for ops, perm in mirrors:
        seen = _MirroredCapture(capture, ops, perm) if ops else capture
        maps = _predict(nets, seen, tile, overlap, progress)
        maps["normal"] = normalize_normals(maps["normal"])
        for name, t in maps.items():
            t = _unmirror_array(t if name == "normal" else t.clamp_(0, 1), ops)
            if name == "normal" and ops:
                t = torch.cat([torch.einsum("ij,jhw->ihw", mirror_frame(ops).float(), t[:2]), t[2:]])
            if name in total:
                total[name] += t
            else:
                total[name] = t.clone() if len(mirrors) > 1 else t
    if len(mirrors) > 1:
        total = {name: t / len(mirrors) for name, t in total.items()}
        total["normal"] = normalize_normals(total["normal"])
    return MapSet(**total)


def _predict(nets: MapNets, capture: Capture, tile: int, overlap: int, progress: bool) -> dict[str, Tensor]:
    """The networks' maps of one capture (or mirrored view), not yet normalised or clamped."""
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
    return {name: t.div_(weight)[0] for name, t in out.items()}  # in place: no second copy at full size
