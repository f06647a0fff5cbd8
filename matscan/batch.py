"""``matscan batch``: many captures reconstructed with the same settings, on Dask.

Captures are given as folders, glob patterns, or text files listing them (one per line;
``#`` starts a comment). Each is reconstructed by :func:`matscan.reconstruct.job.reconstruct`
into ``DIR/<name>/`` (the capture folder's name, made unique), atomically as always, on a
Dask cluster: a local one sized to the machine by default (one worker process per core,
``workers`` to choose; torch threads per worker = cores // workers, so workers never
oversubscribe the cores), or an existing one (``scheduler``: its address), so the same
command runs on a laptop or on many machines. Needs the ``batch`` extra
(``dask[distributed]``).

``DIR/manifest.json`` records the settings and each capture's state: ``done`` (with its
output, time, re-rendering error, warnings), ``failed`` (with the one-line error) or
``pending``. Running the command again skips what is done, runs what is pending, and
retries what failed only with ``retry_failed``; a finished output is recomputed only with
``redo``; other settings than the manifest's are refused. One bad capture never stops
the batch. ``DIR/index.html`` is the catalogue (:mod:`matscan.report.catalogue`),
rewritten as results arrive.
"""

from __future__ import annotations

import glob
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from matscan.atomic import output_lock, write_text
from matscan.errors import MatscanError, input_error
from matscan.jsonfile import dumps, read_json

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "matscan-batch/1"
STATES = ("pending", "done", "failed")


def expand_captures(specs: Sequence[str]) -> list[Path]:
    """Capture folders from folders, glob patterns and list files, in order, each once."""
    out: list[Path] = []
    for spec in specs:
        path = Path(spec)
        if path.is_file() and path.name != "capture.json":
            try:
                lines = path.read_text(encoding="utf-8-sig").splitlines()
            except UnicodeDecodeError:
                raise input_error(path, "is a file but not a text list of capture folders (not UTF-8)") from None
            except OSError as exc:
                raise input_error(path, f"cannot read it ({exc.strerror})") from None
            entries = [ln.split("#", 1)[0].strip() for ln in lines]
            found = [(path.parent / e if not Path(e).is_absolute() else Path(e)) for e in entries if e]
        elif any(c in spec for c in "*?["):
            found = [Path(p) for p in sorted(glob.glob(spec)) if Path(p).is_dir()]
            if not found:
                raise MatscanError(f"{spec}: matches no folder")
        else:
            found = [path]
        for f in found:
            if not (f / "capture.json").is_file():
                raise input_error(f, "is not a capture folder (no capture.json)")
            if f.resolve() not in {p.resolve() for p in out}:
                out.append(f)
    if not out:
        raise MatscanError("batch: no captures given")
    return out


#: Names in a batch folder that are the batch's own, never a capture's output.
RESERVED = frozenset({"thumbs", "index.html", MANIFEST})


def output_names(captures: Sequence[Path]) -> list[str]:
    """A unique output folder name per capture: its folder's name (without leading dots:
    a hidden output would hide from the catalogue), then -2, -3, … (also where the name is
    one of the batch's own, ``RESERVED``)."""
    names: list[str] = []
    for c in captures:
        base = c.resolve().name.lstrip(".") or "capture"
        name, k = base, 2
        while name in names or name in RESERVED:
            name, k = f"{base}-{k}", k + 1
        names.append(name)
    return names


def cluster_shape(workers: int | None, cores: int | None = None) -> tuple[int, int]:
    """(workers, torch threads per worker) for a local cluster on ``cores`` cores: one
    worker per core by default, and the cores shared out so none is oversubscribed."""
    cores = cores or os.cpu_count() or 1
    n = cores if workers is None else max(1, workers)
    return n, max(1, cores // n)


def reconstruct_one(capture: str, out: str, cfg: dict[str, Any], threads: int) -> dict[str, Any]:
    """One capture on a worker: the reconstruction's summary, or its one-line error."""
    import torch

    from matscan.reconstruct.job import ReconstructConfig, reconstruct
    from matscan.reconstruct.lm import SolverConfig

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    try:
        config = ReconstructConfig(**{**cfg, "lm": SolverConfig(**cfg["lm"])})
        rec = reconstruct(capture, out, config, overwrite=True)
    except MatscanError as exc:
        return {"state": "failed", "error": " ".join(str(exc).split()), "seconds": round(time.perf_counter() - t0, 2)}
    except Exception as exc:  # a bug must not stop the batch either; it is reported with its type
        return {
            "state": "failed",
            "error": f"{type(exc).__name__}: {exc}",
            "seconds": round(time.perf_counter() - t0, 2),
        }
    summary = {
        "state": "done",
        "seconds": round(time.perf_counter() - t0, 2),
        "rerender_rmse": rec["rerender_rmse"],
        "warnings": rec["warnings"],
        "size_px": rec["size_px"],
        "refined": rec["refined"],
    }
    if "validation" in rec:
        summary["validation"] = {k: v for k, v in rec["validation"].items() if k != "left_out"}
    if rec.get("confidence"):
        summary["confidence"] = {k: v["mean"] for k, v in rec["confidence"].items()}
    return summary


def batch(
    captures: Sequence[str],
    out: str | Path,
    cfg=None,
    workers: int | None = None,
    scheduler: str | None = None,
    threads: int | None = None,
    retry_failed: bool = False,
    redo: bool = False,
    progress: bool = False,
    on_result: Callable[[str, dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """``matscan batch`` (module doc). Returns the manifest."""
    from matscan.reconstruct.job import ReconstructConfig
    from matscan.weights import load_anyrig, load_model, model_path

    if workers is not None and scheduler:
        raise MatscanError("--workers: a scheduler has its own workers; give --workers or --scheduler, not both")
    cfg = cfg or ReconstructConfig()
    if cfg.model != "none":  # read before any work: a damaged file would fail every capture, one by one
        if not (weights := model_path(cfg.model)).is_file():
            raise input_error(weights, "no such weights file")
        load_model(cfg.model)
    if cfg.anyrig != "none":
        load_anyrig(cfg.anyrig)
    if cfg.calibration is not None:  # one bad file would fail every capture, one by one
        from matscan.calibrate import check_calibration_file

        check_calibration_file(cfg.calibration)
    paths = expand_captures(captures)
    names = output_names(paths)
    out = Path(out)
    from matscan.outputs import check_utf8

    check_utf8(out, *paths)  # the manifest and catalogue record them
    where = out.resolve()
    for path in paths:  # a batch folder resumes, never replaces: only in a capture is it refused
        if where == path.resolve() or path.resolve() in where.parents:
            how = "is" if where == path.resolve() else "lies inside"
            raise input_error(out, f"{how} the input capture {path}; matscan never writes into its inputs")
    settings = json_safe(asdict(cfg))
    created = not out.exists()
    with output_lock(out):
        try:
            return _batch(
                out, paths, names, settings, workers, scheduler, threads, retry_failed, redo, progress, on_result
            )
        except MatscanError:
            if (
                created
                and out.is_dir()
                and not any(e["state"] != "pending" for e in _manifest_or_empty(out).get("captures", {}).values())
            ):  # a batch that could not start (an unreachable scheduler) leaves nothing behind
                shutil.rmtree(out, ignore_errors=True)
            raise


def _manifest_or_empty(out: Path) -> dict[str, Any]:
    try:
        return read_json(out / MANIFEST)
    except MatscanError:
        return {}


def _batch(out, paths, names, settings, workers, scheduler, threads, retry_failed, redo, progress, on_result):
    """:func:`batch` once its output is locked."""
    manifest = _open_manifest(out, settings)
    entries = manifest["captures"]
    for name, path in zip(names, paths, strict=True):
        entry = entries.get(name)
        if entry is None or entry["capture"] != str(path.resolve()):
            entries[name] = {"capture": str(path.resolve()), "state": "pending"}
        elif redo or (retry_failed and entry["state"] == "failed"):
            entries[name] = {"capture": str(path.resolve()), "state": "pending"}
        elif entry["state"] == "done" and not (out / name / "matscan.json").is_file():
            entries[name] = {"capture": str(path.resolve()), "state": "pending"}
    todo = [n for n in names if entries[n]["state"] == "pending"]
    _save(out, manifest)
    if todo:
        _run(out, manifest, todo, settings, workers, scheduler, threads, progress, on_result)
    from matscan.report.catalogue import write_catalogue

    write_catalogue(out, manifest)
    return manifest


def json_safe(obj: Any) -> Any:
    """``obj`` as it reads back from JSON (tuples become lists), so settings compare."""
    import json

    return json.loads(dumps(obj, "settings"))


def _as_now(settings: Any) -> Any:
    """A manifest's settings as this version writes the same ones: before ``shared_f0``
    could be None (follow ``lightpos.SHARED_F0``) a batch without the positions' fit wrote
    False, the same settings (with the fit, False was each pixel's own F0: ``--own-f0``);
    before ``calibration`` there was none to name."""
    if isinstance(settings, dict) and "calibration" not in settings:  # before --calibration: none
        settings = {**settings, "calibration": None}
    if not isinstance(settings, dict) or settings.get("self_calibrate_positions"):
        return settings
    if settings.get("shared_f0") is False:
        return {**settings, "shared_f0": None}
    return settings


def _open_manifest(out: Path, settings: dict[str, Any]) -> dict[str, Any]:
    path = out / MANIFEST
    if path.exists():
        manifest = read_json(path)
        if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
            raise input_error(path, f"is not a {MANIFEST_FORMAT} manifest")
        _check_entries(manifest, path)
        if _as_now(manifest.get("settings")) != settings:
            raise input_error(
                path,
                "was made with other reconstruction settings; use another --out, or the same settings "
                "(a changed setting would mix maps made two ways in one catalogue)",
            )
        return manifest
    if out.exists() and any(p for p in out.iterdir() if not p.name.startswith(".")):
        raise input_error(out, "exists and is not a matscan batch folder; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    return {"format": MANIFEST_FORMAT, "settings": settings, "captures": {}}


#: A capture's states in a manifest.
STATES = ("pending", "done", "failed")


def _check_entries(manifest: dict[str, Any], path: Path) -> None:
    """A manifest's captures as the batch and its catalogue read them; errors name the
    file and the entry."""
    from matscan.jsonfile import check_object, check_string

    for name, entry in check_object(manifest.get("captures"), f"{path}: captures").items():
        where = f"{path}: captures.{name}"
        check_object(entry, where)
        check_string(entry.get("capture"), f"{where}.capture")
        check_string(entry.get("state"), f"{where}.state", STATES)
        for key, kind in (("validation", dict), ("confidence", dict), ("warnings", list)):
            if key in entry and not isinstance(entry[key], kind):
                raise input_error(path, f"captures.{name}.{key}: expected {'an object' if kind is dict else 'a list'}")
        if entry["state"] == "done" and not isinstance(entry.get("rerender_rmse"), (int, float)):
            raise input_error(path, f"captures.{name}.rerender_rmse: expected a number for a finished capture")


def _save(out: Path, manifest: dict[str, Any]) -> None:
    write_text(out / MANIFEST, dumps(manifest, str(out / MANIFEST)))


def _run(out, manifest, todo, settings, workers, scheduler, threads, progress, on_result) -> None:
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise MatscanError("batch: needs Dask: pip install 'matscan[batch]'") from None
    from tqdm import tqdm

    entries = manifest["captures"]
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as exc:
            raise MatscanError(f"--scheduler: cannot reach {scheduler} ({exc})") from None
        cluster = None
        threads = threads or 1  # a cluster's machines are not ours to count: one thread per task unless told
    else:
        n, local_threads = cluster_shape(workers)
        threads = threads or local_threads
        cluster = LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
        )
        client = Client(cluster)
    try:
        futures = {}
        for name in todo:
            fut = client.submit(
                reconstruct_one, entries[name]["capture"], str(out / name), settings, threads, key=f"matscan-{name}"
            )
            futures[fut] = name
        with tqdm(total=len(todo), desc="batch", unit="capture", disable=not progress) as bar:
            for fut in as_completed(futures):
                name = futures[fut]
                try:
                    result = fut.result()
                except Exception as exc:  # a worker that died
                    result = {"state": "failed", "error": f"the worker failed: {type(exc).__name__}: {exc}"}
                entries[name].update(result)
                if result["state"] == "done":
                    entries[name]["output"] = name
                _save(out, manifest)
                from matscan.report.catalogue import write_catalogue

                write_catalogue(out, manifest)
                if on_result is not None:
                    on_result(name, result)
                bar.update(1)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
