"""``--help`` for the bench scripts that read ``sys.argv`` by hand: each prints its own
docstring and stops, rather than take the flag for an argument and start a run of minutes."""

from __future__ import annotations

import sys


def usage(doc: str | None) -> None:
    """Print ``doc`` and exit when ``-h`` or ``--help`` is among the arguments."""
    if {"-h", "--help"} & set(sys.argv[1:]):
        print((doc or "").strip())
        raise SystemExit(0)
