"""The one Numba decorator of the project's kernels: compiled on first use, cached on
disk next to the calling module, GIL released; without Numba the kernels run as plain
Python (slow, same results)."""

from __future__ import annotations

try:
    from numba import njit as _numba_njit

    def njit(fn):  # noqa: D103
        return _numba_njit(cache=True, nogil=True)(fn)

    def njit_inline(fn):
        """``njit`` for a small helper, inlined into its compiled callers at Numba's IR
        level: LLVM does not always inline across Numba's function boundaries, and a
        helper left as a call keeps its branches (``vio.io.png._paeth``: 0.97 -> 0.67 ms
        an image once inlined, its choice compiled to selects)."""
        return _numba_njit(cache=True, nogil=True, inline="always")(fn)
except ImportError:  # pragma: no cover - without numba the kernels run as plain Python
    def njit(fn):  # noqa: D103
        return fn

    def njit_inline(fn):  # noqa: D103
        return fn


def cache_is_warm(kernel) -> bool:
    """Whether Numba's disk cache holds a compiled version of ``kernel`` for its current
    source (False when unknown: no Numba, caching off, or a Numba without these
    internals). Used to tell the user that a first run compiles."""
    try:
        index = kernel._cache._cache_file._load_index()
    except Exception:  # noqa: BLE001 - private Numba API; any failure means "unknown"
        return False
    return bool(index)
