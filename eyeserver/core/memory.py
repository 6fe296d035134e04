"""The C allocator told to keep the memory it is given, for the speed of array work.

By default glibc serves each block over 128 KB (a 640 × 512 float32 image is 1.3 MB) with fresh
pages from the kernel and gives it back when freed, and on this kind of virtual machine a fresh
page's first touch is costly. Every array of a frame's reconstruction is such a block, so by
default they are paid for again and again (what it costs: docs/notes/speed.md). With
:func:`keep_freed_memory` large blocks come from the heap (below glibc's 32 MB cap) and freed
memory is not trimmed, so a process's resident memory stays at its peak.
"""

from __future__ import annotations

import ctypes

import numpy as np

__all__ = ["MMAP_THRESHOLD_MAX", "keep_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 << 20
"""glibc's largest mmap threshold on 64-bit systems, bytes: blocks up to it come from the heap."""

_kept = False


def keep_freed_memory(touch_bytes: int = 0) -> bool:
    """Have glibc keep freed memory and serve blocks up to :data:`MMAP_THRESHOLD_MAX` from the
    heap, and touch ``touch_bytes`` of it now (so even the first arrays of a new size find pages
    already mapped). Returns False where the C library has no ``mallopt`` (not glibc): nothing
    changes there. Safe to call more than once."""
    global _kept
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    if not _kept:
        mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(2**31 - 1))
        mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(MMAP_THRESHOLD_MAX))
        _kept = True
    block = MMAP_THRESHOLD_MAX // 2
    touched = [np.ones(block, dtype=np.uint8) for _ in range(touch_bytes // block)]
    del touched
    return True
