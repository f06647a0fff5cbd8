"""Evaluation: scores of predicted maps against ground truth, per input-light subset,
beside a trivial baseline.

The trivial baseline is what a user gets with no learning at all: diffuse = each
photo divided by the irradiance a flat surface receives there (the cosine and the
distance falloff and LED lobe of design.md's image formation), taking the median
over the photos so highlights drop out; a flat normal; roughness 0.5; specular 0.04.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from matscan.data import fixed_validation_set
from matscan.nets import MAPS, MapNets, network_input
from matscan.render import flat_irradiance, surface_points
from matscan.rig import Rig, resolve_rig

BASELINE_ROUGHNESS = 0.5
BASELINE_SPECULAR = 0.04


def baseline_maps(sample: dict[str, Tensor], rig: Rig) -> dict[str, Tensor]:
    """The trivial baseline's maps (3 or 1, H, W) for one sample (see module doc)."""
    present = sample["present"].nonzero().flatten().tolist()
    h, w = sample["inputs"].shape[-2:]
    pts = surface_points(rig.field_mm, (h, w), tuple(sample["offset"].tolist()), tuple(sample["full_size"].tolist()))
    e = flat_irradiance(rig.light_set(present), pts)
    rho = (sample["inputs"][present] / e.clamp_min(1e-3)).median(dim=0).values.clamp(0, 1)
    normal = torch.zeros(3, h, w)
    normal[2] = 1
    return {
        "diffuse": rho,
        "specular": torch.full((3, h, w), BASELINE_SPECULAR),
        "roughness": torch.full((1, h, w), BASELINE_ROUGHNESS),
        "normal": normal,
    }


class Scores:
    """Running sums for RMSE per map and mean normal angle."""

    def __init__(self) -> None:
        self.sq = {m: 0.0 for m in MAPS}
        self.n = {m: 0 for m in MAPS}
        self.angle = 0.0
        self.pixels = 0

    def add(self, pred: dict[str, Tensor], truth: dict[str, Tensor]) -> None:
        for m in MAPS:
            if m in pred:
                self.sq[m] += float(((pred[m] - truth[m]) ** 2).sum())
                self.n[m] += truth[m].numel()
        if "normal" in pred:
            cos = (pred["normal"] * truth["normal"]).sum(-3).clamp(-1, 1)
            self.angle += float(torch.rad2deg(torch.acos(cos)).sum())
            self.pixels += cos.numel()

    def result(self) -> dict[str, float]:
        res = {f"rmse_{m}": math.sqrt(self.sq[m] / self.n[m]) for m in MAPS if self.n[m]}
        if self.pixels:
            res["normal_degrees"] = self.angle / self.pixels
        return res


@torch.no_grad()
def subset_table(
    nets: MapNets | None,
    rig_name: str = "dome24",
    count: int = 32,
    crop: int = 128,
    subsets: Sequence[str] | None = None,
    batch: int = 8,
) -> dict[str, dict[str, dict[str, float]]]:
    """Scores of the networks (if given) and of the trivial baseline on the fixed
    validation set, for each named light subset of the rig (the same materials for
    every subset). Returns {subset: {"nets": scores, "baseline": scores}}."""
    rig = resolve_rig(rig_name)
    names = list(subsets) if subsets is not None else sorted(rig.subsets, key=lambda k: len(rig.subsets[k]))
    table: dict[str, dict[str, dict[str, float]]] = {}
    if nets is not None:
        nets.eval()
    for name in names:
        samples = fixed_validation_set(count, crop, rig_name, subsets=name)
        ours, base = Scores(), Scores()
        for i in range(0, len(samples), batch):
            chunk = samples[i : i + batch]
            truth = {m: torch.stack([s[m] for s in chunk]) for m in MAPS}
            if nets is not None:
                b = {k: torch.stack([s[k] for s in chunk]) for k in ("inputs", "present", "offset", "full_size")}
                ours.add(nets(network_input(b["inputs"], b["present"], b["offset"], b["full_size"], rig)), truth)
            for s in chunk:
                base.add(baseline_maps(s, rig), {m: s[m] for m in MAPS})
        table[name] = {"baseline": base.result()}
        if nets is not None:
            table[name]["nets"] = ours.result()
    return table
