"""The one Numba decorator of the project's kernels: compiled on first use, cached on
disk next to the calling module, GIL released; without Numba the kernels run as plain
Python (slow, same results)."""

from __future__ import annotations

import sys


def _skip_blas_probe() -> None:
    """Import ``numba.np.arraymath`` with ``scipy.linalg`` unimportable, once per process.

    That module probes for BLAS at import (``_HAVE_BLAS = _check_blas()``), which imports
    ``scipy.linalg`` only to see that it is there: 0.15-0.25 s of every process's first
    kernel load (``scipy.linalg``'s own imports pull in ``numpy.f2py`` and
    ``numpy.testing``). The probe's answer decides one thing, whether ``np.correlate`` and
    ``np.convolve`` use BLAS, and no kernel here calls them; a kernel that does call BLAS
    (``np.dot``, ``@``) still finds it, because Numba looks BLAS up when such a call is
    compiled or first run, after this. Nothing is done when either module is already
    imported; a Numba whose module fails so is simply imported again later, normally."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    sys.modules["scipy.linalg"] = None   # import raises ModuleNotFoundError for None
    try:
        import numba.np.arraymath  # noqa: F401
    except Exception:  # noqa: BLE001 - a Numba without this layout: its normal import later
        pass
    finally:
        if sys.modules.get("scipy.linalg", 0) is None:
            del sys.modules["scipy.linalg"]


try:
    from numba import njit as _numba_njit

    _skip_blas_probe()

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
