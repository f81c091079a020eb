"""Per-frame backend time of a run, split by the frame's role (issue 17's latency).

    python benchmarks/frame_times.py DATASET [--mode stereo] [--config A.yaml [--config B.yaml ...]]
                                     [--rounds 3]

Runs ``vio.run.run_dataset`` in this process (the KLT front end in its worker process as
``vio run`` does) and prints, for the frames after initialization, the pipeline's own
time per frame (``FrameOutput.seconds``: from the packet's arrival in the pipeline to its
output; the front end's work is the worker's) as mean / p50 / p95 / max, for all frames,
the keyframes, the frame after each keyframe (where ``SolverConfig.outlier_update`` and
``bookkeeping`` "next_frame" put their work) and the others; and the sum. With several
``--config`` files (``-`` for the mode's defaults) the runs alternate, ``--rounds`` times,
so that a shared machine's slow periods hit every variant alike. Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads: bit-reproducible runs (vio.threads)

import numpy as np  # noqa: E402

from vio.io.euroc import load_euroc  # noqa: E402
from vio.run import default_config, load_config, resolve_mode, run_dataset  # noqa: E402


def split(outputs: list) -> dict[str, np.ndarray]:
    """Per-frame times (ms) by role: all, keyframe, after a keyframe, other."""
    ms = np.array([o.seconds for o in outputs]) * 1e3
    kf = np.array([o.keyframe for o in outputs], bool)
    after = np.r_[False, kf[:-1]] & ~kf
    return {"all": ms, "keyframe": ms[kf], "after keyframe": ms[after], "other": ms[~kf & ~after]}


def line(name: str, v: np.ndarray) -> str:
    if not len(v):
        return f"  {name:15s} n=   0"
    return (f"  {name:15s} n={len(v):4d} mean {v.mean():6.1f} p50 {np.percentile(v, 50):6.1f} "
            f"p95 {np.percentile(v, 95):6.1f} max {v.max():6.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--mode", default="auto")
    ap.add_argument("--config", action="append", default=None,
                    help="YAML overrides ('-': the mode's defaults); repeat to alternate variants")
    ap.add_argument("--rounds", type=int, default=1)
    a = ap.parse_args()
    data = load_euroc(a.dataset)
    mode = resolve_mode(data, a.mode)
    configs = a.config or ["-"]
    for r in range(a.rounds):
        for c in configs:
            cfg = default_config(mode) if c == "-" else load_config(Path(c), mode=mode)
            res = run_dataset(data, cfg, mode=mode)
            parts = split(res.outputs[res.n_init:])
            print(f"round {r + 1}, config {c}: {len(parts['all'])} frames after initialization, "
                  f"sum {parts['all'].sum() / 1e3:.2f} s")
            for name, v in parts.items():
                print(line(name, v))


if __name__ == "__main__":
    main()
