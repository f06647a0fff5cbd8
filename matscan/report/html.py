"""``report.html``: one self-contained page a person opens after a reconstruction.

It shows each input photo beside its re-rendering from the maps under the same
light, with an error heat map and the per-light RMSE; the maps; the numbers
(timings, leave-out error, warnings); and a relighting viewer (WebGL, the paper's
Eq. 1 in a fragment shader, ``viewer.js``) in which you drag a light over the
material. Images are embedded as PNG data; nothing is fetched from the network.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any
from urllib.parse import quote

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from matscan.atomic import write_text
from matscan.capture import Capture
from matscan.color import linear_to_srgb
from matscan.jsonfile import dumps
from matscan.mapset import MapSet
from matscan.render import render_maps
from matscan.report.sheet import to_display

HERE = Path(__file__).parent
DISPLAY = 256  # longest side of the images shown per light
VIEWER = 1024  # longest side of the viewer's textures


def _png_uri(display: np.ndarray, kind: str = "png") -> str:
    """(H, W, 3) display values in [0, 1] → a PNG (or, for photos, JPEG) data URI."""
    arr = np.rint(np.clip(display, 0, 1) * 255).astype(np.uint8)[:, :, ::-1]
    ext, params = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 92]) if kind == "jpeg" else (".png", [])
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(arr), params)
    assert ok
    mime = "image/jpeg" if kind == "jpeg" else "image/png"
    return f"data:{mime};base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _shrink(t: Tensor, longest: int) -> Tensor:
    h, w = t.shape[-2:]
    if max(h, w) <= longest:
        return t
    s = longest / max(h, w)
    return F.interpolate(t[None], size=(max(1, round(h * s)), max(1, round(w * s))), mode="area")[0]


def heat(err: Tensor, top: float) -> np.ndarray:
    """(H, W) error → (H, W, 3) colours: black, red, yellow, white at ``top`` and above."""
    x = (err / max(top, 1e-6)).clamp(0, 1).numpy()
    return np.stack([np.clip(3 * x, 0, 1), np.clip(3 * x - 1, 0, 1), np.clip(3 * x - 2, 0, 1)], axis=-1)


def per_light_rows(capture: Capture, maps: MapSet, scale: float) -> tuple[list[dict[str, Any]], float]:
    """Photo, re-rendering and error of every input, at display size; and the overall RMSE."""
    rows, total, count = [], 0.0, 0
    for i, file in enumerate(capture.files):
        img = torch.empty(3, *capture.size)  # one photo and its rendering at a time, made a band at a time
        photo = torch.empty(3, *capture.size)
        sq, n = 0.0, 0
        light = capture.lights.select([i])
        for band_rows in capture.strips(1):
            r = slice(*band_rows)
            with torch.no_grad():
                band = render_maps(maps, light, capture.field_mm, scale, band_rows, compile=False)[0]
            img[:, r] = band.clamp(0, 1)
            photo[:, r] = capture.linear([i], band_rows)[0]
            ok = ~capture.saturation([i], band_rows)[0].expand_as(band)
            diff = (img[:, r] - photo[:, r])[ok]
            sq += float(diff.square().sum())
            n += diff.numel()
        rmse = (sq / n) ** 0.5 if n else float("nan")
        total += sq
        count += n
        small_img, small_photo = _shrink(img, DISPLAY), _shrink(photo, DISPLAY)  # what the page shows
        err = (linear_to_srgb(small_img) - linear_to_srgb(small_photo)).abs().mean(0)
        rows.append(
            {
                "file": file,
                "light": capture.light_indices[i],
                "rmse": rmse,
                "photo": _png_uri(to_display(small_photo), "jpeg"),
                "render": _png_uri(to_display(small_img), "jpeg"),
                "error": _png_uri(heat(err, 0.1)),
            }
        )
    return rows, (total / max(count, 1)) ** 0.5


def _viewer_textures(maps: MapSet) -> dict[str, str]:
    """The viewer's textures; a material without emission or holes gets black emission and
    alpha 1 (constant images, a few bytes as PNG), so the shader has one path."""
    h, w = maps.size
    emissive = maps.emissive if maps.emissive is not None else torch.zeros(3, h, w)
    alpha = maps.alpha if maps.alpha is not None else torch.ones(1, h, w)
    out = {}
    for name, t, kind in (
        ("diffuse", maps.diffuse, "srgb"),
        ("specular", maps.specular, "srgb"),
        ("roughness", maps.roughness, "grey"),
        ("normal", maps.normal, "normal"),
        ("emissive", emissive, "srgb"),
        ("alpha", alpha, "grey"),
    ):
        out[name] = _png_uri(to_display(_shrink(t, VIEWER), kind))
    return out


def _map_files(maps: MapSet) -> list[str]:
    """The map files :func:`matscan.mapset.write_maps` writes for these maps (PNG)."""
    return [f"{name}.png" for name in maps.present()] + ["mapset.json"]


def write_report(
    path: Path,
    capture: Capture,
    maps: MapSet,
    record: dict[str, Any],
    scale: float = 1.0,
    confidence: dict[str, Tensor] | None = None,
    light_rows: tuple[list[dict[str, Any]], float] | None = None,
) -> None:
    """Write ``report.html`` (see module doc); ``confidence``: a (1, H, W) map in [0, 1]
    per map, shown beside the maps (white: the photos determined it; black: the prior);
    ``light_rows``: :func:`per_light_rows` when the caller has made them already."""
    rows, overall = light_rows if light_rows is not None else per_light_rows(capture, maps, scale)
    e = html.escape
    left_out = set(record.get("validation", {}).get("left_out", []))
    table = "\n".join(
        f"<tr><td>{e(r['file'])}{'<br>(left out of the validation)' if r['file'] in left_out else ''}</td>"
        f"<td>{'' if r['light'] is None else r['light']}</td>"
        f"<td><img src='{r['photo']}' alt='photo'></td><td><img src='{r['render']}' alt='re-rendering'></td>"
        f"<td><img src='{r['error']}' alt='error'></td><td>{r['rmse']:.4f}</td></tr>"
        for r in rows
    )
    kinds = {"diffuse": "srgb", "specular": "srgb", "basecolor": "srgb", "emissive": "srgb", "normal": "normal"}
    map_cells = []
    for name, t in maps.present().items():
        if name == "height":
            lo, hi = float(t.min()), float(t.max())
            t = (t - lo) / (hi - lo) if hi > lo else torch.zeros_like(t)
            label = f"height ({lo:.3f} to {hi:.3f} mm)"
        else:
            label = name
        uri = _png_uri(to_display(_shrink(t, DISPLAY), kinds.get(name, "grey")))
        map_cells.append(f"<figure><img src='{uri}' alt='{name}'><figcaption>{e(label)}</figcaption></figure>")
    for name, t in (confidence or {}).items():
        uri = _png_uri(to_display(_shrink(t, DISPLAY), "grey"))
        label = f"{name} confidence (mean {float(t.mean()):.2f})"
        map_cells.append(f"<figure><img src='{uri}' alt='{e(label)}'><figcaption>{e(label)}</figcaption></figure>")
    numbers = {
        "rig": record.get("rig"),
        "size (px)": record.get("size_px"),
        "mm per pixel": [round(v, 4) for v in record.get("mm_per_pixel", [])],
        "calibration": record.get("calibration") or "none",
        "model": record.get("model", {}).get("name"),
        "maps started from": record.get("start"),
        "refined": record.get("refined"),
        "re-rendering RMSE (all inputs)": round(overall, 5),
        "intensity scale": round(scale, 4),
        "timings (s; the total, written last, is in matscan.json)": record.get("timings_s"),
    }
    if record.get("start") == "any-rig network" and record.get("model", {}).get("anyrig_file"):
        numbers["any-rig network"] = record["model"]["anyrig_file"]
    if "validation" in record:
        v = record["validation"]
        numbers["validation: photos left out of a second fit"] = ", ".join(v["left_out"])
        numbers["validation: re-rendering RMSE, left out / fitted"] = (
            f"{v['rmse_left_out']:.5f} / {v['rmse_fitted']:.5f}"
        )
        numbers["validation: left out, as displayed (sRGB)"] = (
            f"PSNR {v['psnr_left_out']:.2f} dB, SSIM {v['ssim_left_out']:.3f}"
        )
        if "hsh" in v:
            numbers["validation: an HSH fit (order 2) to the same photos"] = (
                f"PSNR {v['hsh']['psnr_left_out']:.2f} dB, SSIM {v['hsh']['ssim_left_out']:.3f}"
            )
    numbers_html = "\n".join(
        f"<tr><th>{e(k)}</th><td>{e(v if isinstance(v, str) else json.dumps(v))}</td></tr>" for k, v in numbers.items()
    )
    warnings = "".join(f"<li>{e(w)}</li>" for w in record.get("warnings", [])) or "<li>none</li>"
    cam = capture.rig.camera_point if not capture.rig.per_image_geometry else tuple(capture.lights.camera[0].tolist())
    viewer_cfg = {
        "field_mm": list(capture.field_mm),
        "camera_mm": list(cam),
        "camera_w": capture.rig.camera_w,
        "R": capture.rig.reference_distance_mm,
        "textures": _viewer_textures(maps),
    }
    exports = record.get("exports", [])
    inside = {  # a folder export's files (exr/): written by now, beside this page
        p.relative_to(path.parent).as_posix()
        for folder in exports
        if folder.endswith("/")
        for p in (path.parent / folder).rglob("*")
        if p.is_file()
    }
    files = sorted(
        {*(f for f in exports if not f.endswith("/")), *_map_files(maps), *inside}
        | {entry["file"] for entry in record.get("confidence", {}).values()}
        | {"matscan.json"}
    )
    files_html = "\n".join(f"<li><a href='{quote(f)}'>{e(f)}</a></li>" for f in files)
    conventions_html = "\n".join(
        f"<tr><th>{e(k)}</th><td>{e(str(v))}</td></tr>" for k, v in record.get("conventions", {}).items()
    )
    name = capture.folder.name if capture.folder is not None else str(record.get("capture", ""))
    page = (HERE / "template.html").read_text(encoding="utf-8")
    page = (
        page.replace("{{TITLE}}", e(f"matscan report: {name}"))
        .replace("{{FILES}}", files_html)
        .replace("{{CONVENTIONS}}", conventions_html)
        .replace("{{NUMBERS}}", numbers_html)
        .replace("{{WARNINGS}}", warnings)
        .replace("{{MAPS}}", "\n".join(map_cells))
        .replace("{{LIGHTS}}", table)
        .replace("{{VIEWER_CONFIG}}", dumps(viewer_cfg, "report viewer", indent=None))
        .replace("{{VIEWER_JS}}", (HERE / "viewer.js").read_text(encoding="utf-8"))
    )
    write_text(path, page)
