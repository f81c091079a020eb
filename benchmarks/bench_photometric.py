"""Timing of the direct (photometric) stack; prints numbers, asserts nothing.

    python benchmarks/bench_photometric.py [--points 500] [--repeat 5]

1. Linearizing N one-point temporal factors (``factors.photometric.temporal_factor``)
   through GTSAM: cost per point and per pattern pixel (8 per point).
2. The same residuals+Jacobians vectorized in one call (what TrackFrame uses).
3. TrackFrame per frame for ~N points over 4 pyramid levels (640x480).
4. Point selection and epipolar search for N points (stereo, 11 cm baseline).
Scenes come from the tiny plane renderer in tests/cases_photometric.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gtsam
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from cases_photometric import box_scene, render_planes  # noqa: E402
from factors.image_ops import BilinearImage  # noqa: E402
from factors.photometric import (PATTERN, Pinhole, PhotometricParams, make_host_patch,  # noqa: E402
                                 sqrt_weights, temporal_eval, temporal_factor)
from vio.direct import (EpipolarConfig, SelectConfig, epipolar_search, make_reference,  # noqa: E402
                        select_points, track_frame)

W, H = 640, 480
K = Pinhole(450.0, 450.0, 319.5, 239.5)
X, D, A = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.D, gtsam.symbol_shorthand.A


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def scene(rng, n_points: int):
    planes = box_scene(rng, scales_m=(0.025, 0.08))
    T_new = gtsam.Pose3(gtsam.Rot3.Expmap(np.deg2rad([0.6, -0.7, 0.3])), [0.012, -0.01, 0.012])
    kf, idepth = render_planes(planes, K, gtsam.Pose3(), W, H)
    new, _ = render_planes(planes, K, T_new, W, H, gain=np.exp(0.1), bias=5.0)
    right, _ = render_planes(planes, K, gtsam.Pose3(gtsam.Rot3(), [0.11, 0, 0]), W, H)
    kf, new, right = (im + rng.normal(0, 1.0, im.shape) for im in (kf, new, right))
    sel = select_points(kf, SelectConfig(n_points=n_points))
    rho = idepth[sel.uv[:, 1].astype(int), sel.uv[:, 0].astype(int)]
    return kf, new, right, sel, rho, T_new


def bench_factors(kf, new, sel, rho, T_new, repeat: int) -> None:
    host = make_host_patch(BilinearImage(kf), sel.uv, K)
    target = BilinearImage(new)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    values.insert(X(0), gtsam.Pose3())
    values.insert(X(1), T_new)
    values.insert(A(0), np.zeros(2))
    values.insert(A(1), np.array([0.1, 5.0]))
    for n in range(len(sel)):
        graph.add(temporal_factor([X(0), X(1), D(n), A(0), A(1)], host.subset([n]), target, K,
                                  gtsam.Pose3(), PhotometricParams()))
        values.insert(D(n), np.array([rho[n]]))
    n, P = len(sel), PATTERN.shape[0]
    t = best_of(lambda: graph.linearize(values), repeat)
    print(f"GTSAM linearize, {n} one-point factors: {t * 1e3:8.2f} ms = "
          f"{t / n * 1e6:7.1f} us/point = {t / n / P * 1e6:6.2f} us/pattern pixel")
    t = best_of(lambda: graph.error(values), repeat)
    print(f"GTSAM error only, {n} factors:          {t * 1e3:8.2f} ms = {t / n * 1e6:7.1f} us/point")
    params = PhotometricParams()

    def batch():
        ev = temporal_eval(gtsam.Pose3(), T_new, rho, np.zeros(2), np.array([0.1, 5.0]), host,
                           target, K, gtsam.Pose3())
        return sqrt_weights(ev, host, params)
    t = best_of(batch, repeat)
    print(f"vectorized eval (r + all Jacobians):    {t * 1e3:8.2f} ms = "
          f"{t / n * 1e6:7.2f} us/point = {t / n / P * 1e6:6.3f} us/pattern pixel")


def bench_tracking(kf, new, right, sel, rho, repeat: int) -> None:
    ref = make_reference(kf, sel.uv, rho, K, idepth_var=np.full(len(rho), 1e-4))
    out = track_frame(ref, new)
    t = best_of(lambda: track_frame(ref, new), repeat)
    t_ref = best_of(lambda: make_reference(kf, sel.uv, rho, K), repeat)
    print(f"TrackFrame, {len(sel)} points, 4 levels: {t * 1e3:8.2f} ms/frame "
          f"({out.iterations} LM iterations, {sum(s.evaluations for s in out.levels)} evaluations, "
          f"rmse {out.rmse:.2f}); make_reference {t_ref * 1e3:.2f} ms")
    t = best_of(lambda: select_points(kf, SelectConfig(n_points=len(sel))), repeat)
    print(f"select_points ({len(sel)} points, 640x480):     {t * 1e3:8.2f} ms")
    T_r_l = gtsam.Pose3(gtsam.Rot3(), [-0.11, 0, 0])
    t = best_of(lambda: epipolar_search(kf, right, sel.uv, K, K, T_r_l, EpipolarConfig()), repeat)
    res = epipolar_search(kf, right, sel.uv, K, K, T_r_l, EpipolarConfig())
    print(f"epipolar_search ({len(sel)} points):           {t * 1e3:8.2f} ms "
          f"({t / len(sel) * 1e6:.1f} us/point, {res.ok.mean() * 100:.0f} % ok)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=500)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    kf, new, right, sel, rho, T_new = scene(np.random.default_rng(0), args.points)
    bench_factors(kf, new, sel, rho, T_new, args.repeat)
    bench_tracking(kf, new, right, sel, rho, args.repeat)


if __name__ == "__main__":
    main()
