"""Group a py-spy raw profile of a run by backend stage (the shares in README.md).

    py-spy record -r 200 -f raw -o prof.raw -- python benchmarks/bench_profile.py DATASET --no-profile
    python benchmarks/spy_stages.py prof.raw

Each sample goes to the first stage in ``STAGES`` whose marker (a function name as py-spy
prints it) is on its stack, so nested work is counted once, under the innermost listed
stage that applies (callbacks inside the outlier update count as callbacks). Shares are of
the per-frame work: start-up (imports, data loading), initialization and waiting for the
front-end worker are listed but left out of the denominator. py-spy samples wall-clock
time of running threads: read the shares, and take CPU seconds from ``bench_profile.py``.
"""

from __future__ import annotations

import argparse
import collections

STAGES = [  # (stage, marker on the stack); the first match wins
    ("initialization", "start.py:"),
    ("linearization callbacks (Python)", "error_func ("),
    ("factor construction: residual rows and td velocities", "track_rows ("),
    ("factor construction: landmark factors", "_factor ("),
    ("factor construction: re-anchoring", "_hand_over ("),
    ("factor construction: new landmarks", "_try_insert ("),
    ("factor construction: the rest", "prepare_update ("),
    ("outlier check", "outlier_removals ("),
    ("outlier update (iSAM2, C++)", "_remove_outliers ("),
    ("iSAM2 update (C++)", "_update ("),
    ("divergence check", "_check_health ("),
    ("IMU preintegration and prediction", "integrate"),
    ("IMU preintegration and prediction", "predict ("),
    ("front end: waiting for the worker", "select"),
    ("output", ";emit ("),
    ("keyframe bookkeeping", "add_keyframe ("),
    ("start-up", "<module>"),
]
SKIP = {"initialization", "start-up", "front end: waiting for the worker"}


def stage_samples(path: str) -> collections.Counter:
    """Samples per stage of a ``py-spy record -f raw`` file (``other``: none matched)."""
    out: collections.Counter = collections.Counter()
    with open(path) as fh:
        for line in fh:
            line = line.rstrip()
            if not line:
                continue
            stack, count = line.rsplit(" ", 1)
            out[next((name for name, marker in STAGES if marker in stack), "other")] += int(count)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("raw", help="py-spy raw output (-f raw)")
    a = ap.parse_args(argv)
    c = stage_samples(a.raw)
    work = sum(v for k, v in c.items() if k not in SKIP)
    print(f"{sum(c.values())} samples, {work} of them per-frame work")
    for name, v in c.most_common():
        share = "" if name in SKIP else f"{100 * v / max(work, 1):5.1f} % of the work"
        print(f"  {name:46s} {v:6d}  {share}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
