"""One BLAS thread per process.

The pipeline already runs two processes on two cores (the backend and the image
front-end worker, ``vio.overlap``) and does its heavy numerics in Numba kernels and
GTSAM (single-threaded); numpy's OpenBLAS would start a thread per core in each
process, whose spinning takes CPU from the other process. Measured on real MH_05 mono
(``benchmarks/bench_profile.py``, two runs each): CPU of the backend 4.60 / 4.51 ->
4.06 / 4.15 s, of the front-end worker 3.98 / 4.03 -> 3.61 / 3.65 s, real-time factor
2.9 -> 3.0-3.1x, trajectory unchanged; real MH_01 stereo 3.50 -> 3.40 s / 7.85 -> 7.56 s.

It also keeps runs bit-reproducible: with OpenBLAS's default threads an in-process
``run_dataset`` under load differed in the last bits from some keyframe on (generated
MH_03 td 5 ms features, four processes at once: 3 of 28 runs, 9e-10 m), with one BLAS
thread 0 of 16.

This module imports nothing heavy: call :func:`one_blas_thread` before numpy is first
imported (``vio`` CLI, front-end worker, benchmark workers; Python users of the API set
``OPENBLAS_NUM_THREADS=1`` themselves). A user's own ``OPENBLAS_NUM_THREADS`` wins.
"""

from __future__ import annotations

import os


def one_blas_thread(env: dict | None = None) -> dict:
    """Set ``OPENBLAS_NUM_THREADS=1`` in ``env`` (default ``os.environ``) unless set;
    returns ``env``."""
    env = os.environ if env is None else env
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env
