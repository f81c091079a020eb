"""The backend's CPU seconds by stage, measured with ``time.process_time`` (not cProfile).

    python benchmarks/backend_cpu.py DATASET [--mode stereo|mono|features] [--config Y.yaml]

Runs ``vio.run.run_dataset`` in this process and wraps a few backend functions with CPU
timers (``time.process_time``: this process only, so the front-end worker and the other
jobs on a shared machine do not count; cProfile's ~2x inflation of Python code is
avoided). Prints the main process's CPU seconds, the keyframe update's total and its
parts (nested: a line's seconds include the lines indented under it), ATE, and iSAM2's
figures per keyframe update: variables in the window, variables re-eliminated, factors
recalculated. Used for the eliminated-depth comparison (``VisionConfig.eliminate_depth``)
in the README.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent)]

# (label, module, object, attribute, indent)
TIMERS = [
    ("keyframe update (Estimator.add_keyframe)", "vio.backend.estimator", "Estimator", "add_keyframe", 0),
    ("smoother updates incl. callbacks", "vio.backend.estimator", "Estimator", "_update", 1),
    ("bundle linearization kernel", "factors.landmark_schur", None, "linearize", 2),
    ("bundle square root", "factors.landmark_schur", None, "square_root", 2),
    ("factor construction (prepare_update)", "vio.backend.tracks", "LandmarkManager", "prepare_update", 1),
    ("factor construction (prepare_update)", "vio.backend.bundles", "EliminatedLandmarks", "prepare_update", 1),
    ("per-track arrays of the bundles", "vio.backend.bundles", "EliminatedLandmarks", "_landmark", 2),
    ("outlier check", "vio.backend.tracks", "LandmarkManager", "outlier_removals", 1),
    ("outlier check", "vio.backend.bundles", "EliminatedLandmarks", "outlier_removals", 1),
    ("depth refinement at the estimate", "factors.landmark_schur", None, "refine", 2),
]


def _wrap(table: collections.Counter, label: str, module: str, obj: str | None, attr: str) -> None:
    import importlib
    owner = importlib.import_module(module)
    owner = getattr(owner, obj) if obj else owner
    f = getattr(owner, attr)

    def timed(*a, **k):
        t = time.process_time()
        try:
            return f(*a, **k)
        finally:
            table[label] += time.process_time() - t

    setattr(owner, attr, timed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--mode", default="auto")
    ap.add_argument("--config", type=Path, default=None)
    a = ap.parse_args(argv)
    from vio.backend.estimator import Estimator
    from vio.evaluation import evaluate
    from vio.io.euroc import LoadOptions, load_euroc
    from vio.run import load_config, resolve_mode, run_dataset

    table: collections.Counter = collections.Counter()
    seen = set()
    for label, module, obj, attr, _ in TIMERS:
        if (module, obj, attr) not in seen:
            seen.add((module, obj, attr))
            _wrap(table, label, module, obj, attr)
    stats = []
    update = Estimator._update

    def spy(self, g, v, stamps, removals):
        update(self, g, v, stamps, removals)
        r = self.smoother.getISAM2Result()
        stats.append((self.values.size(), r.getVariablesReeliminated(), r.getFactorsRecalculated()))

    Estimator._update = spy
    data = load_euroc(a.dataset, LoadOptions())
    mode = resolve_mode(data, a.mode)
    cfg = load_config(a.config, None, mode)
    t0 = time.process_time()
    res = run_dataset(data, cfg, None, mode=mode)
    cpu = time.process_time() - t0
    print(f"{a.dataset} mode {mode}{' config ' + str(a.config) if a.config else ''}: "
          f"{res.keyframes} keyframes, main process CPU {cpu:.2f} s")
    printed = set()
    for label, _, _, _, indent in TIMERS:
        if label in printed:
            continue
        printed.add(label)
        if label in table:
            print(f"  {'  ' * indent}{label:{44 - 2 * indent}s} {table[label]:6.2f} s")
    if stats:
        n = max(len(stats), 1)
        print(f"  iSAM2 per update: {sum(s[0] for s in stats) / n:.0f} variables, "
              f"{sum(s[1] for s in stats) / n:.0f} re-eliminated, {sum(s[2] for s in stats) / n:.0f} "
              f"factors recalculated ({len(stats)} updates)")
    print(f"  ATE {evaluate(*res.arrays(), data.groundtruth).ate_rmse:.4f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
