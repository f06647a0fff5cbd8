"""Outputs that appear whole or not at all, one writer at a time.

Every file and folder matscan writes is built under a temporary name beside its
destination and renamed when complete, so an interrupted run never leaves a
half-written map set or capture behind.

- **Temporary names** say whose they are: ``.NAME.matscan-tmp-PID-TOKEN`` (work in
  progress) and ``.NAME.matscan-old-PID-TOKEN`` (a replaced output on its way out).
  A later writer of the same output removes the ones whose process is dead
  (:func:`clean_stale`), and restores an ``old`` one when the output itself is
  missing (a process killed between the two renames of a replacement).
- **Replacement** of an existing folder swaps the two atomically
  (``renameat2(RENAME_EXCHANGE)`` on Linux), so the final name is never empty;
  where the kernel or file system cannot swap, the old output is renamed aside
  first and restored if the second rename fails.
- **One writer**: :func:`output_lock` takes an exclusive, non-blocking ``flock`` on
  ``.NAME.matscan-lock`` beside the output; a second writer fails at once.

The checks that decide whether an output may be written at all (does it touch an
input, is it writable, is there room) live in :mod:`matscan.outputs`.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fcntl
import os
import re
import secrets
import shutil
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from matscan.errors import MatscanError, input_error

TMP_TAG = "matscan-tmp"
OLD_TAG = "matscan-old"
LOCK_TAG = "matscan-lock"
#: Characters a temporary name adds to the output's own name (".", ".matscan-tmp-", pid, "-", token).
TMP_NAME_EXTRA = 1 + 1 + len(TMP_TAG) + 1 + 10 + 1 + 8


def temp_path(path: Path, tag: str = TMP_TAG) -> Path:
    """A fresh temporary name beside ``path`` that names this process."""
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}-{secrets.token_hex(4)}")


def _pattern(name: str) -> re.Pattern[str]:
    return re.compile(rf"^\.{re.escape(name)}\.({TMP_TAG}|{OLD_TAG})-(\d{{1,10}})-[0-9a-f]+(\.[^.]*)?$")


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (on this machine)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def clean_stale(path: Path) -> list[Path]:
    """Remove temporaries of ``path`` left by dead processes; restore an output that
    a killed replacement left only under its ``old`` name. Returns what was removed."""
    parent = path.parent
    if not parent.is_dir():
        return []
    pattern = _pattern(path.name)
    removed = []
    stale = []
    for entry in parent.iterdir():
        m = pattern.match(entry.name)
        if m and not pid_alive(int(m.group(2))):
            stale.append((m.group(1), entry))
    if not path.exists() and not path.is_symlink():
        olds = [e for tag, e in stale if tag == OLD_TAG]
        if olds:  # the newest old output is the one that was being replaced
            newest = max(olds, key=lambda e: e.stat().st_mtime)
            newest.rename(path)
            stale = [(t, e) for t, e in stale if e != newest]
    for _, entry in stale:
        _remove(entry)
        removed.append(entry)
    return removed


# --- one writer at a time ---------------------------------------------------------------


#: Outputs this process holds the lock of, with the nesting depth.
_HELD: dict[Path, int] = {}


def held(path: str | Path) -> bool:
    """Whether this process holds the lock of output ``path``."""
    return Path(path).absolute() in _HELD


def lock_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{LOCK_TAG}")


@contextmanager
def output_lock(path: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on output ``path`` (a file beside it); another process
    asking for it fails at once with a :class:`MatscanError`, while this process may
    take it again (nested). The lock file is removed on release."""
    path = Path(path).absolute()
    if path in _HELD:  # this process holds it already (a command claims early, a writer again)
        _HELD[path] += 1
        try:
            yield
        finally:
            _HELD[path] -= 1
        return
    lp = lock_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise input_error(path, f"cannot create a lock file beside it ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise input_error(
                path, "another matscan process is writing this output right now; wait for it or choose another --out"
            ) from None
        except OSError as exc:  # no locks on this file system (some network mounts)
            os.close(fd)
            raise input_error(path, f"cannot lock this output ({exc.strerror}); write it to a local disk") from None
        # the file we locked must still be the one at lp (a releasing holder unlinks it)
        try:
            same = os.fstat(fd).st_ino == os.stat(lp).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    _HELD[path] = 1
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        del _HELD[path]
        try:
            lp.unlink(missing_ok=True)
        finally:
            os.close(fd)


# --- replacing a folder without an empty moment -----------------------------------------

_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _libc():
    name = ctypes.util.find_library("c")
    try:
        lib = ctypes.CDLL(name, use_errno=True)
        lib.renameat2  # noqa: B018  (probe: glibc ≥ 2.28)
        return lib
    except (OSError, AttributeError, TypeError):
        return None


_LIBC = _libc()


def exchange(a: Path, b: Path) -> bool:
    """Atomically swap two existing paths (Linux ``renameat2``); False where unsupported."""
    if _LIBC is None:
        return False
    rc = _LIBC.renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
        return False
    raise OSError(err, os.strerror(err), str(b))


def replace_folder(tmp: Path, path: Path) -> None:
    """Move the complete folder ``tmp`` to ``path``, replacing what is there; at no
    moment is there nothing at ``path`` once something was."""
    if not path.exists():
        tmp.rename(path)
        return
    if exchange(tmp, path):  # tmp now holds the old output
        _remove(tmp)
        return
    old = temp_path(path, OLD_TAG)
    path.rename(old)
    try:
        tmp.rename(path)
    except BaseException:
        old.rename(path)
        raise
    _remove(old)


def _os_error(path: Path, exc: OSError) -> MatscanError:
    if exc.errno == errno.ENOSPC:
        return input_error(path, "no space left on the device; nothing was written")
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return input_error(path, f"cannot write here ({exc.strerror}); nothing was written")
    if exc.errno == errno.ENAMETOOLONG:
        return input_error(path, "the name is too long for the file system; nothing was written")
    return input_error(path, f"cannot write ({exc.strerror or exc}); nothing was written")


@contextmanager
def atomic_folder(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``path`` when the block succeeds.

    The caller has checked the destination (:func:`matscan.outputs.claim_output`)
    and should hold its lock. An existing non-empty ``path`` is an error unless
    ``overwrite``; it is replaced only once the new folder is complete. On an
    exception (an interrupt too) the temporary folder is removed and ``path`` is
    left as it was; an ``OSError`` becomes a one-line :class:`MatscanError`.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise input_error(path, "exists and is not a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise input_error(path, "folder exists and is not empty (choose another --out, or pass --overwrite)")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        clean_stale(path)
        tmp = temp_path(path)
        tmp.mkdir()
    except OSError as exc:
        raise _os_error(path, exc) from None
    try:
        yield tmp
        replace_folder(tmp, path)
    except OSError as exc:
        _remove(tmp)
        raise _os_error(path, exc) from None
    except BaseException:
        _remove(tmp)
        raise


def plain_mode(path: Path) -> int:
    """The permissions a file written in place at ``path`` would have: those of the file
    there now, else 0o666 less the process's umask (what ``open(path, "w")`` gives)."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        mask = os.umask(0o022)
        os.umask(mask)
        return 0o666 & ~mask


@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary file name (same suffix as ``path``) that replaces ``path``
    atomically (``os.replace``) when the block succeeds; removed on failure. Temporaries
    of ``path`` left by killed writers are removed first (:func:`clean_stale`). The file
    gets the permissions of :func:`plain_mode`, whatever the writer created it with
    (safetensors' ``save_file`` creates files readable by their owner only)."""
    path = Path(path)
    tmp = temp_path(path)
    tmp = tmp.with_name(tmp.name + path.suffix)  # writers choose the format by suffix
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        clean_stale(path)
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, plain_mode(path))
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise _os_error(path, exc) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> None:
    """Write a UTF-8 text file atomically."""
    with atomic_file(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
