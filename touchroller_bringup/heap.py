"""The C heap of a long-running process: large blocks go back to the system when freed.

A scan makes and drops large arrays every frame (images, bands, warped planes) on several threads. With
glibc's defaults each thread gets a heap arena of its own, and the threshold above which a block is
mapped (and unmapped when freed) rises to the largest block freed so far: after the first few frames
megabyte-sized frames come from the arenas, whose free space fragments and stays resident, and the
process's memory creeps up with the frames although the Python objects do not (tracemalloc shows no
growth). `bound_heap_growth()` fixes the mmap threshold (which also stops its rise) and bounds the number
of arenas. glibc only (Linux); elsewhere, or with TOUCHROLLER_DEFAULT_MALLOC=1, it does nothing.
"""
from __future__ import annotations

import os
import sys

M_MMAP_THRESHOLD = -3   # malloc.h
M_ARENA_MAX = -8
MMAP_THRESHOLD = 128 * 1024   # glibc's initial value, kept: a band or an image is mapped, then given back
ARENA_MAX = 2

_done = False


def bound_heap_growth() -> bool:
    """Set the allocator once per process; True when it was set."""
    global _done
    if _done or not sys.platform.startswith("linux") or os.environ.get("TOUCHROLLER_DEFAULT_MALLOC"):
        return _done
    import ctypes

    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):   # not glibc (musl has no mallopt)
        return False
    _done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_ARENA_MAX, ARENA_MAX))
    return _done
