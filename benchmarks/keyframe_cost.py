"""Per-keyframe cost of a run: wall time of ``Estimator.add_keyframe`` (factor construction,
smoother update, outlier check), the smoother updates inside it, the window's size, and the
split between keyframes on the configured factorization and those on QR after a Cholesky
refusal (``vio.backend.smoother``). Prints a table, asserts nothing.

    python benchmarks/keyframe_cost.py DATASET [--mode mono] [--config FILE] [--per-keyframe]

The per-frame latency (p95, max) follows the keyframe cost: a keyframe's frame waits for its
update. Timings are wall clock (``time.perf_counter``) in this process, so a loaded machine
inflates them; compare runs on the same machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads (vio.threads)

import gtsam  # noqa: E402
import numpy as np  # noqa: E402

from vio.backend import estimator as est_mod, smoother  # noqa: E402
from vio.io.euroc import load_euroc  # noqa: E402
from vio.run import load_config, run_dataset  # noqa: E402


def measure(data: Path, mode: str, config: Path | None) -> list[tuple]:
    """(seconds, smoother-update seconds, variables, world points, keyframes in the window,
    on the configured factorization) per keyframe."""
    rows, upd = [], []
    add, update = est_mod.Estimator.add_keyframe, smoother.update

    def timed_update(sm, *a):
        t = time.perf_counter()
        update(sm, *a)
        upd.append(time.perf_counter() - t)

    def timed_add(self, *a, **k):
        upd.clear()
        t = time.perf_counter()
        out = add(self, *a, **k)
        keys = list(self.values.keys())
        n_p = sum(1 for key in keys if gtsam.Symbol(key).chr() == ord("p"))
        rows.append((time.perf_counter() - t, sum(upd), len(keys), n_p, len(self.kf_t),
                     self.smoother_factorization == self.home_factorization))
        return out

    est_mod.Estimator.add_keyframe, smoother.update = timed_add, timed_update
    try:
        run_dataset(load_euroc(data), load_config(config, mode=mode), mode=mode)
    finally:
        est_mod.Estimator.add_keyframe, smoother.update = add, update
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--mode", default="mono")
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--per-keyframe", action="store_true")
    a = ap.parse_args()
    rows = measure(a.data, a.mode, a.config)
    R = np.array(rows, float)[5:]          # the first keyframes after initialization are small
    if not len(R):
        sys.exit("fewer than 6 keyframes")
    ms = 1e3 * R[:, 0]
    print(f"{a.data.name} {a.mode}: {len(R)} keyframes, add_keyframe mean {ms.mean():.1f} / p50 "
          f"{np.median(ms):.1f} / p90 {np.percentile(ms, 90):.1f} / max {ms.max():.1f} ms; smoother "
          f"updates {1e3 * R[:, 1].mean():.1f} ms; window {R[:, 2].mean():.0f} variables, "
          f"{R[:, 3].mean():.0f} world points, {R[:, 4].mean():.1f} keyframes")
    home = R[:, 5] == 1
    mean = [ms[m].mean() if m.any() else 0.0 for m in (home, ~home)]
    print(f"configured factorization: {home.sum()} keyframes, mean {mean[0]:.1f} ms; "
          f"QR after a refusal: {(~home).sum()} keyframes, mean {mean[1]:.1f} ms")
    if a.per_keyframe:
        for i, (r, m) in enumerate(zip(R, ms)):
            print(f"{i + 5:4d} {m:7.1f} ms  update {1e3 * r[1]:6.1f} ms  {int(r[2]):4d} variables  "
                  f"{int(r[3]):4d} points  {'' if r[5] else 'QR'}")


if __name__ == "__main__":
    main()
