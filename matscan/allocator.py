"""glibc told, before the command starts, to reuse freed memory: less time in the kernel.

A reconstruction allocates and frees large tensors over and over (photos, renderings,
Jacobians of tens to hundreds of MB). glibc hands each block above its mmap threshold
back to the operating system when it is freed, so the next one is mapped and faulted in
again, page by page, each page zeroed by the kernel. On the 2-core machines this project
is measured on, that kernel time was as large as the arithmetic: ``matscan reconstruct``
of rti-icon (72 photos of 402 × 395) took 38.6 s, 32.8 s of processor time in the kernel.
With ``MALLOC_MMAP_MAX_=0`` (every block from the heap) and a large
``MALLOC_TRIM_THRESHOLD_`` (the heap's free top kept), freed memory is reused as it is:
18.6 s, 6.2 s in the kernel, the maps bit for bit the same, peak memory 2.7 GB against
2.2 (docs/results.md, "Speed and memory"; ``bench/reconstruct.py --allocator``).

glibc reads these variables when the process starts; set later with ``mallopt`` the
same policy made ``matscan simulate`` many times slower. So the ``matscan`` command, run
without them, starts itself again once with them set (:func:`environment`), before any
heavy import. ``MATSCAN_MALLOC=system`` keeps glibc's defaults; nothing changes where the
C library is not glibc, or for library users, who may set the variables themselves.
"""

from __future__ import annotations

import ctypes
import os
import sys

#: ``MATSCAN_MALLOC=system`` keeps the C library's own allocation policy.
ENV = "MATSCAN_MALLOC"
#: The variables glibc reads at start-up, and the values the command sets.
POLICY = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(2**31 - 1)}


def _glibc() -> bool:
    try:
        ctypes.CDLL(None).gnu_get_libc_version  # noqa: B018 (glibc only)
    except (OSError, AttributeError):
        return False
    return True


def environment() -> dict[str, str] | None:
    """The environment to start the command again with, or None where it runs as it is:
    the policy already set (or any part of it set by the user), ``MATSCAN_MALLOC=system``,
    not Linux, or not glibc."""
    if os.environ.get(ENV, "").lower() == "system" or not sys.platform.startswith("linux"):
        return None
    if any(k in os.environ for k in POLICY) or not _glibc():
        return None
    return {**os.environ, **POLICY}
