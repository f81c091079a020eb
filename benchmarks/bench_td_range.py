"""td over its whole range on tracks from another generator (issue 20: unbiased from -30
to +30 ms on any reasonable track source).

    python benchmarks/bench_td_range.py [--variant boxwall] [--sequences MH_03_medium,V1_03_difficult,V2_01_easy]
                                        [--td-ms=-30,-20,-10,0,10,20,30] [--seed 430] [--seconds 60]
                                        [--baseline]

For each sequence, tracks of ``vio.sim.variants.VARIANTS[variant]`` (default issue 20's
generator) are generated from ``../shared/data/euroc_imu_gt/SEQ`` (60 s from 1 s after the
first ground-truth row, as the suite's variant rows) at every true td, all with the same
seed (default 430, a seed no development run used; the suite's variant rows use 400-420),
and ``vio run --mode features`` runs on each with the sync layer at 0, so the estimator
finds td. Printed per run: the true and estimated td (ms) and the error, ATE (m and % of
the path, SE3-aligned online estimate) and its ratio to the sequence's td = 0 run; with
``--baseline`` also the GTSAM-native baseline on our keyframes told the true td
(``benchmarks/baseline_gtsam.py``; it has no td factor) and its own ratio. Generated
tracks are cached as the suite's (``datasets.prepare``). Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads: bit-reproducible runs (vio.threads)

import datasets as ds  # noqa: E402

DEFAULT_TD_MS = (-30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0)


def specs(variant: str, sequences: list[str], td_ms: list[float], seed: int,
          seconds: float) -> list[ds.DatasetSpec]:
    """The runs, sequence by sequence, each sequence's td = 0 run included."""
    from vio.sim.variants import VARIANTS
    if variant not in VARIANTS:
        raise SystemExit(f"--variant: {variant!r} is not one of {sorted(VARIANTS)}")
    tds = sorted(set(td_ms) | {0.0})
    return [ds._variant_spec(variant, VARIANTS[variant], seq, td * 1e-3, seed, seconds)
            for seq in sequences for td in tds]


def run_one(spec: ds.DatasetSpec, baseline: bool) -> dict:
    """Ours (and the baseline told the true td) on one generated set: a row of the table."""
    from baseline_gtsam import run_baseline
    from baseline_stereo import told_true_td
    from schedule import record_schedule
    from vio.evaluation import evaluate
    from vio.io.euroc import load_euroc
    from vio.run import default_config
    path = ds.prepare(spec)
    data = load_euroc(path)
    td_true = ds.true_td_s(spec, path)
    cfg = default_config("features")
    res, sched = record_schedule(data, cfg)
    ev = evaluate(*res.arrays(), data.groundtruth)
    row = {"name": spec.name, "group": spec.group, "td_true_ms": td_true * 1e3,
           "td_ms": res.outputs[-1].td_s * 1e3, "ate": ev.ate_rmse, "pct": 100 * ev.ate_rmse / ev.path_length}
    if baseline:
        b = run_baseline(data, *told_true_td(sched, cfg, td_true))
        row["base"] = evaluate(*b.arrays(), data.groundtruth).ate_rmse
    return row


def table(rows: list[dict]) -> list[str]:
    """The printed table: each row against its sequence's td = 0 run."""
    zero = {r["group"]: r for r in rows if abs(r["td_true_ms"]) < 0.01}
    out = [f"{'run':44s} {'true td':>8s} {'td':>8s} {'error':>7s} {'ATE m':>7s} {'% path':>7s} "
           f"{'/ td0':>6s} {'base m':>7s} {'/ td0':>6s}"]
    for r in rows:
        z = zero.get(r["group"], {})
        ratio = r["ate"] / z["ate"] if z.get("ate") else float("nan")
        base = r.get("base", float("nan"))
        bratio = base / z["base"] if z.get("base") else float("nan")
        out.append(f"{r['name']:44s} {r['td_true_ms']:8.2f} {r['td_ms']:8.2f} {r['td_ms'] - r['td_true_ms']:+7.2f} "
                   f"{r['ate']:7.4f} {r['pct']:7.3f} {ratio:6.2f} {base:7.4f} {bratio:6.2f}")
    err = [abs(r["td_ms"] - r["td_true_ms"]) for r in rows]
    out.append(f"td error max {max(err):.2f} ms, {sum(e <= 0.5 for e in err)} of {len(err)} within 0.5 ms; "
               f"ATE max {max(r['pct'] for r in rows):.3f} % of the path")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", default="boxwall")
    ap.add_argument("--sequences", default=",".join(ds.VARIANT_SEQUENCES))
    ap.add_argument("--td-ms", default=",".join(f"{t:g}" for t in DEFAULT_TD_MS))
    ap.add_argument("--seed", type=int, default=430)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--baseline", action="store_true", help="also the GTSAM-native baseline told the true td")
    a = ap.parse_args(argv)
    todo = specs(a.variant, a.sequences.split(","), [float(t) for t in a.td_ms.split(",")], a.seed, a.seconds)
    rows = []
    for s in todo:
        rows.append(run_one(s, a.baseline))
        print(table(rows)[-2], flush=True)
    print("\n".join(["", *table(rows)]))


if __name__ == "__main__":
    main()
