"""vio.overlap's worker pipes: replies that reach the parent together are all seen."""

from __future__ import annotations

import operator
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from vio import overlap
from vio.overlap import overlapped


def test_replies_arriving_together_are_all_received():
    """The worker answers four packets while the parent is busy, so one pipe read could
    take all four replies; a buffered reader then hid three of them from ``select`` and
    the last results timed out (``LivePipeline.close`` waited forever)."""
    def source():
        for i in range(4):
            yield SimpleNamespace(index=i)
        time.sleep(1.5)   # the worker replies to all four meanwhile

    got = list(overlapped(operator.attrgetter, ("index",), source(), depth=5, timeout_s=5.0))
    assert got == [0, 1, 2, 3]



def test_first_packets_are_sent_before_overlapped_returns():
    """``prime``: the first packets go to the worker when ``overlapped`` is called, so it
    tracks them while the caller starts up (``vio.run``: the pipeline loads its kernels);
    afterwards at most ``depth`` are in flight again, and every result comes in order."""
    pulled = []

    def source():
        for i in range(20):
            pulled.append(i)
            yield SimpleNamespace(index=i)

    it = overlapped(operator.attrgetter, ("index",), source(), depth=3, prime=8, timeout_s=10.0)
    assert len(pulled) == 8
    time.sleep(0.5)                      # the caller's start-up: the worker answers meanwhile
    assert next(it) == 0 and len(pulled) == 8   # 7 still in flight, above depth: none sent
    assert list(it) == list(range(1, 20))
    it = overlapped(operator.attrgetter, ("index",), iter(()), depth=3, prime=8, timeout_s=10.0)
    assert list(it) == []


def test_worker_error_after_it_exits_is_reported_not_a_broken_pipe():
    """The worker stops at its first error; the parent, still sending packets ahead,
    used to die on ``BrokenPipeError`` (a traceback, the worker's message lost: a
    cv2 assertion inside the KLT front end surfaced that way)."""
    import pytest
    pkts = (SimpleNamespace(index=i) if i == 1 else SimpleNamespace(index=i, value=i)
            for i in range(50))
    got = []
    with pytest.raises(AttributeError, match="no attribute 'value'"):
        for x in overlapped(operator.attrgetter, ("value",), pkts, depth=4, timeout_s=10.0):
            got.append(x)
            time.sleep(0.5)   # the worker meanwhile answers packet 1 with its error and exits
    assert got == [0]


class _Unpicklable:
    """Pickles fine in the parent, fails to unpickle in the worker."""

    index = 1

    def __reduce__(self):
        return (int, ("corrupt packet stream",))   # unpickling raises ValueError


def test_broken_packet_stream_is_reported_not_a_hang():
    """The worker's reader thread (which receives packets and decodes images ahead) must
    pass a failure to read a packet on to the main thread, which reports it: a silently
    dead reader left the parent waiting out its whole timeout."""
    import pytest
    pkts = [SimpleNamespace(index=0), _Unpicklable(), SimpleNamespace(index=2)]
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="corrupt packet stream"):
        list(overlapped(operator.attrgetter, ("index",), pkts, depth=4, timeout_s=30.0))
    assert time.perf_counter() - t0 < 20.0


def test_prestarted_worker_is_taken_by_the_next_run_and_an_unused_one_stopped():
    """``prestart`` (``vio run`` calls it before its own imports) leaves a worker that has
    already imported its modules; ``overlapped`` takes that one, with the same results,
    and a prestarted worker nobody takes is stopped at exit."""
    from vio import overlap
    overlap.prestart(("json",))
    proc = overlap._PRESTARTED[0]
    got = list(overlapped(operator.attrgetter, ("index",), (SimpleNamespace(index=i) for i in range(3)),
                          timeout_s=10.0))
    assert got == [0, 1, 2] and not overlap._PRESTARTED and proc.poll() is not None
    overlap.prestart(("no_such_module_here",))   # its import fails: it reports and exits
    proc = overlap._PRESTARTED[0]
    overlap._stop_prestarted()
    assert not overlap._PRESTARTED and proc.poll() is not None


def test_image_stage_warm_up_tracks_its_synthetic_pair():
    """``vio.tracking.warm_up`` (run by a prestarted worker) goes through the whole stereo
    front end: a change of the front end's API must not turn it into a silent no-op
    (``_preload`` only reports a failing warm-up)."""
    from vio import tracking
    assert tracking.warm_up() is None


def test_worker_pipes_hold_the_primed_packets_without_blocking_the_parent():
    """Both pipes of a worker are widened (Linux): the primed packets (~1.5 KB each, two to
    a page of the default 16-page pipe) had filled the worker's stdin while it was still
    loading its kernels, and the parent waited there 0.5-0.8 s (real MH_01 stereo)."""
    fcntl = pytest.importorskip("fcntl")
    if not sys.platform.startswith("linux"):
        pytest.skip("F_SETPIPE_SZ is Linux-only")
    cap = Path("/proc/sys/fs/pipe-max-size")
    want = min(1 << 20, int(cap.read_text())) if cap.exists() else 1 << 20   # what _widen can get
    proc = overlap._worker_process()
    try:
        get = getattr(fcntl, "F_GETPIPE_SZ", 1032)
        assert fcntl.fcntl(proc.stdin.fileno(), get) >= want
        assert fcntl.fcntl(proc.stdout.fileno(), get) >= want
    finally:
        overlap._shutdown(proc)
