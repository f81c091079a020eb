"""Returning freed heap memory to the operating system on long runs.

Each keyframe builds and frees Jacobians, factors and Values copies of many sizes.
glibc's allocator keeps most freed blocks in its arenas instead of returning them,
so the resident size of a long run creeps up although nothing leaks: on the 300-s
soak (``benchmarks/memory_soak.py``) live Python objects and iSAM2's factor slots
stay constant while RSS grows ~1.2 MB/min, and ``malloc_trim(0)`` brings it back to
the same level every time (measured 270, 269, 268, 269, 267 MB at 50-s intervals).
``trim_heap`` does that; elsewhere (macOS, musl, Windows) it is a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    name = ctypes.util.find_library("c")
    if not name:
        return None
    try:
        fn = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


def trim_heap() -> bool:
    """Release free heap pages to the OS (glibc ``malloc_trim(0)``); True if it ran."""
    fn = _malloc_trim()
    if fn is None:
        return False
    fn(0)
    return True
