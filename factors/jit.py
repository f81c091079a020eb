"""The one Numba decorator of the project's kernels: compiled on first use, cached on
disk next to the calling module, GIL released; without Numba the kernels run as plain
Python (slow, same results)."""

from __future__ import annotations

try:
    from numba import njit as _numba_njit

    def njit(fn):  # noqa: D103
        return _numba_njit(cache=True, nogil=True)(fn)
except ImportError:  # pragma: no cover - without numba the kernels run as plain Python
    def njit(fn):  # noqa: D103
        return fn
