"""Freed memory kept for reuse by the C library's allocator during the package's long loops.

A learning month makes and frees a few dozen arrays of about a megabyte (the critic's
``720 x 204`` feature matrices and their scaled copies, :mod:`mpcrl_lite.learning.lstd`).
glibc's allocator serves blocks of that size with fresh ``mmap`` pages (or hands a freed
heap top back to the system), so every such array costs its pages' first-touch faults
again, month after month. :func:`keep_freed_memory` raises the two thresholds that decide
it (``mallopt``): blocks below :data:`MMAP_THRESHOLD` come from the heap, and freed memory is
handed back to the system only once more than :data:`TRIM_THRESHOLD` lies free at its top.
The arithmetic is untouched (the same results to the last bit); what changes is the time:
the learning step of a month took 8.4 ms instead of 10.7 ms (``benchmarks/README.md``,
"Freed memory kept"), and the process keeps up to :data:`TRIM_THRESHOLD` of freed memory
for reuse.

It is called where the package's long loops start (the ``python -m mpcrl_lite`` commands,
:func:`mpcrl_lite.learning.learner.run_months`, :func:`mpcrl_lite.studies.lockstep.run_lockstep`),
once per process; it does nothing on a C library without ``mallopt`` (not glibc) or when
the environment variable :data:`ENV` is ``0``.
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["ENV", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

#: Set to ``0`` to leave the allocator's settings alone.
ENV = "MPCRL_LITE_KEEP_MEMORY"
#: Blocks up to this size (bytes) come from the heap (glibc's default starts at 128 KiB).
MMAP_THRESHOLD = 16 << 20
#: Free memory at the heap's top kept for reuse up to this size (bytes; default 128 KiB).
TRIM_THRESHOLD = 64 << 20

# glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Set the allocator's thresholds (see the module docstring) once per process; returns
    whether they are set. Nothing happens, and False is returned, where ``mallopt`` is
    missing or ``MPCRL_LITE_KEEP_MEMORY=0``."""
    global _applied
    if _applied is None:
        _applied = _apply()
    return _applied


def _apply() -> bool:
    if os.environ.get(ENV, "").strip() == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library this process runs on
    except (OSError, AttributeError):  # no mallopt (e.g. musl)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and \
        bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
