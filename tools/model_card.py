"""Export a training run's weights into the package, score them, and write the model card.

For each of the rig's named light subsets (dome24: the paper's Table 4, 1 to 24
lights) it scores the networks and the trivial baseline (matscan.evaluate) on the
same procedural materials, never used in training, and writes the table into
docs/model-card.md together with how the weights were trained (from the weights'
own metadata and the run's log).

Run: .venv/bin/python tools/model_card.py runs/dome24-cpu [count] [--fill FILE] [--take MAPS]
(writes matscan/weights/dome24-cpu.safetensors and docs/model-card.md)

The card's second table, on materials unlike the training set, comes from a study:
    matscan evaluate procedural:8 photos artist --encodings srgb8 --out docs/results/engine ...
    .venv/bin/python tools/model_card.py --unlike docs/results/engine/results.json
(rewrites that section only; it names the weights file's SHA-256, and a card rewritten
for other weights keeps the section marked stale until the study is re-run).

A run that trained only some of the four networks (``matscan train --maps``) is
completed with the others of ``--fill`` (default: the weights the run started
from, its ``init``); the card says, per network, how much training is behind it. A run
whose checkpoint is not committed is exported from its ``weights.safetensors``.
``--take diffuse,normal`` ships only those networks of the run, the others from ``--fill``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from pathlib import Path

import torch

from matscan.evaluate import subset_table
from matscan.materials.procedural import PRIORS
from matscan.train import CHECKPOINT, _metadata, export_weights, load_weights
from matscan.weights import ROOT, SHIPPED

MAP_COLUMNS = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "rmse_normal", "normal_degrees")
CARD = Path("docs/model-card.md")
UNLIKE = "## On materials unlike the training set"
PROCEDURAL = "## On the study's procedural materials"
UNLIKE_METHODS = ("nets", "baseline", "fit", "auto")
UNLIKE_COLUMNS = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "normal_degrees", "novel_rmse")


def sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def unlike_section(results: Path, weights: Path) -> list[str]:
    """The card's sections made from a study: the texture-photograph and artist-style map
    sets (never trained on), then, where the study has them, its procedural materials
    (the validation table's distribution, with the per-pixel fit and novel lights beside)."""
    doc = json.loads(results.read_text())
    sha = sha256(weights)[:16]
    rows = [r for r in doc["rows"] if r["encoding"] == "srgb8"]
    unlike = [r for r in rows if r["material"].startswith(("photo-", "artist-"))]
    materials = sorted({r["material"] for r in unlike})
    lines = [
        UNLIKE,
        "",
        f"Weights SHA-256 `{sha}`. {len(materials)} map sets that no network was trained on "
        f"({', '.join(m for m in materials)}; `matscan/materials/photos.py` and `artist.py`, 256², "
        "docs/artist-materials.png), photographed by the virtual dome24 in 8-bit sRGB with noise under each "
        "Table 4 subset; mean over the map sets. `nets`: these networks alone; `baseline`: as above; `fit`: the "
        "second-order solver from the baseline's flat start, no networks (per-pixel fitting); `auto`: what "
        "`matscan reconstruct` does by default. `novel`: RMSE of renderings under 16 lights the rig does not "
        "have (docs/results.md).",
        "",
        *study_table(unlike, doc["lights"]),
    ]
    procedural = [r for r in rows if r["material"].startswith("procedural-")]
    if procedural:
        names = sorted({r["material"] for r in procedural})
        lines += [
            PROCEDURAL,
            "",
            f"Weights SHA-256 `{sha}`. The same study's {len(names)} procedural materials (`procedural:{len(names)}`: "
            "prior v1, the validation table's distribution, seeds 2^41 + i, never drawn in training; 256²), "
            "photographed and scored as above: the per-pixel fit and the novel lights beside the networks on "
            "the procedural families (the networks' training drew these and later priors' families).",
            "",
            *study_table(procedural, doc["lights"]),
        ]
    made = "Both made" if procedural else "Made"
    lines += [f"{made} with `.venv/bin/python tools/model_card.py --unlike {results}`.", ""]
    return lines


def study_table(rows: list[dict], lights: list[str]) -> list[str]:
    """A study's rows as the card's table (mean over the map sets per count and method),
    where the networks' map errors rise, and where their novel-light error is below the
    baseline's and the fit's."""
    lines = [
        "| lights | method | diffuse | specular | roughness | normal ° | novel |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    novel: dict[tuple[str, str], float] = {}
    for n in lights:
        for method in UNLIKE_METHODS:
            sel = [r for r in rows if r["lights"] == n and r["method"] == method]
            if not sel:
                continue
            means = [sum(r[c] for r in sel) / len(sel) for c in UNLIKE_COLUMNS]
            novel[n, method] = means[-1]
            lines.append(
                f"| {n} | {method} | "
                + " | ".join(
                    f"{v:.1f}" if c == "normal_degrees" else f"{v:.4f}"
                    for c, v in zip(UNLIKE_COLUMNS, means, strict=True)
                )
                + " |"
            )
    lines += ["", "Where the networks' map errors rise as lights are added: " + unlike_rises(rows, lights) + "."]
    for other in ("baseline", "fit"):
        counts = [n for n in lights if (n, "nets") in novel and (n, other) in novel]
        below = [n for n in counts if novel[n, "nets"] < novel[n, other]]
        where = f"{len(below)} of the {len(counts)} light counts ({', '.join(below)})" if below else "no light count"
        lines += ["", f"The networks' novel-light error is below the {other}'s at {where}."]
    return [*lines, ""]


def unlike_rises(rows: list[dict], lights: list[str]) -> str:
    """Each map error of the networks alone (``nets``; mean over the map sets) that is
    higher at a light count than at the one before it, or "nowhere"."""
    means = {}
    for n in lights:
        sel = [r for r in rows if r["lights"] == n and r["method"] == "nets"]
        if sel:
            means[n] = {c: sum(r[c] for r in sel) / len(sel) for c in UNLIKE_COLUMNS[:-1]}
    names = list(means)
    rises = [
        f"{c.removeprefix('rmse_').replace('_', ' ')} from {a} to {b} lights "
        + (
            f"({means[a][c]:.1f} → {means[b][c]:.1f})"
            if c == "normal_degrees"
            else f"({means[a][c]:.3f} → {means[b][c]:.3f})"
        )
        for c in UNLIKE_COLUMNS[:-1]
        for a, b in zip(names, names[1:], strict=False)
        if means[b][c] > means[a][c]
    ]
    return "; ".join(rises) if rises else "nowhere"


def replace_unlike(card: str, section: list[str]) -> str:
    """The card with its unlike-the-training-set section replaced (or appended)."""
    head, found, _ = card.partition(UNLIKE)
    return head.rstrip("\n") + "\n\n" + "\n".join(section) if found else card.rstrip("\n") + "\n\n" + "\n".join(section)


STALE = "**Stale: made with earlier weights; re-run the study and `--unlike`.**"


def kept_unlike(card: str, weights: Path) -> list[str]:
    """The old card's sections made from a study (the unlike sets', and the procedural
    materials' where there), each marked stale when it was made with other weights."""
    _, found, tail = card.partition(UNLIKE)
    if not found:
        return []
    lines = (UNLIKE + tail).rstrip("\n").split("\n")
    kept: list[str] = []
    i = 0
    while i < len(lines):
        kept.append(lines[i])
        if lines[i].startswith("## ") and i + 2 < len(lines):
            start = i + 2
            if lines[start] == STALE:  # marked by an earlier rewrite: mark it once
                start += 2
            kept.append(lines[i + 1])
            if sha256(weights)[:16] not in lines[start]:
                kept += [STALE, ""]
            i = start
            continue
        i += 1
    return [*kept, ""]


def reading(table: dict, statistic: str) -> list[str]:
    """What the table says, derived from its numbers (so it cannot go stale)."""
    names = list(table)
    losses = [
        f"{c.removeprefix('rmse_').replace('_', ' ')} at {n} lights ({table[n]['nets'][c]:.3f} vs "
        f"{table[n]['baseline'][c]:.3f})"
        for n in names
        for c in MAP_COLUMNS
        if table[n]["nets"][c] >= table[n]["baseline"][c]
    ]
    rises = [
        f"{c.removeprefix('rmse_').replace('_', ' ')} from {a} to {b} lights ({table[a]['nets'][c]:.3f} → "
        f"{table[b]['nets'][c]:.3f})"
        for c in MAP_COLUMNS
        for a, b in zip(names, names[1:], strict=False)
        if table[b]["nets"][c] > table[a]["nets"][c]
    ]
    out = [
        "Reading the table: "
        + (
            "the networks beat the baseline on every map at every light count."
            if not losses
            else "the networks beat the baseline everywhere except " + "; ".join(losses) + "."
        ),
        "",
        "Where the networks' error rises as lights are added: " + ("; ".join(rises) if rises else "nowhere") + ".",
    ]
    if statistic == "median" and any(" from 2 to 3 lights" in r for r in rises):
        out += [
            "",
            "The 3-light subset of Table 4 (lights 0, 16, 23) puts two of its three lights in the top ring beside "
            "the camera, so on glossy materials two of three photos carry a highlight. G_d starts from the median "
            "of photo ÷ flat irradiance, and the median of three then keeps a highlight; the baseline's "
            "lower-third order statistic drops it. Changing G_d's starting estimate means retraining G_d.",
        ]
    out += [
        "",
        "Every row is a named subset of the rig (Table 4), which training favours: with "
        'other lights of the same count the networks do measurably worse (docs/results.md, "Which lights", '
        "measures how much), and `matscan reconstruct` warns when it reads such a capture.",
        "",
        "Training continues across sessions; this card is rewritten each time the weights are.",
    ]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, nargs="?")
    parser.add_argument("count", type=int, nargs="?", default=64, help="validation materials (default 64)")
    parser.add_argument("--fill", type=Path, default=None, help="weights of the networks the run did not train")
    parser.add_argument("--take", default=None, help="ship only these networks of the run, e.g. diffuse,normal")
    parser.add_argument("--unlike", type=Path, help="rewrite only the unlike-the-training-set section from this study")
    args = parser.parse_args()
    if args.unlike:
        card = CARD.read_text()
        CARD.write_text(replace_unlike(card, unlike_section(args.unlike, ROOT / SHIPPED["default"])))
        return 0
    if args.run is None:
        parser.error("give a training run, or --unlike RESULTS")
    old_card = CARD.read_text() if CARD.is_file() else ""
    run, count = args.run, args.count
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    # the run's checkpoint, or the float16 weights kept in git where the checkpoint is too large to commit
    source = run / CHECKPOINT if (run / CHECKPOINT).is_file() else run / "weights.safetensors"
    run_meta = _metadata(source)
    fill = args.fill
    take = args.take.split(",") if args.take else None
    if fill is None and len(take or json.loads(run_meta.get("config") or run_meta["train_config"])["maps"]) < 4:
        fill = Path(run_meta["init"])
        if not fill.is_file():
            sys.exit(f"{fill}: the weights this run started from are needed for the networks it did not train (--fill)")
    weights = export_weights(source, ROOT / SHIPPED["default"], {"run": str(run)}, fill_from=fill, take=take)
    weights.chmod(0o644)
    nets, meta = load_weights(weights)
    cfg = json.loads(meta.get("train_config") or meta["config"])
    net = json.loads(meta["net_config"])
    networks = json.loads(meta["networks"])
    t0 = time.perf_counter()
    table = subset_table(nets, cfg["rig"], count=count, crop=cfg["crop"])
    seconds = time.perf_counter() - t0
    (run / "scores.json").write_text(json.dumps(table, indent=2) + "\n")

    rows = list(csv.DictReader((run / "log.csv").open())) if (run / "log.csv").is_file() else []
    hours = float(meta.get("elapsed_seconds", 0)) / 3600
    init_hours = float(meta.get("init_elapsed_seconds", 0)) / 3600
    if "init_networks" in meta:  # per network: an assembled init file's networks had different training
        before = "steps before this run: " + ", ".join(
            f"{m} {r['steps']:,} ({r['elapsed_seconds'] / 3600:.2f} h)"
            for m, r in json.loads(meta["init_networks"]).items()
        )
    else:
        before = (
            f"{meta.get('init_step')} steps, {init_hours:.2f} h, G_d's start the "
            f"{meta.get('init_photo_statistic', '').replace('_', ' ')}"
        )
    params = sum(p.numel() for p in nets.parameters())
    options = (f" --fill {args.fill}" if args.fill else "") + (f" --take {args.take}" if args.take else "")
    # the run's own settings file is the command's: a list of flags would leave out
    # some (the prior, the photo library, the rendering loss's form)
    train_cmd = f"matscan train --out {run} --config {run}/config.json --minutes M"
    joint = cfg.get("render_with", "own") == "joint"
    lines = [
        "# Model card: `default` (dome24, `cpu` preset)",
        "",
        f"File: `matscan/weights/{weights.name}` ({weights.stat().st_size / 2**20:.1f} MiB, {params:,} parameters "
        "in four networks, float32, safetensors).",
        "",
        "The any-rig network shipped beside it (`reconstruct --anyrig default`) has its own card: "
        "[model-card-anyrig.md](model-card-anyrig.md).",
        "",
        "## How it was trained",
        "",
        f"- Command: `{train_cmd}` (resumed across sessions; the run's `config.json` holds every setting), "
        f"then `tools/model_card.py {run} {count}" + options + "`.",
        f"- Networks: the paper's U-Net with global skip connections, preset `{cfg['preset']}` "
        f"(variant `{cfg['variant']}`): four independent networks for diffuse, specular, roughness (via "
        "glossiness) and normals; inputs are 24 light slots with presence planes and field coordinates, so one "
        "set of weights takes any subset of lights. Each photo is divided by the irradiance a flat surface gets "
        "there from its light, and G_d predicts a correction to the "
        + {"median": "median", "lower_third": "lower-third order statistic"}[net["photo_statistic"]]
        + " of those ratios over the photos present (the `cpu` preset's `diffuse_from_photos` and "
        "`photo_statistic`; the `paper` preset keeps G_d plain).",
        "- Data"
        + (" in this run (the runs before it: their `config.json`)" if "init" in meta else "")
        + ": procedural materials of `matscan.materials` ("
        + (f"prior `{cfg.get('prior', 'v1')}`, {sum(w > 0 for w in PRIORS[cfg.get('prior', 'v1')].values())} families")
        + ", mixed as in Deschaintre et al. 2018)"
        + (
            f" and, in {cfg.get('library_prob', 0.5):.0%} of this run's samples, the {len(cfg['library'])} "
            "photo-built map sets of `tools/photo_library.py` (texture photographs of a Debian package, "
            "never the evaluation photos)"
            if cfg.get("library")
            else ""
        )
        + f", {cfg['crop']}² crops anywhere in the dome24 field, random light subsets (Table 4 subsets half the time), "
        "calibration jitter, Poisson–Gaussian noise, 8-bit sRGB or 16-bit linear quantisation; rendered on the fly.",
        f"- Optimiser: Adam, lr {cfg['lr']:g}"
        + (" in this run (the runs before it, with theirs: README.md, Development)" if "init" in meta else "")
        + f", batch {cfg['batch']}, per-network gradient clipping at "
        f"{cfg['grad_clip']}; losses: map L1, rendering loss under {cfg['render_lights']} random novel lights "
        f"(λ_r = {cfg['lambda_render']:.4f}), 1 − SSIM for diffuse, cosine for normals.",
        f"- This run: {meta['step']} steps ({int(meta['step']) * cfg['batch']:,} samples) of "
        f"{', '.join(cfg['maps'])} in {hours:.2f} h on 2 CPU cores (no GPU)"
        + (f", of which this file ships {args.take} (the others: `{fill}`)" if take else "")
        + (
            f", started from `{meta['init']}` ({before}) and drawing the samples after the "
            f"{meta['init_step']} steps behind it"
            + (
                f"; how those were trained, on what hardware and with what batch: "
                f"`{Path(meta['init']).parent}/README.md`."
                if (Path(meta["init"]).parent / "README.md").is_file()
                else "."
            )
            if "init" in meta
            else "."
        ),
    ]
    if rows:
        lines.append(
            f"- Last logged training losses (step {rows[-1]['step']}): "
            + ", ".join(f"{m} {float(rows[-1][m]):.3f}" for m in cfg["maps"])
        )
    lines += [
        "",
        "| network | steps in all | training behind it | from |",
        "|---|---:|---:|---|",
        *(
            f"| {m} | {r['steps']:,} | {r['elapsed_seconds'] / 3600:.2f} h | `{r['from']}` |"
            for m, r in networks.items()
        ),
        "",
        "Steps of every run behind a network add up whatever their batch (4 in CPU runs, 32 in GPU runs; each "
        # hand-kept: the weights' metadata records steps and hours per network, not the hardware
        "run's `config.json`). Hardware: every CPU run on 2 CPU cores (no GPU); behind all four networks, two "
        "short stages on one NVIDIA H100 (1,936 steps of batch 32 in 14 minutes, `runs/dome24-v2-gpu/README.md`), "
        "continued on the CPU by `runs/dome24-mix-cpu`.",
        "",
        'The four networks are independent. With the paper\'s rendering loss (`render_with` "own") each has '
        "its own (one predicted map rendered with the other three true maps), so one network trained alone "
        "gets the same updates as in a run of all four (`tests/test_train.py`); the hours are the wall time "
        "of the runs behind each network, whether they trained all four networks at once or it alone."
        + (
            f" This run rendered the predicted {' and '.join(cfg['maps'])} maps together instead "
            '(`render_with` "joint", the other maps true), so its networks learned to relight well '
            "together and its weights are not those of each trained alone."
            if joint
            else ""
        ),
    ]
    lines += [
        "",
        "## What it scores",
        "",
        f"Validation: {count} procedural materials never drawn in training (`matscan.data.fixed_validation_set`, "
        f"{cfg['crop']}² crops, noise and quantisation as in training), the same materials for every light subset. "
        "RMSE of each map in its own units (linear albedo, roughness, unit-vector components) and the mean angle "
        "between predicted and true normals. Baseline: photo ÷ flat-surface irradiance (lower-third order "
        "statistic over the photos, `matscan.render.flat_albedo`), flat normal, roughness 0.5, specular 0.04 "
        "(`matscan.evaluate.baseline_maps`).",
        "",
        "| lights | method | diffuse | specular | roughness | normal | normal ° |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for name, res in table.items():
        for method in ("nets", "baseline"):
            r = res[method]
            lines.append(
                f"| {name} | {method} | "
                + " | ".join(f"{r[c]:.4f}" if c != "normal_degrees" else f"{r[c]:.1f}" for c in MAP_COLUMNS)
                + " |"
            )
    lines += ["", *reading(table, net["photo_statistic"])]
    cmd = f"tools/model_card.py {run} {count}" + options
    lines += [
        "",
        f"Scored in {seconds:.0f} s with `.venv/bin/python {cmd}`. Its 1-light networks row, and the 1-light "
        "networks row of the table below, are reproduced by `MATSCAN_SLOW=1 .venv/bin/python -m pytest "
        "tests/test_card_rows.py` (the second alone runs in `make test`).",
        "",
    ]
    lines += kept_unlike(old_card, weights)
    CARD.write_text("\n".join(lines))
    print("\n".join(lines[-len(table) * 2 - 4 :]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
