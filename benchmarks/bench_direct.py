"""``--mode direct`` / ``hybrid`` / ``stereo`` on one simulated stereo sequence with
exposure changes; prints a table, asserts nothing.

    python benchmarks/bench_direct.py [--data DIR] [--seconds 20] [--seed 3]
                                      [--modes direct,hybrid,stereo] [--max-frames N]
                                      [--config YAML]

Without ``--data`` the sequence (``vio sim --seconds S --seed N --exposure smooth``) is
generated once into ``$VIO_BENCH_CACHE`` (default ``~/.cache/vio-bench``). Columns:
ATE RMSE (m, SE3-aligned online estimate), time per frame over the frames after
initialization (ms; "frame" = everything between two pipeline outputs: image loading,
front end / photometric stage, backend), mean and p95, its backend-only part
(``FrameOutput.seconds``), keyframes, and the real-time factor (sequence duration / wall
time of the whole run, initialization included; > 1 is faster than real time), the CPU
seconds of the run (this process and the front-end worker, ``resource.getrusage``) and
the CPU-bound real-time factor (sequence duration / CPU seconds: on a shared machine
compare these, wall times are inflated by the other jobs), then the load average.
``--config``: a YAML file laid over each mode's defaults (``vio.run.load_config``), e.g.
a keyframe policy. Runs are sequential in one process (the machine has few cores; do
not run two at once).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from vio.evaluation import evaluate  # noqa: E402
from vio.io.euroc import load_euroc  # noqa: E402
from vio.run import load_config, run_dataset  # noqa: E402


def dataset(args: argparse.Namespace) -> Path:
    if args.data:
        return Path(args.data)
    from vio.sim import simulate
    from vio.sim.config import SimConfig
    cache = Path(os.environ.get("VIO_BENCH_CACHE", Path.home() / ".cache" / "vio-bench"))
    root = cache / f"direct_s{args.seed}_{args.seconds:g}s_exposure"
    if not (root / "mav0").is_dir():
        print(f"generating {root} ...", flush=True)
        simulate(root, SimConfig(seconds=args.seconds, seed=args.seed, exposure_changes="smooth"))
    return root


class FrameClock:
    """Sink: wall time between consecutive pipeline outputs (whole per-frame cost)."""

    def __init__(self) -> None:
        self.last: float | None = None
        self.dt: list[float] = []

    def __call__(self, out) -> None:
        now = time.perf_counter()
        if self.last is not None:
            self.dt.append(now - self.last)
        self.last = now


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and its waited-for children."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                 resource.getrusage(resource.RUSAGE_CHILDREN)))


def run_mode(data, mode: str, max_frames: int | None, config: Path | None = None) -> dict:
    clock = FrameClock()
    cfg = load_config(config, None, mode)
    c0, t0 = _cpu_s(), time.perf_counter()
    res = run_dataset(data, cfg, max_frames, sinks=[clock], mode=mode)
    wall, cpu = time.perf_counter() - t0, _cpu_s() - c0
    e = evaluate(*res.arrays(), data.groundtruth)
    ms = np.array(clock.dt) * 1e3
    be = np.array([o.seconds for o in res.outputs[1:]]) * 1e3
    return {"mode": mode, "ate": e.ate_rmse, "ms_mean": ms.mean(), "ms_p95": np.percentile(ms, 95),
            "be_mean": be.mean(), "keyframes": res.keyframes, "frames": res.frames_in,
            "recoveries": res.recoveries, "rtf": res.data_s / wall, "wall": wall, "cpu": cpu,
            "rtf_cpu": res.data_s / max(cpu, 1e-9)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", help="EuRoC/ASL folder with cam0+cam1 images and ground truth")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--modes", default="direct,hybrid,stereo")
    p.add_argument("--max-frames", type=int)
    p.add_argument("--config", type=Path, help="YAML overrides of every mode's defaults")
    args = p.parse_args(argv)
    data = load_euroc(dataset(args))
    rows = []
    for mode in args.modes.split(","):
        print(f"running --mode {mode} ...", flush=True)
        rows.append(run_mode(data, mode, args.max_frames, args.config))
    print(f"\n{'mode':8s} {'ATE [m]':>8s} {'ms/frame':>9s} {'p95 [ms]':>9s} {'backend':>8s} "
          f"{'kf':>5s} {'frames':>6s} {'recov':>5s} {'RTF':>6s} {'wall [s]':>8s} {'CPU [s]':>8s} {'RTF cpu':>7s}")
    for r in rows:
        print(f"{r['mode']:8s} {r['ate']:8.4f} {r['ms_mean']:9.1f} {r['ms_p95']:9.1f} "
              f"{r['be_mean']:8.1f} {r['keyframes']:5d} {r['frames']:6d} {r['recoveries']:5d} "
              f"{r['rtf']:6.2f} {r['wall']:8.1f} {r['cpu']:8.1f} {r['rtf_cpu']:7.2f}")
    print("load average (1, 5, 15 min): " + ", ".join(f"{x:.2f}" for x in os.getloadavg()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
