"""Returning freed heap memory to the operating system on long runs.

Each keyframe builds and frees Jacobians, factors and Values copies of many sizes.
glibc's allocator keeps most freed blocks in its arenas instead of returning them,
so the resident size of a long run creeps up although nothing leaks: on the 300-s
soak (``benchmarks/memory_soak.py``) live Python objects and iSAM2's factor slots
stay constant while RSS grows ~1.2 MB/min, and ``malloc_trim(0)`` brings it back to
the same level every time (measured 270, 269, 268, 269, 267 MB at 50-s intervals).
``trim_heap`` does that; elsewhere (macOS, musl, Windows) it is a no-op.

The opposite cost on short time scales: every image stage allocates and frees arrays of
0.4-9 MB per frame (decoded images, pyramids, [I, gx, gy] stacks, Jacobians). Above
glibc's mmap threshold each is a fresh ``mmap`` whose pages fault in zeroed, and below
it a free at the top of the heap returns pages (trim threshold 128 KB) that the next
allocation faults in again. ``tune_heap`` raises the mmap threshold to 32 MB, the trim
threshold to 128 MB and the top pad to 16 MB (``mallopt``), so those blocks are reused.
Measured on the seed-14 render (20 s, 401 stereo frames): hybrid 1.01 M -> 0.17 M minor
page faults, system CPU 1.77 -> 0.7-1.2 s (`vio run`, repeated runs), trajectory and peak
RSS unchanged (736 vs 737 MB); direct 0.70 -> 0.4-0.46 s system CPU. ``trim_heap`` still
returns the retained memory on long runs.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.lru_cache(maxsize=None)
def _libc(name: str, argtypes: tuple, restype):
    """glibc's function ``name`` with its C signature, or None where there is none."""
    lib = ctypes.util.find_library("c")
    if not lib:
        return None
    try:
        fn = getattr(ctypes.CDLL(lib), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = list(argtypes), restype
    return fn


def _malloc_trim():
    return _libc("malloc_trim", (ctypes.c_size_t,), ctypes.c_int)


def trim_heap() -> bool:
    """Release free heap pages to the OS (glibc ``malloc_trim(0)``); True if it ran."""
    fn = _malloc_trim()
    if fn is None:
        return False
    fn(0)
    return True


M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3   # glibc malloc.h


def _mallopt():
    return _libc("mallopt", (ctypes.c_int, ctypes.c_int), ctypes.c_int)


def tune_heap(mmap_threshold: int = 32 << 20, trim_threshold: int = 128 << 20,
              top_pad: int = 16 << 20) -> bool:
    """glibc ``mallopt`` for per-frame image-sized arrays (module docstring), in bytes;
    True if all three were set (False elsewhere: a no-op)."""
    fn = _mallopt()
    if fn is None:
        return False
    return all(fn(opt, int(val)) == 1 for opt, val in ((M_MMAP_THRESHOLD, mmap_threshold),
                                                        (M_TRIM_THRESHOLD, trim_threshold),
                                                        (M_TOP_PAD, top_pad)))
