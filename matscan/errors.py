"""The one error type matscan raises for bad input.

Every check at a public boundary (a file, a CLI argument, a function argument a
user passes) raises :class:`MatscanError` with a one-line message that names the
file or argument, what was wrong, and what would be right. The CLI prints that
line and exits non-zero; it never shows a traceback for one.
"""

from __future__ import annotations

from pathlib import Path


class MatscanError(ValueError):
    """Bad input, described in one line for a person to act on."""


def input_error(where: str | Path, problem: str) -> MatscanError:
    """Build a :class:`MatscanError` reading ``"<where>: <problem>"``."""
    return MatscanError(f"{where}: {problem}")


def not_a_folder(path: str | Path, kind: str) -> MatscanError:
    """The error for a ``kind`` folder (``"capture folder"``) that ``path`` is not: a file
    is named as a file, and a ``capture.json`` or ``mapset.json`` as the folder's file."""
    path = Path(path)
    if path.is_file():
        hint = " (give the folder that holds it)" if path.name in ("capture.json", "mapset.json") else ""
        return input_error(path, f"is a file, not a {kind}{hint}")
    return input_error(path, f"no such {kind}")
