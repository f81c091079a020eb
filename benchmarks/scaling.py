"""Scaling: time per frame (ours and the GTSAM-native baseline) vs features and window.

Data: generated feature tracks on an excerpt of V1_02_medium (real IMU and ground
truth, td 5 ms, fixed seed). Features: ``max_features`` 50/100/200/400 (the room's
point density grows with it so that enough points are visible). Window: smoother
lag 1/2/4/8 s at 100 features. Each point runs ours, then the baseline on our
keyframes, in subprocesses (``run_all.compare``).

    python benchmarks/scaling.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]

import datasets as ds  # noqa: E402

SEQUENCE = "V1_02_medium"
SEED = 300
LAG_FEATURES = 100


def _density(n: int) -> float:
    """Room points per m^2 for ``n`` features per frame (the generator's default is 8)."""
    return max(8.0, n / 5.0)


def _point(row: dict, **extra) -> dict:
    """The figures of one scaling point (both systems)."""
    out = dict(extra)
    for sys_ in ("ours", "baseline"):
        m = row[sys_]
        out[sys_] = {"frame_ms": m.get("frame_ms"), "ate_rmse": m.get("ate_rmse"), "rtf": m.get("rtf"),
                     "landmarks_p50": m.get("landmarks_p50"), "peak_rss_mb": m.get("peak_rss_mb"),
                     "error": m.get("error")}
    out["ratio_time"] = row["ratio"]["time"]
    return out


def run_scaling(quick: bool, log=print) -> dict:
    """Both sweeps; returns ``{"features": [...], "lag": [...], "dataset": ...}``."""
    from run_all import compare
    seconds = 15.0 if quick else 20.0
    feats = (50, 100, 200) if quick else (50, 100, 200, 400)
    lags = (1.0, 2.0, 4.0) if quick else (1.0, 2.0, 4.0, 8.0)
    base = ds.generated_spec(SEQUENCE, ds.TD_TRUE_S, SEED, 0.0, seconds, group="scaling")
    res: dict = {"dataset": base.name, "seconds": seconds, "features": [], "lag": []}
    for n in feats:
        spec = ds.with_overrides(base, f"/f{n}", max_features=n, points_per_m2=_density(n))
        row = compare(spec, ds.prepare(spec), log=log)
        res["features"].append(_point(row, features=n))
    spec = ds.with_overrides(base, f"/f{LAG_FEATURES}", max_features=LAG_FEATURES,
                             points_per_m2=_density(LAG_FEATURES))
    path = ds.prepare(spec)
    for lag in lags:
        row = compare(ds.with_overrides(spec, f"/lag{lag:g}"), path,
                      overrides={"backend.solver.lag_s": lag}, log=log)
        res["lag"].append(_point(row, lag_s=lag, features=LAG_FEATURES))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args(argv)
    res = run_scaling(args.quick)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
