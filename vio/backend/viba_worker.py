"""The visual-inertial BA of the scale refinement (:mod:`vio.backend.viba`) in a worker
process, off the frame path.

GTSAM holds the GIL inside ``LevenbergMarquardtOptimizer.optimize`` (a thread next to the
frame loop got 2 loop iterations in 2.6 s of optimization), so only a process overlaps
it. The worker is the front end's (``python -m vio.overlap``: a fresh interpreter, pickles
over its pipes); here it applies :func:`viba.solve` to each job.

Deterministic by construction: a job submitted at keyframe time ``t`` is due at the
first keyframe at or after ``t + delay_s`` of data time, and :meth:`BatchWorker.due`
waits for it there if the worker is late, so results never depend on timing (same input,
same output). A worker that fails or dies is logged and its jobs count as refused; the
estimator goes on without the refinement.
"""

from __future__ import annotations

import logging
import time
import weakref
from collections import deque
from typing import Any, Callable

from vio.backend import viba
from vio.overlap import WorkerError, _receive, _send, _shutdown, _worker_process

log = logging.getLogger(__name__)


def stage() -> Callable[[tuple], tuple[viba.VibaResult, float]]:
    """The worker's job function: ``viba.solve(*args)`` and its duration (s)."""
    return _solve


def _solve(args: tuple) -> tuple[viba.VibaResult, float]:
    t0 = time.perf_counter()
    return viba.solve(*args), time.perf_counter() - t0


class BatchWorker:
    """Submit :func:`viba.solve` jobs to a worker process and collect them when due
    (module docstring). ``timeout_s``: the longest wait for one result."""

    def __init__(self, timeout_s: float = 120.0) -> None:
        self.timeout_s = timeout_s
        self._proc = None
        self._finalizer: weakref.finalize | None = None
        self._jobs: deque[tuple[int, Any]] = deque()   # (due t_ns, caller's tag), in order
        self.failed = False

    def pending(self) -> bool:
        return bool(self._jobs)

    def start(self) -> None:
        """Start the worker process (its imports take ~1 s of CPU: started ahead of the
        first job, it does not make that job late)."""
        if self._proc is not None or self.failed:
            return
        try:
            self._proc = _worker_process()
            self._finalizer = weakref.finalize(self, _shutdown, self._proc)
            _send(self._proc.stdin, (stage, ()))
        except (OSError, ValueError) as exc:
            self._fail(f"could not start ({exc})")

    def submit(self, due_ns: int, args: tuple, tag: Any) -> bool:
        """Send ``viba.solve(*args)`` to the worker, due at keyframe time ``due_ns``;
        False when the worker is unavailable (the caller solves in process instead)."""
        self.start()
        if self.failed:
            return False
        try:
            _send(self._proc.stdin, args)
        except (OSError, ValueError) as exc:
            self._fail(f"could not send a job ({exc})")
            return False
        self._jobs.append((due_ns, tag))
        return True

    def due(self, t_ns: int) -> list[tuple[Any, tuple[viba.VibaResult, float]]]:
        """``(tag, (result, seconds))`` of every job due at or before ``t_ns``, in
        submission order (waiting for them if needed); a failed worker gives refusals."""
        out = []
        while self._jobs and self._jobs[0][0] <= t_ns:
            _, tag = self._jobs.popleft()
            out.append((tag, self._result()))
        return out

    def _result(self) -> tuple[viba.VibaResult, float]:
        refused = (viba.VibaResult(False, "batch worker unavailable"), float("nan"))
        if self.failed:
            return refused
        t0 = time.perf_counter()
        try:
            out = _receive(self._proc, self.timeout_s)
            log.debug("visual-inertial BA result waited for %.3f s", time.perf_counter() - t0)
            return out
        except (WorkerError, OSError, EOFError) as exc:
            self._fail(str(exc))
        except Exception as exc:  # noqa: BLE001 - the job's own error, re-raised from the worker
            log.warning("visual-inertial BA failed in the worker: %s", exc)
            self._fail(f"{type(exc).__name__}: {exc}")
        return refused

    def _fail(self, why: str) -> None:
        log.warning("visual-inertial BA worker stopped (%s): the scale refinement is off for "
                    "the rest of the run", why)
        self.failed = True
        self.close()

    def close(self) -> None:
        """Stop the worker (pending jobs are dropped)."""
        if self._finalizer is not None:
            self._finalizer()
        self._proc, self._finalizer = None, None
        self._jobs.clear()
