"""Where a command may write: every output checked before the work, never an input.

A command claims its output first (:func:`claim_output`), before it reads photos
or computes anything:

- the output must not be, contain, or lie inside any of the command's inputs
  (capture folder and every file its ``capture.json`` names, map set, calibration
  file, weights file), nor be the current folder or one holding it;
- a file that a ``capture.json`` beside it lists (or that ``capture.json`` itself),
  any existing file or folder inside a capture folder (one holding ``capture.json``, at
  any depth), and an RTI light file (``.lp``) whose photos lie beside it are never
  replaced, whatever the flags;
- a folder holding a capture (a ``capture.json`` in it or below it) is replaced only by
  the command that wrote it (its ``matscan.json`` says which: ``simulate`` over a
  simulated capture, ``import-rti`` over an imported one, ``synth`` over a synth set),
  and only when that record lists every capture there (:func:`captures_not_its_own`),
  whatever the flags: ``--overwrite`` never turns a capture into another output;
- a path that is not valid UTF-8 is refused (:func:`check_utf8`): records hold paths;
- an existing folder is replaced only with ``--overwrite``, and only when it holds
  nothing but a previous matscan output (every file listed in its ``matscan.json``,
  :func:`foreign_entries`), unless ``--overwrite-any`` is given too; an existing
  file is replaced only with ``--overwrite``;
- the nearest existing folder above it must be a writable folder, the name short
  enough for the file system with room for a temporary name, and (once the input
  size is known, :meth:`OutputClaim.check_space`) the free space plausible;
- the output is locked for the rest of the command, so a second writer fails at
  once, and stale temporaries of killed writers are removed; folders made for an
  output that the command then fails to write are removed again.

Then :meth:`OutputClaim.folder` / :meth:`OutputClaim.file` write it atomically
(:mod:`matscan.atomic`). Every refusal is one :class:`MatscanError` line.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath
from typing import Any

from matscan.atomic import TMP_NAME_EXTRA, atomic_file, atomic_folder, clean_stale, held, output_lock
from matscan.errors import MatscanError, input_error
from matscan.jsonfile import dumps

RECORD = "matscan.json"
OUTPUT_FORMAT = "matscan-output/1"
#: What a matscan reconstruction wrote before its ``matscan.json`` listed its files.
_LEGACY_OUTPUT_NAMES = {
    "matscan.json",
    "mapset.json",
    "report.html",
    "material.gltf",
    "material.mtlx",
    "normal_directx.png",
}
_LEGACY_MAP_STEMS = {
    "diffuse",
    "specular",
    "roughness",
    "normal",
    "alpha",
    "metallic",
    "basecolor",
    "emissive",
    "height",
    "base_color",
    "metallic_roughness",
    "specular_color",
}


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def _resolve(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError) as exc:  # symlink loops
        raise input_error(path, f"cannot resolve this path ({exc})") from None
    except ValueError:  # an embedded NUL byte
        raise MatscanError(f"{str(path)!r} is not a usable path (it holds a NUL byte)") from None


def capture_inputs(folder: str | Path) -> list[Path]:
    """The capture folder and every file its ``capture.json`` names (rig, calibration,
    photos, backlight): what a command reading it must never write over. A
    malformed ``capture.json`` gives just the folder (reading it reports the fault)."""
    folder = Path(folder)
    found = [folder]
    try:
        doc = json.loads((folder / "capture.json").read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError):
        return found
    if not isinstance(doc, dict):
        return found
    names: list[Any] = []
    images = doc.get("images")
    if isinstance(images, list):
        names += [e.get("file") for e in images if isinstance(e, dict)]
    if isinstance(doc.get("backlight"), dict):
        names += list(doc["backlight"].values())
    names.append(doc.get("rig"))
    for name in names:
        if isinstance(name, str) and name and "\x00" not in name:
            found.append(folder / name)
    cal = doc.get("calibration")
    if isinstance(cal, str) and cal and "\x00" not in cal:
        found += calibration_inputs(folder / cal)
    elif isinstance(cal, dict):  # an inline calibration: its flat fields are relative to the capture
        found += _flat_inputs(cal, folder)
    return found


def calibration_inputs(path: Path) -> list[Path]:
    """A calibration file and the flat fields it names (beside it): inputs too. An
    unreadable or malformed file gives just itself (reading it reports the fault)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError):
        return [path]
    return [path, *_flat_inputs(doc, path.parent)]


def _flat_inputs(cal: Any, base: Path) -> list[Path]:
    flats = cal.get("flat_fields", {}) if isinstance(cal, dict) else {}
    if not isinstance(flats, dict):
        return []
    return [base / f for f in flats.values() if isinstance(f, str) and f and "\x00" not in f]


def _capture_files_here(path: Path) -> set[str]:
    """Names a ``capture.json`` in ``path``'s folder lists (and ``capture.json``)."""
    manifest = path.parent / "capture.json"
    if not manifest.is_file():
        return set()
    return {p.name for p in capture_inputs(path.parent)[1:] if p.parent == path.parent} | {"capture.json"}


def capture_above(path: Path) -> Path | None:
    """The nearest folder above ``path`` that holds a ``capture.json`` (a capture that
    ``path`` lies in), or None."""
    for folder in path.parents:
        if (folder / "capture.json").is_file():
            return folder
    return None


def _captures_within(folder: Path) -> list[str]:
    """The ``capture.json`` files in ``folder`` or below it (relative paths)."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("capture.json"))


def _listed_files(folder: Path) -> set[str] | None:
    """The files the ``matscan.json`` in ``folder`` lists as its output's (None where it
    lists none: no record, an unreadable one, or one written before records listed them)."""
    try:
        record = json.loads((folder / RECORD).read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError):
        return None
    listed = record.get("files") if isinstance(record, dict) else None
    return {f for f in listed if isinstance(f, str)} if isinstance(listed, list) else None


def captures_not_its_own(folder: Path, command: str | None) -> list[str]:
    """The captures in ``folder`` or below it (their ``capture.json``, relative) that are
    not part of a previous output of ``command`` there: all of them unless its
    ``matscan.json`` says ``command`` wrote the folder, and then each one its record does
    not list (one put there since; where the record lists no files, every capture but
    the folder's own)."""
    held = _captures_within(folder)
    if not held or command is None or _written_by(folder) != command:
        return held
    listed = _listed_files(folder)
    if listed is None:
        return [c for c in held if c != "capture.json"]
    return [c for c in held if c not in listed]


def _written_by(folder: Path) -> str | None:
    """The command a ``matscan.json`` in ``folder`` says wrote it (None where none says)."""
    try:
        record = json.loads((folder / RECORD).read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError):
        return None
    command = record.get("command") if isinstance(record, dict) else None
    return command if isinstance(command, str) else None


def _lp_files_beside(path: Path) -> list[Path]:
    """The RTI light files (``.lp``) beside ``path`` that list at least one photo there."""
    try:
        return sorted(p for p in path.parent.glob("*") if p.suffix.lower() == ".lp" and _rti_photos_beside(p))
    except OSError:
        return []


def _owned_here(path: Path) -> str | None:
    """What ``path`` belongs to, if a record beside it claims it: an RTI capture (an
    ``.lp`` there lists it) or a map set (``mapset.json`` there, or a map it lists); else
    None."""
    for lp in _lp_files_beside(path):
        if path.name in _rti_photos_beside(lp):
            return f"is a photo of the RTI capture in {path.parent} (listed in {lp.name})"
    manifest = path.parent / "mapset.json"
    if manifest.is_file():
        if path.name == "mapset.json":
            return f"is the record of the map set in {path.parent}"
        try:
            listed = json.loads(manifest.read_text(encoding="utf-8")).get("files", {})
            names = {entry.get("file") for entry in listed.values() if isinstance(entry, dict)}
        except (OSError, ValueError, AttributeError):
            names = set()
        if path.name in names:
            return f"is a map of the map set in {path.parent}"
    return None


def _rti_photos_beside(path: Path) -> list[str]:
    """The photos beside ``path`` that it lists, if it is an RTI light file (``.lp``: a
    'FILE x y z' line per photo); empty otherwise."""
    if path.suffix.lower() != ".lp" or not path.is_file():
        return []
    try:
        if path.stat().st_size > 2**20:
            return []
        raw = path.read_bytes()
    except OSError:
        return []
    try:
        lines = raw.decode("utf-8-sig").splitlines()
    except UnicodeDecodeError:  # as matscan.capture.rti.read_lp reads it
        lines = raw.decode("cp1252", errors="replace").splitlines()
    found = []
    for line in lines:
        parts = line.split()
        if len(parts) >= 4 and not parts[0].startswith("#"):
            name = " ".join(parts[:-3])
            base = PureWindowsPath(name).name if "\\" in name else Path(name).name  # as parse_lp reads it
            if "\x00" not in base and base and (path.parent / base).is_file():
                found.append(base)
    return found


def foreign_entries(folder: Path) -> list[str]:
    """Files in ``folder`` (relative paths) that no ``matscan.json`` there says matscan
    wrote; empty for a previous matscan output. A folder without a readable
    ``matscan.json`` is all foreign."""
    entries = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir())
    try:
        record = json.loads((folder / RECORD).read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError):
        return entries
    if not isinstance(record, dict):
        return entries
    listed = record.get("files")
    if isinstance(listed, list):
        known = {f for f in listed if isinstance(f, str)} | {RECORD}
        return [e for e in entries if e not in known]
    if not str(record.get("format", "")).startswith("matscan-reconstruction/"):
        return entries
    known = set(_LEGACY_OUTPUT_NAMES) | {"material.bin", "exr/mapset.json"}
    for stem in _LEGACY_MAP_STEMS:  # an older reconstruction: exactly the names it wrote
        known |= {f"{stem}.png", f"tex_{stem}.png", f"exr/{stem}.exr"}
    return [e for e in entries if e not in known]


def write_record_files(folder: Path, command: str) -> None:
    """List every file of the finished output ``folder`` in its ``matscan.json``
    (created, with the command's name, when the command wrote none)."""
    from matscan import __version__

    path = folder / RECORD
    if path.is_file():
        record = json.loads(path.read_text(encoding="utf-8-sig"))
    else:
        record = {"format": OUTPUT_FORMAT, "command": command, "matscan_version": __version__}
    record["files"] = sorted(  # every file but this record (a nested one, synth's say, is a file of the output)
        p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir() and p != path
    )
    path.write_text(dumps(record, RECORD), encoding="utf-8")


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def check_utf8(*paths: str | Path) -> None:
    """Refuse a path that is not valid UTF-8 (a name from another system's encoding):
    matscan records paths in JSON and HTML files, which could not hold it."""
    for item in map(str, paths):
        try:
            item.encode("utf-8")
        except UnicodeEncodeError:
            name = os.fsencode(item).decode("utf-8", errors="backslashreplace")
            raise MatscanError(
                f"{name}: the path is not valid UTF-8, and matscan records paths in JSON and HTML files; rename it"
            ) from None


def check_place(
    out: str | Path, inputs: Iterable[str | Path] = (), flag: str = "--out", current_ok: bool = False
) -> tuple[Path, Path]:
    """The checks of where an output lies, whatever it replaces (:func:`check_destination`
    adds those; ``matscan capture``, which resumes its own folder, makes only these and
    its own): a usable UTF-8 path, not a symbolic link, not the root or the current
    folder (unless ``current_ok``: a training run, which never replaces its folder), not an
    input nor inside or around one. Returns the path as given and resolved."""
    text = str(out)
    if not text or "\x00" in text:
        raise MatscanError(f"{flag}: {text!r} is not a usable path")
    inputs = list(inputs)
    check_utf8(text, *inputs)
    given = Path(text)
    if given.is_symlink():
        if not given.exists():
            raise input_error(given, "is a dangling symbolic link; give a real path for the output")
        raise input_error(given, "is a symbolic link; give the real path of the output")
    path = _resolve(given)
    if path.parent == path:
        raise input_error(given, "is the root of the file system; choose a folder for the output")
    try:
        cwd = _resolve(Path.cwd())
    except FileNotFoundError:  # the current folder was deleted: nothing to protect there
        cwd = None
    if cwd is not None and _within(cwd, path) and not (current_ok and cwd == path):
        raise input_error(given, "is the current folder or holds it; choose a new folder for the output")
    for item in inputs:
        inp = _resolve(Path(item))
        if _within(path, inp) or _within(inp, path):
            how = "is" if path == inp else ("lies inside" if _within(path, inp) else "contains")
            raise input_error(
                given, f"{how} the input {item}; matscan never writes over its inputs (choose another {flag})"
            )
    return given, path


def check_run_folder(
    run: str | Path, inputs: Iterable[str | Path] = (), files: Iterable[str] = (), flag: str = "--out"
) -> Path:
    """Where a training run may write (``matscan train``, ``train-anyrig``), checked before
    anything is written: :func:`check_place`'s checks, not a capture or a map set nor in a
    capture, and no file of a run's (``config.json`` and ``files``) that is not a run's: a
    run adds and rewrites its own files in place (to resume), so a folder holding one of
    those names without a run's ``config.json`` is refused rather than written over
    (other files beside a run, its notes, are left alone). Returns the path resolved."""
    given, path = check_place(run, inputs, flag, current_ok=True)
    if (holder := capture_above(path)) is not None:
        raise input_error(given, f"lies in the capture {holder}; matscan never writes into a capture")
    if path.exists():
        if not path.is_dir():
            raise input_error(given, "exists and is not a folder")
        for name, what in (("capture.json", "a capture"), ("mapset.json", "a map set")):
            if (path / name).is_file():
                raise input_error(given, f"is {what} folder; a training run needs a folder of its own ({flag})")
        if not (path / "config.json").is_file():
            found = [name for name in files if (path / name).exists()]
            if found:
                raise input_error(
                    given,
                    f"holds {found[0]} but no training run (its config.json); matscan never writes over it "
                    f"(choose another {flag})",
                )
    return path


def check_destination(
    out: str | Path,
    inputs: Iterable[str | Path] = (),
    kind: str = "folder",
    overwrite: bool = False,
    overwrite_any: bool = False,
    flag: str = "--out",
    command: str | None = None,
) -> Path:
    """Check an output path before any work (module doc); return it resolved. ``command``
    names the command writing it: a folder holding a capture is replaced only by the
    command that wrote it."""
    if kind not in ("folder", "file"):
        raise ValueError(f"kind {kind!r}")
    given, path = check_place(out, inputs, flag)
    if kind == "file" and path.name in _capture_files_here(path):
        raise input_error(given, f"belongs to the capture in {path.parent}; matscan never replaces a capture's files")
    if path.exists() and (holder := capture_above(path)) is not None:
        raise input_error(
            given, f"lies in the capture {holder}; matscan never replaces a capture's files (choose another {flag})"
        )
    if kind == "file" and path.exists() and (owner := _owned_here(path)) is not None:
        raise input_error(given, f"{owner}; matscan never replaces it (choose another {flag})")
    if kind == "file" and (photos := _rti_photos_beside(path)):
        raise input_error(
            given,
            f"is the light file of the RTI photos beside it ({photos[0]}…); matscan never replaces a capture's "
            f"files (choose another {flag})",
        )
    anc = _nearest_existing(path.parent)
    if not anc.is_dir():
        raise input_error(anc, f"is not a folder, so {flag} {given} cannot be created")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise input_error(anc, "is not writable; choose another place for the output")
    limit = _name_max(anc)
    if len(os.fsencode(path.name)) + TMP_NAME_EXTRA + len(path.suffix) > limit:
        raise input_error(
            given,
            f"the name is {len(path.name)} characters; this file system allows {limit}, and matscan needs "
            f"{TMP_NAME_EXTRA + len(path.suffix)} more for a temporary name",
        )
    if path.exists():
        if kind == "file":
            if path.is_dir():
                raise input_error(given, "is a folder; give a file name")
            if not overwrite:
                raise input_error(given, "exists (pass --overwrite to replace it)")
        else:
            if not path.is_dir():
                raise input_error(given, "exists and is not a folder")
            if any(path.iterdir()):
                if not overwrite:
                    raise input_error(
                        given, "folder exists and is not empty (choose another --out, or pass --overwrite)"
                    )
                held_captures = captures_not_its_own(path, command)
                if held_captures:
                    raise input_error(
                        given,
                        f"holds a capture ({held_captures[0]}); matscan never replaces a capture, whatever the "
                        f"flags (move it, or choose another {flag})",
                    )
                foreign = foreign_entries(path)
                if foreign and not overwrite_any:
                    more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
                    raise input_error(
                        given,
                        f"holds {foreign[0]}{more}, which no matscan.json there lists as matscan's output; "
                        "--overwrite replaces only previous matscan outputs (move those files, or pass "
                        "--overwrite-any to delete them)",
                    )
    return path


@dataclass
class OutputClaim:
    """A checked, locked output (from :func:`claim_output`)."""

    path: Path
    kind: str
    overwrite: bool
    command: str
    overwrite_any: bool = False

    def check_space(self, need_bytes: int) -> None:
        """Refuse (before the work) when the file system has less free space than the
        output is expected to take."""
        anc = _nearest_existing(self.path)
        free = shutil.disk_usage(anc).free
        if free < need_bytes:
            raise input_error(
                self.path,
                f"needs about {need_bytes / 2**20:.0f} MiB but only {free / 2**20:.0f} MiB are free there",
            )

    @contextmanager
    def folder(self) -> Iterator[Path]:
        """A temporary folder that becomes the output when the block succeeds."""
        with atomic_folder(self.path, overwrite=self.overwrite) as tmp:
            yield tmp
            write_record_files(tmp, self.command)
            # again just before the swap: a file put into the old output during the work
            # would otherwise go with it
            if self.path.is_dir() and (held := captures_not_its_own(self.path, self.command)):
                raise input_error(
                    self.path,
                    f"a capture ({held[0]}) appeared there during the work; matscan never replaces a capture, "
                    "and nothing was replaced",
                )
            if self.path.is_dir() and not self.overwrite_any:
                foreign = foreign_entries(self.path)
                if foreign:
                    raise input_error(
                        self.path,
                        f"{foreign[0]} appeared there during the work and matscan did not write it; "
                        "nothing was replaced (move it, or pass --overwrite-any)",
                    )

    @contextmanager
    def file(self) -> Iterator[Path]:
        """A temporary file name that becomes the output when the block succeeds."""
        with atomic_file(self.path) as tmp:
            yield tmp


@contextmanager
def claim_output(
    out: str | Path,
    command: str,
    inputs: Iterable[str | Path] = (),
    kind: str = "folder",
    overwrite: bool = False,
    overwrite_any: bool = False,
    flag: str = "--out",
    suffixes: tuple[str, ...] = (),
) -> Iterator[OutputClaim]:
    """Check ``out`` (:func:`check_destination`; and, where ``suffixes`` are given, that
    its name ends in one of them, as the file the command writes must), lock it, clear
    stale temporaries, and yield an :class:`OutputClaim` for the rest of the command."""
    if suffixes and Path(out).suffix not in suffixes:  # exact, as the readers match it (rig .json, .lp)
        raise MatscanError(f"{flag}: {out}: {command} writes a {' or '.join(suffixes)} file; name it so")
    resolved = _resolve(Path(out))
    if held(resolved) and resolved in _ACTIVE:  # claimed earlier in this command, checked then: the same claim
        with output_lock(resolved):
            yield _ACTIVE[resolved]
        return
    path = check_destination(out, inputs, kind, overwrite, overwrite_any, flag, command)
    made = [p for p in (path.parent, *path.parent.parents) if not p.exists()]  # deepest first
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise input_error(path.parent, f"cannot create this folder ({exc.strerror})") from None
    try:
        with output_lock(path):
            check_destination(out, inputs, kind, overwrite, overwrite_any, flag, command)  # again, now it is ours
            try:
                clean_stale(path)
            except OSError as exc:
                raise input_error(path, f"cannot remove a stale temporary beside it ({exc.strerror})") from None
            _ACTIVE[path] = OutputClaim(path, kind, overwrite, command, overwrite_any)
            try:
                yield _ACTIVE[path]
            finally:
                del _ACTIVE[path]
    finally:
        if not path.exists():  # the command failed: the folders made for its output go too, where empty
            for folder in made:
                try:
                    folder.rmdir()
                except OSError:
                    break


#: The claims this process holds, by path (a nested claim of the same output reuses its flags).
_ACTIVE: dict[Path, OutputClaim] = {}
