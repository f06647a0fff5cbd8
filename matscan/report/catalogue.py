"""The batch catalogue: ``DIR/index.html``, every material of a ``matscan batch`` on one page.

One row per capture: thumbnails of its diffuse, normal, roughness and specular maps and a
relit preview (the maps rendered under one light from the upper left, 45° up), its
re-rendering error (and the leave-out validation's, when the batch ran one), mean
confidence, warnings, and links to its report and exports; failed captures with their
error; pending ones as such. Thumbnails are small PNG files under ``DIR/thumbs/``, so the
page stays light with hundreds of materials and works offline from the folder. The table
sorts by name, error or warnings and filters by name, largest error and whether there are
warnings; the same settings can be given in the page's address (``?sort=error&desc=1&
name=leather&max_error=0.01&warnings=with``), which is how the tests drive it.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any
from urllib.parse import quote

import torch

from matscan.atomic import write_text

THUMB = 128
MAPS = ("diffuse", "normal", "roughness", "specular")
EXPORTS = ("report.html", "material.glb", "material.gltf", "material.mtlx", "material.usdz", "matscan.json")


def _thumbs(out: Path, name: str) -> dict[str, str]:
    """Write (once) and name the thumbnails of a finished capture's maps."""
    from matscan.color import linear_to_srgb
    from matscan.imagefile import write_image
    from matscan.mapset import read_mapset
    from matscan.render import render_maps
    from matscan.rig import LightSet

    folder = out / "thumbs"
    files = {m: f"thumbs/{name}_{m}.png" for m in (*MAPS, "relit")}
    if all((out / f).is_file() for f in files.values()):
        return files
    folder.mkdir(exist_ok=True)
    maps = read_mapset(out / name)
    h, w = maps.size
    scale = THUMB / max(h, w)
    size = (max(1, round(h * scale)), max(1, round(w * scale)))
    small = {k: torch.nn.functional.interpolate(v[None], size=size, mode="area")[0] for k, v in maps.present().items()}
    small["normal"] = small["normal"] / small["normal"].norm(dim=0, keepdim=True).clamp_min(1e-8)
    from matscan.mapset import MapSet

    thumbs = MapSet(**small)
    record = json.loads((out / name / "matscan.json").read_text(encoding="utf-8"))
    field = record.get("field_mm", [120.0, 120.0])
    reach = max(field) / 2
    light = LightSet.points([(-reach, reach, reach * math.sqrt(2))], (0.0, 0.0, 4 * reach), 2 * reach)
    relit = render_maps(thumbs, light, field)[0].clamp(0, 1)
    images = {
        "diffuse": linear_to_srgb(thumbs.diffuse.clamp(0, 1)),
        "normal": (thumbs.normal + 1) / 2,
        "roughness": thumbs.roughness.expand(3, -1, -1),
        "specular": linear_to_srgb(thumbs.specular.clamp(0, 1)),
        "relit": linear_to_srgb(relit),
    }
    for key, img in images.items():
        write_image(out / files[key], img.permute(1, 2, 0).numpy(), bits=8)
    return files


def _row(out: Path, name: str, entry: dict[str, Any]) -> str:
    e = html.escape
    state = entry.get("state", "pending")
    error = entry.get("rerender_rmse")
    validation = entry.get("validation", {}).get("rmse_left_out")
    warnings = entry.get("warnings", [])
    confidence = entry.get("confidence", {})
    cells = [f"<td class='name'>{e(name)}<div class='capture'>{e(entry.get('capture', ''))}</div></td>"]
    if state == "done":
        thumbs = _thumbs(out, name)
        cells.append(
            "<td class='thumbs'>"
            + "".join(
                f"<figure><img src='{quote(thumbs[m])}' alt='{e(name)} {m}' loading='lazy'><figcaption>{m}</figcaption>"
                "</figure>"
                for m in ("relit", *MAPS)
            )
            + "</td>"
        )
        error_text = f"{error:.4f}" + (f"<div class='sub'>left out {validation:.4f}</div>" if validation else "")
        conf = ", ".join(f"{k} {v:.2f}" for k, v in confidence.items()) or "–"
        links = " · ".join(
            f"<a href='{quote(name)}/{quote(f)}'>{e(f)}</a>" for f in EXPORTS if (out / name / f).is_file()
        )
        cells += [
            f"<td class='error'>{error_text}</td>",
            f"<td>{e(conf)}</td>",
            f"<td class='warnings'>{'<br>'.join(e(w) for w in warnings) or '–'}</td>",
            f"<td>{links}</td>",
        ]
    elif state == "failed":
        cells += [
            "<td class='thumbs'></td>",
            "<td class='error'>failed</td>",
            "<td>–</td>",
            f"<td class='warnings'>{e(entry.get('error', ''))}</td>",
            "<td></td>",
        ]
    else:
        cells += ["<td class='thumbs'></td>", "<td class='error'>pending</td>", "<td>–</td>", "<td>–</td>", "<td></td>"]
    sort_error = error if state == "done" else math.inf
    n_warn = len(warnings) if state == "done" else (1 if state == "failed" else 0)
    sort_value = sort_error if math.isfinite(sort_error) else 1e9  # failed and pending sort last
    attrs = f"data-name='{e(name.lower())}' data-state='{state}' data-error='{sort_value}' data-warnings='{n_warn}'"
    return f"<tr {attrs}>{''.join(cells)}</tr>"


def write_catalogue(out: Path, manifest: dict[str, Any]) -> Path:
    """Write ``out/index.html`` from a batch manifest (module doc)."""
    entries = manifest.get("captures", {})
    rows = "\n".join(_row(out, name, entry) for name, entry in sorted(entries.items()))
    counts = {s: sum(1 for v in entries.values() if v.get("state") == s) for s in ("done", "failed", "pending")}
    page = (Path(__file__).with_name("catalogue.html")).read_text(encoding="utf-8")
    page = (
        page.replace("{{TITLE}}", html.escape(f"matscan catalogue: {out.resolve().name}"))
        .replace("{{ROWS}}", rows)
        .replace(
            "{{COUNTS}}", html.escape(f"{counts['done']} done, {counts['failed']} failed, {counts['pending']} pending")
        )
    )
    write_text(out / "index.html", page)
    return out / "index.html"
