"""Where a run's time goes: the backend's cost by stage, from cProfile.

    python benchmarks/bench_profile.py DATASET [--mode stereo|mono|features] [--max-frames N]
                                       [--no-profile] [--stats FILE.prof]

Runs ``vio.run.run_dataset`` in this process (the KLT front end in its worker process,
as ``vio run`` does) and prints: CPU seconds of this process and of the front-end worker
(``resource.getrusage``, load-independent: compare these across commits on a shared
machine), wall time and the real-time factor, per-frame time mean / p95 / max after
initialization (``RunResult.frame_ms``) and split into keyframes, the frames after a
keyframe and the rest, ATE, and, unless ``--no-profile``, the
main process's time by stage:

* ``front end wait``: the main process waiting for the worker (``select``);
* ``initialization``: ``vio.start.Start.initialize`` without the frames it replays;
* ``IMU preintegration``: ``vio.imu.integrate`` and the per-frame IMU prediction;
* ``factor construction``: ``LandmarkManager.prepare_update`` and the extra factor
  sources (the photometric points);
* ``linearization callbacks``: Python ``CustomFactor`` evaluations inside iSAM2;
* ``iSAM2 (C++)``: ``IncrementalFixedLagSmoother.update`` without the callbacks:
  relinearization bookkeeping, elimination, the back-substitution and the fixed-lag
  marginalization (cProfile cannot split the C++);
* ``outlier check``: reprojection errors of every landmark after each update;
* ``outlier update``: the second smoother update that removes rejected landmarks;
* ``output``: ``Pipeline.emit`` (estimate, landmarks, sinks) and the run loop's bookkeeping.

cProfile slows Python-heavy code by ~1.5-2x: read the shares, not the absolute seconds,
and time with ``--no-profile``.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import resource
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent)]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads, as `vio run` (vio.threads)

# (stage, [(file suffix, function name, "cum" | "tot")]); a stage's seconds are the sum
# of its entries; entries nested in another stage's entry are subtracted there (below)
STAGES = [
    ("front end wait", [("~", "<built-in method select.select>", "tot")]),
    ("initialization", [("vio/start.py", "initialize", "cum")]),
    ("IMU preintegration", [("vio/imu.py", "integrate", "cum"), ("vio/backend/estimator.py", "predict", "cum")]),
    ("factor construction", [("vio/backend/tracks.py", "prepare_update", "cum"),
                             ("vio/backend/bundles.py", "prepare_update", "cum"),
                             ("vio/direct/source.py", "prepare_update", "cum")]),
    ("linearization callbacks", [("factors/adapter.py", "error_func", "cum")]),
    # the C++ update runs inside vio.backend.smoother.update; cProfile records no call event
    # for it (pybind11), so that function's own time is the C++ update's
    ("iSAM2 (C++)", [("~", "<method 'update' of 'gtsam.gtsam.IncrementalFixedLagSmoother' objects>", "tot"),
                     ("~", "<built-in method gtsam.gtsam.update>", "tot"),
                     ("vio/backend/smoother.py", "update", "tot")]),
    ("outlier check", [("vio/backend/tracks.py", "outlier_removals", "cum"),
                       ("vio/backend/bundles.py", "outlier_removals", "cum")]),
    ("outlier update", [("vio/backend/estimator.py", "_remove_outliers", "cum")]),
    ("output", [("vio/pipeline.py", "emit", "cum"), ("vio/backend/estimator.py", "window_poses", "cum")]),
]


def _lookup(stats: pstats.Stats, suffix: str, name: str, kind: str) -> float:
    total = 0.0
    for (file, _, fn), (cc, nc, tt, ct, _) in stats.stats.items():
        if fn == name and (file.endswith(suffix) or (suffix == "~" and file == "~")):
            total += ct if kind == "cum" else tt
    return total


def breakdown(stats: pstats.Stats) -> dict[str, float]:
    """Seconds per stage (see the module docstring). The outlier update's smoother update
    and callbacks are counted by their own stages, so the check is subtracted from it;
    ``initialization`` includes the frames a dynamic start replays (an upper bound)."""
    out = {name: sum(_lookup(stats, *e) for e in entries) for name, entries in STAGES}
    out["outlier update"] = max(0.0, out["outlier update"] - out["outlier check"])
    return out


def latency_by_kind(res) -> list[str]:
    """Per-frame backend time (ms, ``FrameOutput.seconds``) after initialization, split by
    what the frame carries: a keyframe's update, the frame after a keyframe (the deferred
    outlier update and bookkeeping, ``SolverConfig.outlier_update`` / ``bookkeeping``),
    and the rest (IMU propagation and output). A run's p95 is set by the first two."""
    import numpy as np
    ms = res.frame_ms()
    if not ms.size:
        return []
    kf = np.array([bool(o.keyframe) for o in res.outputs[res.n_init:]])
    after = np.r_[False, kf[:-1]] & ~kf
    lines = []
    for name, m in (("keyframe", kf), ("after keyframe", after), ("other", ~kf & ~after)):
        if m.any():
            x = ms[m]
            lines.append(f"  {name:15s} {int(m.sum()):4d} frames  mean {x.mean():6.1f}  p50 {np.median(x):6.1f}  "
                         f"p90 {np.percentile(x, 90):6.1f}  max {x.max():6.1f} ms")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--mode", default="auto")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--config", type=Path, default=None, help="YAML overrides")
    ap.add_argument("--no-profile", action="store_true")
    ap.add_argument("--stats", type=Path, default=None, help="write the raw cProfile stats here")
    ap.add_argument("--out", type=Path, default=None, help="TUM trajectory")
    a = ap.parse_args(argv)
    from vio.io.euroc import LoadOptions, load_euroc
    from vio.run import load_config, resolve_mode, run_dataset
    from vio.run_summary import summary
    from vio.trajectory import write_tum

    data = load_euroc(a.dataset, LoadOptions())
    mode = resolve_mode(data, a.mode)
    cfg = load_config(a.config, None, mode)
    load0 = os.getloadavg()[0]
    ru0, rc0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    prof = None if a.no_profile else cProfile.Profile()
    t0 = time.perf_counter()
    if prof:
        prof.enable()
    res = run_dataset(data, cfg, a.max_frames, mode=mode)
    if prof:
        prof.disable()
    wall = time.perf_counter() - t0
    ru1, rc1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_main = ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime
    cpu_worker = rc1.ru_utime + rc1.ru_stime - rc0.ru_utime - rc0.ru_stime
    if a.out:
        t, _, _ = res.arrays()
        write_tum(a.out, t, [o.T_w_b for o in res.outputs])
    print(f"{a.dataset} mode {mode}: {res.frames_in} frames, {res.keyframes} keyframes, "
          f"load {load0:.1f} -> {os.getloadavg()[0]:.1f}{' (cProfile on)' if prof else ''}")
    print(f"CPU main {cpu_main:.2f} s, worker {cpu_worker:.2f} s; wall {wall:.2f} s for "
          f"{res.data_s:.1f} s of data (CPU-bound real-time factor "
          f"{res.data_s / max(cpu_main, cpu_worker, 1e-9):.2f}x)")
    for line in summary(res, data):
        print(line)
    print("time per frame by kind (after initialization):")
    for line in latency_by_kind(res):
        print(line)
    if prof:
        st = pstats.Stats(prof)
        b = breakdown(st)
        total = sum(tt for (_, _, _), (_, _, tt, _, _) in st.stats.items())
        print(f"\nmain process by stage (cProfile, {total:.1f} s profiled):")
        for name, _ in STAGES:
            print(f"  {name:26s} {b[name]:7.2f} s  {100 * b[name] / total:5.1f} %")
        print("  (initialization includes the replayed frames of a dynamic start)")
        if a.stats:
            st.dump_stats(str(a.stats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
