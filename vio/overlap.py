"""Run an image stage in a worker process, overlapped with the backend.

The GIL is held during iSAM2 updates, so a thread cannot overlap the KLT front end
with the backend; a process can. The main process keeps iterating the sync layer's
packets and sends up to ``depth`` of them ahead to a worker that applies the stage
(image loading, KLT, stereo matching) and sends the processed packets back. The
worker is a pure function of the packet sequence and handles it strictly in order,
so the backend sees exactly the packets the in-process stage would give: results do
not depend on timing (``tests/test_image_pipeline.py`` checks equality).

The worker is a fresh interpreter (``python -m vio.overlap``) talking pickles over
its stdin/stdout: unlike ``multiprocessing`` it neither forks a process that holds
the parent's threads and locks (which deadlocks) nor re-runs the user's main script
(spawn does, and an unguarded script then recurses). Failures in the worker (an
unreadable image, a bad calibration) come back as the original exception, re-raised
in the main process with the same one-line message.
"""

from __future__ import annotations

import atexit
import gc
import importlib
import logging
import os
import pickle
import queue
import select
import struct
import subprocess
import sys
import threading
import traceback
from collections import deque
from concurrent.futures import Future
from typing import IO, Any, Callable, Iterable, Iterator

from vio.threads import one_blas_thread

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

log = logging.getLogger(__name__)

_HEADER = struct.Struct("<Q")
SUPPORTED = os.name != "nt"    # the parent waits on the worker's pipe with select()


class WorkerError(RuntimeError):
    """The front-end worker died, stalled, or raised an exception that cannot cross
    processes (its type and message are kept)."""


def _send(stream: IO[bytes], obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_HEADER.pack(len(data)) + data)
    while view:   # an unbuffered (raw) stream may write part of it
        n = stream.write(view)
        view = view[n if n is not None else 0:]
    stream.flush()


def _read_exact(stream: IO[bytes], n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            raise EOFError
        buf += chunk
    return bytes(buf)


def _worker_process(preload: tuple[str, ...] = ()) -> subprocess.Popen:
    """``python -m vio.overlap [MODULE ...]`` with unbuffered pipes: the parent waits for
    replies with ``select`` on the pipe, which cannot see bytes a buffered reader has
    already pulled in (two replies read at once left the second one unseen:
    ``LivePipeline.close`` then waited forever, and ``overlapped`` would time out on its
    last result). The worker imports the ``preload`` modules before it reads its stage.
    Both pipes are widened (:func:`_widen`): the packets ``overlapped`` sends ahead
    (``prime``, ~1.5 KB each, one 4-KB page per two) would otherwise fill the worker's
    stdin while it is still loading its kernels, and block the parent there."""
    proc = subprocess.Popen([sys.executable, "-m", "vio.overlap", *preload], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, bufsize=0, env=one_blas_thread(dict(os.environ)))
    _widen(proc.stdout)
    _widen(proc.stdin)
    return proc


_PRESTARTED: list[subprocess.Popen] = []


def prestart(preload: tuple[str, ...] = ("vio.tracking",)) -> None:
    """Start the next :func:`overlapped` call's worker now, importing ``preload`` (the
    image stage's modules: OpenCV, Numba and, through ``vio.tracking.warm_up``, its
    compiled kernels): its start-up then overlaps the
    caller's own (imports, the dataset's listing, the pipeline's construction) instead of
    delaying the first frame. A worker never taken is stopped at exit."""
    if not _PRESTARTED:
        _PRESTARTED.append(_worker_process(preload))
        atexit.register(_stop_prestarted)


def _stop_prestarted() -> None:
    while _PRESTARTED:
        _shutdown(_PRESTARTED.pop())


def _widen(pipe: IO[bytes], size: int = 1 << 20) -> None:
    """Enlarge a pipe's kernel buffer (Linux; 64 KB by default, at most
    ``/proc/sys/fs/pipe-max-size``) so the worker can run ``depth`` results ahead while the
    backend is busy in a keyframe update, instead of blocking on its write after ~4 of
    them (a mono frame's answer is ~10 KB: ~6 frames ahead of a parent still starting up);
    silently left as is where not possible. Both ends call it on the results pipe."""
    if fcntl is None or not sys.platform.startswith("linux"):
        return
    try:
        fcntl.fcntl(pipe.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), size)
    except OSError:
        pass


def _recv(stream: IO[bytes]) -> Any:
    (n,) = _HEADER.unpack(_read_exact(stream, _HEADER.size))
    return pickle.loads(_read_exact(stream, n))


def _describe(exc: BaseException) -> tuple[BaseException, str]:
    """The exception itself when it survives pickling (else a ``WorkerError`` with its
    type and message) and the formatted traceback, for the main process."""
    tb = "".join(traceback.format_exception(exc))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - an exception that cannot cross processes
        exc = WorkerError(f"{type(exc).__name__}: {exc}")
    return exc, tb


def _reader(inp: IO[bytes], load: Callable[[Any], Any] | None, out: "queue.Queue") -> None:
    """Worker thread: read packets until None or EOF and, with ``load``, apply it (image
    decoding: GIL-free in OpenCV, ISA-L and the Numba unfilter kernel) while the main
    thread tracks the previous ones; queue (packet, error) in order, then None."""
    while True:
        try:
            pkt = _recv(inp)
        except EOFError:
            pkt = None
        except BaseException as exc:  # noqa: BLE001 - a broken stream: reported, then stop
            out.put((None, exc))
            return
        if pkt is None:
            out.put(None)
            return
        try:
            out.put((load(pkt) if load is not None else pkt, None))
        except BaseException as exc:  # noqa: BLE001 - raised in order by the main thread
            out.put((pkt, exc))


def _preload(name: str) -> None:
    """Import module ``name`` and run its ``warm_up()`` if it has one (loading compiled
    kernels); a failing warm-up is only reported: the stage itself decides."""
    module = importlib.import_module(name)
    warm = getattr(module, "warm_up", None)
    if warm is not None:
        try:
            warm()
        except Exception as exc:  # noqa: BLE001 - the run itself reports real failures
            print(f"vio.overlap: {name}.warm_up failed: {exc}", file=sys.stderr)


def worker_main() -> None:
    """Worker loop: read (factory, args[, nice]), then packets until None; answer each with
    ("ok", packet) or ("error", (exception, traceback)) and stop at the first error.
    A reader thread receives the packets and runs the stage's ``load`` (if it has one:
    ``vio.tracking.ImageStage.load`` decodes the images) ahead of the stage: real MH_01
    stereo, whose worker bounds the throughput, 2.0-2.1 -> 2.4x real time (wall 7.95 ->
    7.1 s), hybrid 1.8 -> 1.9x, mono unchanged (its backend bounds it); same output.
    A stage with ``submit`` runs pipelined (``_pipelined``)."""
    gc.disable()                     # start-up makes long-lived objects only (enabled below)
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    _widen(out)                      # the results pipe, from this end too
    sys.stdout = sys.stderr          # stray prints must not corrupt the protocol
    inp = sys.stdin.buffer
    try:
        import cv2
        cv2.setNumThreads(1)         # two cores: leave the other one to the backend
        from vio.memory import tune_heap
        tune_heap()                  # per-frame images and pyramids: reuse, not page faults
        for name in sys.argv[1:]:    # ``prestart``'s modules, while the parent starts up
            _preload(name)
        factory, args, *rest = _recv(inp)
        if rest and rest[0]:
            os.nice(int(rest[0]))    # ``overlapped``'s ``nice``
        stage = factory(*args)
    except BaseException as exc:  # noqa: BLE001 - reported to the main process
        _send(out, ("error", _describe(exc)))
        return
    gc.freeze()                      # the modules and kernels: never rescanned (stereo's
    gc.enable()                      # start-up collections, 0.12 s of 1.3 s, are gone)
    ready: queue.Queue = queue.Queue()
    threading.Thread(target=_reader, args=(inp, getattr(stage, "load", None), ready), daemon=True).start()
    submit = getattr(stage, "submit", None)
    if submit is not None:
        _pipelined(submit, ready, out)
        return
    while True:
        item = ready.get()
        if item is None:
            return
        pkt, exc = item
        try:
            if exc is not None:
                raise exc
            _send(out, ("ok", stage(pkt)))
        except BaseException as exc:  # noqa: BLE001 - reported to the main process
            _send(out, ("error", _describe(exc)))
            return


def _pipelined(submit: Callable[[Any], Future], ready: "queue.Queue", out: IO[bytes]) -> None:
    """Worker loop for a stage with ``submit`` (``vio.tracking.ImageStage``: the stereo
    match of frame k in a thread while frame k+1 is tracked): a sender thread resolves
    the futures in packet order and answers as ``worker_main`` does, stopping at the
    first error; this thread stops submitting then."""
    futures: queue.Queue = queue.Queue()
    failed = threading.Event()

    def sender() -> None:
        while (fut := futures.get()) is not None:
            try:
                _send(out, ("ok", fut.result()))
            except BaseException as exc:  # noqa: BLE001 - reported to the main process
                _send(out, ("error", _describe(exc)))
                failed.set()
                return

    thread = threading.Thread(target=sender, daemon=True)
    thread.start()
    while not failed.is_set():
        item = ready.get()
        if item is None:
            break
        pkt, exc = item
        try:
            if exc is not None:
                raise exc
            fut = submit(pkt)
        except BaseException as exc:  # noqa: BLE001 - sent after the earlier results
            fut = Future()
            fut.set_exception(exc)
        futures.put(fut)
        if fut.done() and fut.exception() is not None:
            break
    futures.put(None)
    thread.join()


def overlapped(factory: Callable[..., Callable[[Any], Any]], args: tuple,
               packets: Iterable[Any], depth: int = 16,
               timeout_s: float = 120.0, nice: int = 0, prime: int = 0) -> Iterator[Any]:
    """Yield ``factory(*args)(pkt)`` for every packet, computed in a worker process.

    ``factory`` (an importable callable) and ``args`` must be picklable, as packets
    are. At most ``depth`` packets are in flight (16: the worker keeps tracking through a
    keyframe update of the backend, ~150-250 ms or 5-8 frames in hybrid mode; with 4, real
    MH_01 hybrid took 16.7 instead of 16.3 s); ``timeout_s`` is the longest wait for one
    result. ``nice`` (0-19) lowers the worker's scheduling priority, so that on a busy
    machine the consumer of its results runs first and the worker takes the idle time.
    The first ``max(prime, depth)`` packets are sent before this returns, so the worker
    tracks them while the caller finishes its own start-up (``vio.run.run_dataset``).
    """
    gen = _overlapped(factory, args, packets, depth, timeout_s, nice, max(prime, depth))
    next(gen)            # runs to the first send: the worker is busy from here on
    return gen


def _overlapped(factory: Callable[..., Callable[[Any], Any]], args: tuple, packets: Iterable[Any],
                depth: int, timeout_s: float, nice: int, first: int) -> Iterator[Any]:
    """:func:`overlapped`'s generator: yields None once the first ``first`` packets are
    sent, then the results."""
    proc = _PRESTARTED.pop() if _PRESTARTED else _worker_process()
    pending: deque[int] = deque()
    source = iter(packets)
    try:
        _send(proc.stdin, (factory, args, nice))
        done = stopped = False
        primed = False
        while True:
            while not done and len(pending) < (depth if primed else first):
                pkt = next(source, None)
                if pkt is None:
                    done = True
                    break
                try:
                    _send(proc.stdin, pkt)
                except OSError:   # the worker stopped: its error follows its last results
                    done = stopped = True
                    break
                pending.append(pkt.index)
            if not primed:
                primed = True
                yield None
            if not pending:
                if stopped:
                    raise WorkerError(f"front-end worker stopped early (exit code {proc.wait(5.0)})")
                return
            yield _receive(proc, timeout_s)
            pending.popleft()
    finally:
        _shutdown(proc)


def _receive(proc: subprocess.Popen, timeout_s: float) -> Any:
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    if not ready:
        raise WorkerError(f"front-end worker gave no result in {timeout_s:.0f} s")
    try:
        kind, payload = _recv(proc.stdout)
    except EOFError:
        raise WorkerError(f"front-end worker died (exit code {proc.wait(5.0)})") from None
    if kind == "error":
        exc, tb = payload
        log.debug("front-end worker traceback:\n%s", tb)
        raise exc
    return payload


def _shutdown(proc: subprocess.Popen) -> None:
    try:
        _send(proc.stdin, None)
        proc.stdin.close()
    except (BrokenPipeError, OSError, ValueError):
        pass
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5.0)
    proc.stdout.close()


if __name__ == "__main__":
    worker_main()
    # Every answer is flushed (``_send``) and nothing else is held: skip the interpreter's
    # teardown (numba, OpenCV, the stage's threads), which ``_shutdown`` waits for at the
    # end of every run (real MH_05 mono: 0.31 s of the run's wall time).
    sys.stderr.flush()
    os._exit(0)
