"""Evaluation: scores of predicted maps against ground truth, per input-light subset,
beside a trivial baseline.

The trivial baseline is what a user gets with no learning at all: diffuse = each
photo divided by the irradiance a flat surface receives there (the cosine and the
distance falloff and LED lobe of design.md's image formation), taking a low order
statistic over the photos so highlights drop out (:func:`matscan.render.flat_albedo`);
a flat normal; roughness 0.5; specular 0.04.
"""

from __future__ import annotations

import math
import time
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from matscan.color import linear_to_srgb
from matscan.data import fixed_validation_set
from matscan.errors import MatscanError
from matscan.hsh import HSH_TERMS, fit_hsh_field, relight_hsh_field
from matscan.mapset import MapSet
from matscan.nets import MAPS, MapNets, network_input
from matscan.render import flat_albedo, flat_irradiance, light_vectors, render, surface_points
from matscan.rig import LightSet, Rig, resolve_rig

if TYPE_CHECKING:
    from matscan.capture import Capture

BASELINE_ROUGHNESS = 0.5
BASELINE_SPECULAR = 0.04


def baseline_maps(sample: dict[str, Tensor], rig: Rig) -> dict[str, Tensor]:
    """The trivial baseline's maps (3 or 1, H, W) for one sample (see module doc)."""
    present = sample["present"].nonzero().flatten().tolist()
    h, w = sample["inputs"].shape[-2:]
    pts = surface_points(rig.field_mm, (h, w), tuple(sample["offset"].tolist()), tuple(sample["full_size"].tolist()))
    e = flat_irradiance(rig.light_set(present), pts)
    rho = flat_albedo(sample["inputs"][present], e)
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


# --- the study: matscan evaluate -------------------------------------------------------------

#: Methods compared on the same captures. "baseline": the trivial baseline (the flat
#: start: photo ÷ flat irradiance, flat normal, roughness 0.5, specular 0.04); "nets": the
#: networks alone; "nets+refine": the networks then refinement (what `matscan reconstruct`
#: does from 10 photos up); "fit": per-pixel fitting alone (same renderer and optimiser,
#: from the flat start); "auto": what `matscan reconstruct` does by default (the networks,
#: then refinement where ``--refine auto`` chooses it). Any other weights file is given
#: as "nets:PATH" (or "nets+refine:PATH", "auto:PATH"): ablation variants and candidates.
#: "hsh": no maps, the RTI field's relighting fit (:func:`hsh_images`), scored on
#: re-rendering only, with 9 or more photos.
METHODS = ("baseline", "nets", "nets+refine", "fit", "auto", "hsh")
ENCODINGS = {"srgb8": ("srgb", 8), "linear16": ("linear", 16)}


def map_scores(pred: MapSet, truth: MapSet) -> dict[str, float]:
    """Per-map RMSE, mean normal angle (degrees) and SSIM of diffuse, specular, roughness."""
    from matscan.losses import ssim

    out = {}
    for m in MAPS:
        out[f"rmse_{m}"] = float((getattr(pred, m) - getattr(truth, m)).square().mean().sqrt())
    cos = (pred.normal * truth.normal).sum(0).clamp(-1, 1)
    out["normal_degrees"] = float(torch.rad2deg(torch.acos(cos)).mean())
    for m in ("diffuse", "specular", "roughness"):
        a, b = getattr(pred, m).clamp(0, 1)[None], getattr(truth, m).clamp(0, 1)[None]
        out[f"ssim_{m}"] = float(ssim(a, b)) if min(a.shape[-2:]) >= 11 else float("nan")
    return out


def rendering_scores(
    pred: MapSet, truth: MapSet, lights: LightSet, field_mm, prefix: str, flip: bool = True
) -> dict[str, float]:
    """RMSE (linear, clipped to [0, 1] like a photo) between renderings of the predicted
    and true maps under ``lights``; and mean LDR FLIP of the sRGB images where the
    flip-evaluator package is installed."""
    a = map_images(pred, lights, field_mm)
    b = map_images(truth, lights, field_mm)
    return image_scores(a, b, prefix, flip)


def map_images(maps: MapSet, lights: LightSet, field_mm) -> Tensor:
    """Linear renderings (L, 3, H, W) of maps under lights, clipped to [0, 1] like a photo."""
    pts = surface_points(field_mm, maps.size)
    with torch.no_grad():
        return render(maps.diffuse, maps.specular, maps.roughness, maps.normal, lights, pts).clamp(0, 1)


def image_scores(a: Tensor, b: Tensor, prefix: str, flip: bool = True) -> dict[str, float]:
    """RMSE between predicted images ``a`` and true ones ``b`` (both linear, (L, 3, H, W));
    and mean LDR FLIP of their sRGB encodings where flip-evaluator is installed."""
    out = {f"{prefix}_rmse": float((a - b).square().mean().sqrt())}
    if flip:
        try:
            import flip_evaluator
        except ImportError:
            return out
        values = []
        for x, y in zip(linear_to_srgb(a), linear_to_srgb(b), strict=True):
            _, mean, _ = flip_evaluator.evaluate(
                y.permute(1, 2, 0).numpy().astype("float32"), x.permute(1, 2, 0).numpy().astype("float32"), "LDR"
            )
            values.append(float(mean))
        out[f"{prefix}_flip"] = sum(values) / len(values)
    return out


def evaluation_lights(rig: Rig, count: int = 16, seed: int = 12345) -> LightSet:
    """The fixed novel lights of the study (:func:`matscan.losses.novel_lights`)."""
    from matscan.losses import novel_lights

    nl = novel_lights(
        1, count, rig.reference_distance_mm, rig.camera_point, torch.Generator().manual_seed(seed), rig.camera_w
    )
    return nl.batch_item(0)


def _method_nets(method: str, cache: dict) -> tuple[MapNets | None, str]:
    kind, _, path = method.partition(":")
    refine = {"nets+refine": "on", "fit": "on", "auto": "auto"}.get(kind, "off")
    if kind in ("fit", "baseline") and not path:
        return None, refine
    if kind not in ("nets", "nets+refine", "auto"):
        raise MatscanError(
            f"methods: {method!r} is not one of {', '.join(METHODS)} or nets:FILE, nets+refine:FILE, auto:FILE"
        )
    key = path or "default"
    if key not in cache:
        from matscan.weights import load_model

        cache[key] = load_model(key)[0]
    return cache[key], refine


def check_methods(
    methods: Sequence[str], encodings: Sequence[str], lights: Sequence[str] | None = None, rig_name: str = "dome24"
) -> None:
    """Refuse unknown methods, encodings, light subsets (when given) or weights files
    before any work starts."""
    if lights is not None:
        rig = resolve_rig(rig_name)
        for subset in lights:
            if str(subset) not in rig.subsets:
                names = ", ".join(rig.subsets) or "none"
                raise MatscanError(f"--lights: {subset!r} is not one of the light counts of rig {rig.name} ({names})")
        if "hsh" in methods and all(len(rig.subsets[str(s)]) < HSH_TERMS for s in lights):
            enough = ", ".join(k for k, v in rig.subsets.items() if len(v) >= HSH_TERMS)
            raise MatscanError(
                f"--lights: hsh fits {HSH_TERMS} coefficients a pixel and needs a subset of {HSH_TERMS} or more "
                f"lights ({rig.name}: {enough})"
            )
    for enc in encodings:
        if enc not in ENCODINGS:
            raise MatscanError(f"encodings: {enc!r} is not one of {', '.join(ENCODINGS)}")
    for method in methods:
        kind, _, path = method.partition(":")
        if kind not in METHODS or (path and kind not in ("nets", "nets+refine", "auto")):
            raise MatscanError(
                f"methods: {method!r} is not one of {', '.join(METHODS)} or nets:FILE, nets+refine:FILE, auto:FILE"
            )
        if path:
            from matscan.weights import model_path

            if not model_path(path).is_file():
                raise MatscanError(f"methods: {method}: no such weights file {path}")


def method_inputs(methods: Sequence[str]) -> list[Path]:
    """The weights files that ``methods`` read (``nets:FILE`` and the like; the shipped
    networks for ``nets``, ``nets+refine`` and ``auto``): inputs, which the study's output
    must never overwrite."""
    from matscan.weights import model_path

    found = []
    for method in methods:
        kind, _, path = method.partition(":")
        if kind in ("nets", "nets+refine", "auto") and model_path(path or "default") not in found:
            found.append(model_path(path or "default"))
    return found


#: Networks loaded in this process, by weights name or path.
_NETS_CACHE: dict = {}


def study_capture(name: str, truth: MapSet, enc: str, subset: str, rig_name: str, noise: float) -> Capture:
    """The study's capture of ``truth`` through the rig's light ``subset`` in encoding
    ``enc``: noise seeded by material, encoding and subset, so every method, every run
    and every tool that asks sees the same photos."""
    from matscan.capture import Capture
    from matscan.capture.virtual import CameraModel, simulate_images

    rig = resolve_rig(rig_name)
    encoding, bits = ENCODINGS[enc]
    indices = list(rig.subset(subset))
    seed = zlib.crc32(f"{name}|{enc}|{subset}".encode())
    ls = rig.light_set(indices)
    photos = simulate_images(
        truth, ls, rig.field_mm, CameraModel(read_noise=noise, encoding=encoding, bits=bits), seed=seed
    )
    top = 1.0 - 0.5 / ((1 << bits) - 1)
    return Capture(
        rig,
        rig.field_mm,
        encoding,
        photos,
        (photos >= top).any(1, keepdim=True),
        tuple(indices),
        ls,
        tuple(f"led_{k:02d}" for k in indices),
    )


def study_job(
    name: str,
    truth: MapSet,
    enc: str,
    subset: str,
    methods: Sequence[str],
    rig_name: str,
    refine_steps: int,
    noise: float,
) -> list[dict[str, Any]]:
    """One capture of the study (:func:`study_capture`), reconstructed with each method
    and scored."""
    from matscan.reconstruct import ReconstructConfig, reconstruct_capture

    rig = resolve_rig(rig_name)
    capture = study_capture(name, truth, enc, subset, rig_name, noise)
    rows = []
    for method in methods:
        if method == "hsh":
            if len(capture.files) >= HSH_TERMS:
                rows.append(_hsh_row(capture, truth, rig, name, enc, subset))
            continue
        nets, refine = _method_nets(method, _NETS_CACHE)
        t0 = time.perf_counter()
        res = reconstruct_capture(capture, ReconstructConfig(refine=refine, refine_steps=refine_steps), nets)
        seconds = time.perf_counter() - t0
        row = {"material": name, "encoding": enc, "lights": subset, "method": method, "seconds": seconds}
        row.update(map_scores(res.maps, truth))
        row.update(rendering_scores(res.maps, truth, rig.light_set(), rig.field_mm, "rig"))
        row.update(rendering_scores(res.maps, truth, evaluation_lights(rig), rig.field_mm, "novel"))
        rows.append(row)
    return rows


def hsh_images(capture: Capture, lights: LightSet) -> Tensor:
    """The RTI field's answer to relighting: an order-2 HSH fit per pixel and channel to
    the capture's photos, with each light's own direction and falloff at every pixel
    (:func:`matscan.hsh.fit_hsh_field`), evaluated under ``lights``: linear images
    (L, 3, H, W) in [0, 1]."""
    return relight_capture_hsh(hsh_of_capture(capture), capture, lights)


def hsh_of_capture(capture: Capture) -> Tensor:
    """The per-pixel HSH coefficients (9, 3, H, W) of a capture's photos (saturated pixels
    left out of the fit, as RTI software's fits leave them out)."""
    pts = surface_points(capture.field_mm, capture.size)
    directions, _ = light_vectors(capture.lights, pts)
    valid = (~capture.saturated).float()
    return fit_hsh_field(capture.linear(), flat_irradiance(capture.lights, pts), directions, weights=valid)


def relight_capture_hsh(coefficients: Tensor, capture: Capture, lights: LightSet) -> Tensor:
    pts = surface_points(capture.field_mm, capture.size)
    directions, _ = light_vectors(lights, pts)
    return relight_hsh_field(coefficients, flat_irradiance(lights, pts), directions)


def _hsh_row(capture: Capture, truth: MapSet, rig: Rig, name: str, enc: str, subset: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    coefficients = hsh_of_capture(capture)
    seconds = time.perf_counter() - t0  # the fit, as the other methods' reconstruction is timed
    rig_lights, novel = rig.light_set(), evaluation_lights(rig)
    both = relight_capture_hsh(coefficients, capture, LightSet.cat([rig_lights, novel]))
    row: dict[str, Any] = {"material": name, "encoding": enc, "lights": subset, "method": "hsh", "seconds": seconds}
    n = len(rig_lights)
    row.update(image_scores(both[:n], map_images(truth, rig_lights, rig.field_mm), "rig"))
    row.update(image_scores(both[n:], map_images(truth, novel, rig.field_mm), "novel"))
    return row


def _worker_init() -> None:
    torch.set_num_threads(1)  # one process per core beats threads within one process here


def run_study(
    materials: list[tuple[str, MapSet]],
    rig_name: str = "dome24",
    lights: Sequence[str] = ("1", "2", "3", "6", "10", "16", "24"),
    methods: Sequence[str] = METHODS,
    encodings: Sequence[str] = tuple(ENCODINGS),
    refine_steps: int = 150,
    noise: float = 0.002,
    progress: bool = False,
    jobs: int = 1,
) -> list[dict[str, Any]]:
    """Simulate captures of each material through the rig for each light subset and
    encoding, reconstruct with each method, and score. Returns one row per
    (material, encoding, lights, method), in that order whatever ``jobs`` (the number of
    worker processes; each capture's photos are seeded, so the rows do not depend on it
    beyond floating-point summation order)."""
    from tqdm import tqdm

    check_methods(methods, encodings, lights, rig_name)  # unknown subsets fail here, not in a worker
    work = [
        (n, m, e, s, tuple(methods), rig_name, refine_steps, noise)
        for n, m in materials
        for e in encodings
        for s in lights
    ]
    bar = tqdm(total=len(work), desc="evaluate", unit="capture", disable=not progress)
    results: list[list[dict[str, Any]]] = [[] for _ in work]
    if jobs <= 1:
        for i, w in enumerate(work):
            results[i] = study_job(*w)
            bar.update()
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_init) as pool:
            futures = {pool.submit(study_job, *w): i for i, w in enumerate(work)}
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                bar.update()
    bar.close()
    return [row for rs in results for row in rs]


def summarise(rows: list[dict[str, Any]], keys: Sequence[str]) -> dict[tuple, dict[str, float]]:
    """Mean of every numeric score over rows grouped by ``keys``."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    out = {}
    for key, rs in groups.items():
        numeric = [k for k, v in rs[0].items() if isinstance(v, float)]
        out[key] = {k: sum(r[k] for r in rs) / len(rs) for k in numeric}
    return out


COLUMNS = (
    "rmse_diffuse",
    "rmse_specular",
    "rmse_roughness",
    "normal_degrees",
    "rig_rmse",
    "novel_rmse",
    "novel_flip",
    "seconds",
)


def markdown_table(rows: list[dict[str, Any]], lights: Sequence[str]) -> str:
    """Mean scores per method and light count (over materials and encodings)."""
    summary = summarise(rows, ("method", "lights"))
    cols = [c for c in COLUMNS if any(c in v for v in summary.values())]
    lines = ["| method | lights | " + " | ".join(cols) + " |", "|---|---:|" + "---:|" * len(cols)]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for m in methods:
        for n in lights:
            if (m, n) in summary:
                v = summary[(m, n)]
                lines.append(f"| {m} | {n} | " + " | ".join(f"{v[c]:.4f}" if c in v else "–" for c in cols) + " |")
    return "\n".join(lines) + "\n"


SUMMARY_COLUMNS = (
    "rmse_diffuse",
    "rmse_specular",
    "rmse_roughness",
    "normal_degrees",
    "ssim_diffuse",
    "ssim_roughness",
    "novel_rmse",
    "novel_flip",
)


def source_of(material: str) -> str:
    """The kind of evaluation material: procedural, photo (texture photographs), artist
    (artist-style map sets, :mod:`matscan.materials.artist`) or mapset."""
    return material.split("-", 1)[0] if material.startswith(("procedural-", "photo-", "artist-")) else "mapset"


def summary_table(rows: list[dict[str, Any]], by: str) -> str:
    """The paper's Tables 1 and 9 form: a row per method (and per value of ``by``: "source"
    or "encoding"), the mean of each score over materials and light counts."""
    rows = [{**r, "source": source_of(r["material"])} for r in rows]
    summary = summarise(rows, ("method", by))
    cols = [c for c in SUMMARY_COLUMNS if any(c in v for v in summary.values())]
    lines = [f"| method | {by} | " + " | ".join(cols) + " |", "|---|---|" + "---:|" * len(cols)]
    for m in dict.fromkeys(r["method"] for r in rows):
        for b in dict.fromkeys(r[by] for r in rows):
            if (m, b) in summary:
                v = summary[(m, b)]
                lines.append(f"| {m} | {b} | " + " | ".join(f"{v[c]:.4f}" if c in v else "–" for c in cols) + " |")
    return "\n".join(lines) + "\n"


def plot_curves(rows: list[dict[str, Any]], lights: Sequence[str], path: Path) -> bool:
    """The input-count curves (the paper's Fig. 13): one panel per map, error against
    number of lights, a line per method. Returns False where matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    summary = summarise(rows, ("method", "lights"))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    panels = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "normal_degrees", "novel_rmse")
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.4))
    for ax, panel in zip(axes, panels, strict=True):
        for m in methods:
            scored = [n for n in lights if panel in summary.get((m, n), {})]  # hsh has no maps
            if scored:
                ax.plot([int(n) for n in scored], [summary[(m, n)][panel] for n in scored], marker="o", label=m)
        ax.set_xscale("log")
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xticks([int(n) for n in lights])
        ax.set_xticklabels(list(lights))
        ax.set_xlabel("input lights")
        ax.set_title(panel.replace("_", " "))
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize=8)  # every method relights; hsh has no map panels
    fig.tight_layout()
    from matscan.atomic import atomic_file

    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return True


def evaluate_to_folder(
    materials: list[tuple[str, MapSet]],
    out: Path,
    lights: Sequence[str],
    methods: Sequence[str],
    encodings: Sequence[str],
    refine_steps: int = 150,
    overwrite: bool = False,
    progress: bool = False,
    jobs: int = 1,
    inputs: Sequence[Path] = (),
    overwrite_any: bool = False,
) -> dict[str, Any]:
    """``matscan evaluate``: run the study and write results.json, results.md and plots.

    ``out`` is checked and locked before the study (never one of ``inputs``, the map
    set folders read, nor a weights file that ``methods`` name)."""
    from matscan.jsonfile import dumps, finite_or_null
    from matscan.outputs import claim_output

    check_methods(methods, encodings, lights)
    inputs = [*inputs, *method_inputs(methods)]
    with claim_output(out, "evaluate", inputs, overwrite=overwrite, overwrite_any=overwrite_any) as claim:
        t0 = time.perf_counter()
        rows = run_study(materials, "dome24", lights, methods, encodings, refine_steps, progress=progress, jobs=jobs)
        with claim.folder() as tmp:
            doc = {
                "rows": rows,
                "lights": list(lights),
                "methods": list(methods),
                "encodings": list(encodings),
                "materials": [n for n, _ in materials],
            }
            (tmp / "results.json").write_text(dumps(finite_or_null(doc), "results.json", indent=1))
            _write_tables(tmp, rows, materials, lights, methods, encodings, t0)
    return {"rows": len(rows), "seconds": time.perf_counter() - t0}


def _write_tables(
    tmp: Path,
    rows: list[dict[str, Any]],
    materials: list[tuple[str, MapSet]],
    lights: Sequence[str],
    methods: Sequence[str],
    encodings: Sequence[str],
    t0: float,
) -> None:
    """results.md and the input-count plot of a finished study."""
    plotted = plot_curves(rows, lights, tmp / "input_count.png")
    rows_all = rows
    # a method scored at fewer counts (hsh: 9 lights or more) is compared over those only
    counts = [{r["lights"] for r in rows if r["method"] == m} for m in dict.fromkeys(r["method"] for r in rows)]
    shared = set.intersection(*counts) if counts else set()
    over = "light counts"
    if any(c != shared for c in counts):
        rows = [r for r in rows if r["lights"] in shared]
        over = "the light counts every method has (" + ", ".join(n for n in lights if n in shared) + ")"
    runs = len(materials) * len(encodings) * len(lights) * len(methods)
    scored = "" if len(rows_all) == runs else f", {len(rows_all)} runs (hsh fits {HSH_TERMS} photos or more)"
    md = [
        "# matscan evaluation",
        "",
        f"{len(materials)} materials × {len(encodings)} encodings × "
        f"{len(lights)} light subsets × {len(methods)} methods{scored}; {time.perf_counter() - t0:.0f} s.",
        "",
        "## By method and number of lights (mean over materials and encodings)",
        "",
        markdown_table(rows_all, lights),
        f"## By method and material source (mean over {over} and encodings)",
        "",
        summary_table(rows, "source"),
        f"## By method and capture encoding (mean over materials and {over})",
        "",
        summary_table(rows, "encoding"),
    ]
    if plotted:
        md += ["![input-count curves](input_count.png)", ""]
    (tmp / "results.md").write_text("\n".join(md))
