"""Sensor faults on the real V1_01 input (issue 16): IMU gaps, spikes, dropped frames,
with and without the fault handling; the screen on every clean real IMU file; the
divergence monitor's worst values on clean runs. Prints tables, asserts nothing.

    python benchmarks/bench_faults.py [--at 15 | --at 4,7,11,15,19,23,27] [--columns none,monitor,full]
                                      [--monitor-modes features,mono,stereo]

Faults are injected into copies of ``../shared/data/euroc_V1_01_30s_features`` written to a
temporary folder (``vio.inject``), ``--at`` seconds after its first IMU sample (in flight).
ATE RMSE (m, SE3-aligned online estimate, all frames) per handling level: ``none`` (the
behaviour before issue 16: ``ImuScreenConfig(enabled=False, max_gap_periods=inf)`` and
``HealthConfig(enabled=False)``: gaps preintegrated as one long interpolated interval,
spikes integrated), ``monitor`` (only the divergence monitor and its soft restarts), ``full``
(the defaults); then, for ``full``: IMU gaps bridged, samples dropped, divergence restarts,
frames estimated, wall time (s; the machine is shared, so wall times are inflated by
contention). Runs are sequential.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import math
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads: bit-reproducible runs (vio.threads)

from vio import inject  # noqa: E402
from vio.evaluation import evaluate  # noqa: E402
from vio.faults import ImuScreenConfig, _hampel, screen_imu  # noqa: E402
from vio.io.euroc import load_euroc, read_imu_csv  # noqa: E402
from vio.run import default_config, run_dataset  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
V1_01 = SHARED / "euroc_V1_01_30s_features"


def scenarios(at: float) -> list[tuple[str, object]]:
    return [
        ("clean", lambda r: None),
        (f"IMU gap 0.5 s at {at:g} s", lambda r: inject.imu_gap(r, at, 0.5)),
        (f"IMU gap 3 s at {at:g} s", lambda r: inject.imu_gap(r, at, 3.0)),
        ("accel sample 200 m/s^2", lambda r: inject.imu_spike(r, at, accel=(200.0, 0.0, 0.0))),
        ("gyro sample 5 rad/s", lambda r: inject.imu_spike(r, at, gyro=(0.0, 5.0, 0.0))),
        ("camera frames dropped 0.5 s", lambda r: inject.drop_frames(r, at, 0.5)),
        ("gap 0.5 s + spike + drops", lambda r: (inject.imu_gap(r, at, 0.5), inject.imu_spike(
            r, at + 3, accel=(0.0, -150.0, 0.0)), inject.drop_frames(r, at + 6, 0.3))),
        ("accel offset +6 m/s^2 for 1 s", lambda r: inject.imu_offset(r, at, 1.0, (6.0, 0.0, 0.0))),
    ]


def run(root: Path, level: str) -> dict:
    cfg = default_config("features")
    if level in ("none", "monitor"):
        cfg = dataclasses.replace(cfg, imu_screen=ImuScreenConfig(enabled=False, max_gap_periods=math.inf))
    if level == "none":
        cfg = dataclasses.replace(cfg, backend=dataclasses.replace(
            cfg.backend, health=dataclasses.replace(cfg.backend.health, enabled=False)))
    data = load_euroc(root)
    t = time.perf_counter()
    res = run_dataset(data, cfg, mode="features")
    wall = time.perf_counter() - t
    ate = evaluate(*res.arrays(), data.groundtruth).ate_rmse
    return dict(ate=ate, gaps=res.imu_gaps, dropped=res.imu_dropped, restarts=res.restarts,
                est=len(res.outputs), n=res.frames_in, wall=wall)


TARGETS = (("IMU gap 0.5 s", 1, 0.05), ("IMU gap 3 s", 2, 0.15), ("accel sample 200 m/s^2", 3, 0.04))
"""Issue 16's bounds (ATE m): (label, row of ``scenarios``, bound)."""


def fault_table(at: float, columns: list[str], only: list[int] | None = None) -> list[float]:
    """Print the scenarios at ``at`` s (``only``: those rows of ``scenarios``); returns the
    last column's ATE per scenario (NaN for those left out)."""
    print(f"\nFaults on real V1_01 features (30 s, 8.2 m), injected {at:g} s in; ATE RMSE (m)")
    print(f"{'scenario':32s} " + " ".join(f"{c:>8s}" for c in columns) +
          f" {'gaps':>5s} {'drop':>5s} {'rest.':>5s} {'frames':>9s} {'wall s':>7s}")
    ates: list[float] = []
    with tempfile.TemporaryDirectory(prefix="bench_faults_") as tmp:
        for row, (name, fault) in enumerate(scenarios(at)):
            if only is not None and row not in only:
                ates.append(float("nan"))
                continue
            root = inject.copy_dataset(V1_01, Path(tmp) / "run")
            fault(root)
            r = {c: run(root, c) for c in columns}
            last = r[columns[-1]]
            print(f"{name:32s} " + " ".join(f"{r[c]['ate']:8.4f}" for c in columns) +
                  f" {last['gaps']:5d} {last['dropped']:5d} {last['restarts']:5d} "
                  f"{last['est']:4d}/{last['n']:<4d} {last['wall']:7.1f}", flush=True)
            ates.append(last["ate"])
    return ates


def target_table(times: list[float], ates: list[list[float]]) -> None:
    """Issue 16's fault bounds at every injection time (the last column's handling)."""
    print("\nIssue 16 bounds by injection time (ATE m; * over the bound)")
    print(f"{'fault':24s} {'bound':>6s} " + " ".join(f"{t:>7g}s" for t in times) + "   met")
    for label, row, bound in TARGETS:
        vals = [a[row] for a in ates]
        if all(math.isnan(v) for v in vals):
            continue
        print(f"{label:24s} {bound:6.2f} " + " ".join(f"{v:7.3f}{'*' if v > bound else ' '}" for v in vals)
              + f"   {sum(v <= bound for v in vals)}/{len(vals)}")


def screen_table() -> None:
    print("\nIMU screen on the clean real IMU files (must flag nothing; k = "
          f"{ImuScreenConfig().spike_k:g})")
    print(f"{'file':28s} {'samples':>8s} {'dropped':>8s} {'gaps':>5s} {'max accel':>10s} {'max gyro':>9s}")
    c = ImuScreenConfig()
    files = sorted(glob.glob(str(SHARED / "*" / "mav0" / "imu0" / "data.csv")) +
                   glob.glob(str(SHARED / "euroc_imu_gt" / "*" / "mav0" / "imu0" / "data.csv")))
    for f in files:
        imu = read_imu_csv(Path(f))
        _, gaps, n = screen_imu(imu)
        m = len(imu)
        sa = _hampel(imu.accel, 0, m, c.half_window, c.spread_window, c.accel_floor, c.spike_k)[1].max()
        sw = _hampel(imu.gyro, 0, m, c.half_window, c.spread_window, c.gyro_floor, c.spike_k)[1].max()
        print(f"{Path(f).parts[-4]:28s} {m:8d} {n:8d} {len(gaps):5d} {sa:10.1f} {sw:9.1f}")


def monitor_table(modes: list[str]) -> None:
    import vio.run as vrun
    print("\nDivergence monitor on clean real runs: worst values (limits: speed "
          "30 m/s, bias 10 sigmas, inlier ratio 0.5, IMU chi2 1e4)")
    sets = {"features": V1_01, "mono": SHARED / "euroc_MH_05_mono_15s",
            "stereo": SHARED / "euroc_MH_01_stereo_synimu"}
    for mode in modes:
        holder = {}
        base = vrun.Pipeline

        class Spy(base):
            def __init__(self, *a, **k):
                super().__init__(*a, **k)
                holder["p"] = self
        vrun.Pipeline = Spy
        try:
            data = load_euroc(sets[mode])
            res = run_dataset(data, mode=mode)
        finally:
            vrun.Pipeline = base
        pk = holder["p"].est.health.peaks
        ate = evaluate(*res.arrays(), data.groundtruth).ate_rmse
        print(f"{mode:9s} {sets[mode].name:28s} speed {pk['speed']:.2f} m/s, bias "
              f"{pk['bias_sigmas']:.1f} sigmas, inlier ratio {pk['inlier_ratio']:.2f}, IMU chi2 "
              f"{pk['imu_chi2']:.0f}; restarts {res.restarts}, ATE {ate:.4f} m")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--at", default="15", help="comma list of injection times (s after the first IMU "
                    "sample), e.g. 4,7,11,15,19,23,27; more than one adds the bounds table")
    ap.add_argument("--columns", default="none,full", help="comma list of none,monitor,full")
    ap.add_argument("--monitor-modes", default="features", help="comma list of features,mono,stereo")
    ap.add_argument("--bounds-only", action="store_true", help="run only the scenarios issue 16 bounds "
                    "(e.g. --at 3,3.5,...,12 --columns full --monitor-modes '' for a dense sweep)")
    a = ap.parse_args()
    if not V1_01.exists():
        sys.exit(f"{V1_01} not found (../shared/data)")
    screen_table()
    times = [float(t) for t in a.at.split(",") if t]
    cols = [c for c in a.columns.split(",") if c]
    only = [row for _, row, _ in TARGETS] if a.bounds_only else None
    ates = [fault_table(t, cols, only) for t in times]
    if len(times) > 1:
        target_table(times, ates)
    monitor_table([m for m in a.monitor_modes.split(",") if m])


if __name__ == "__main__":
    main()
