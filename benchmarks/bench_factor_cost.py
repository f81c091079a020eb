"""Linearization cost per observation of the projection factors.

Same problem for every variant: 200 landmarks seen in all 10 frames (2000 observations;
each landmark anchored in one of them):

  (a) naive: one ``projection_factor`` CustomFactor per non-anchor observation
  (b) ``landmark_factor``: one CustomFactor per landmark (pinhole; also sphere + Huber, td)
  (c) ``gtsam.GenericProjectionFactorCal3_S2`` (C++), Point3 landmarks, one per observation

Prints ``graph.linearize`` time per observation (best of ``--repeats``), ratios to (c),
and the time of iSAM2 updates that relinearize everything for (b) and (c).

    python benchmarks/bench_factor_cost.py [--landmarks 200] [--frames 10] [--repeats 7]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from factors.landmark import landmark_factor, make_track  # noqa: E402
from factors.projection import projection_factor  # noqa: E402
from factors.robust import RobustKernel  # noqa: E402

X, C, L, P, T = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.L,
                 gtsam.symbol_shorthand.P, gtsam.symbol_shorthand.T)
FOCAL, SIGMA_PX = 460.0, 1.0
K = gtsam.Cal3_S2(FOCAL, FOCAL, 0.0, 320.0, 240.0)
T_B_C = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2), np.array([0.05, -0.02, 0.01]))


def world(n_lm: int, n_frames: int, rng: np.random.Generator):
    poses = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05),
                         np.array([0.1 * k, 0.02 * np.sin(k), 0.0])) for k in range(n_frames)]
    lms = []
    while len(lms) < n_lm:
        a = len(lms) % n_frames
        uvi, lam = rng.uniform(-0.4, 0.4, 2), rng.uniform(0.15, 0.5)
        p_w = poses[a].compose(T_B_C).transformFrom(np.append(uvi, 1) / lam)
        cams = [P_.compose(T_B_C).transformTo(p_w) for P_ in poses]
        if min(c[2] for c in cams) < 0.5:
            continue
        uv = np.array([c[:2] / c[2] for c in cams]) + rng.normal(size=(n_frames, 2)) * SIGMA_PX / FOCAL
        lms.append((a, uvi, lam, p_w, uv))
    return poses, lms


def graphs(poses, lms) -> dict[str, tuple[gtsam.NonlinearFactorGraph, gtsam.Values]]:
    n_frames = len(poses)
    base = gtsam.Values()
    for k, P_ in enumerate(poses):
        base.insert(X(k), P_)
    base.insert(C(0), T_B_C)
    base.insert(T(0), np.array([0.004]))
    sigma = SIGMA_PX / FOCAL
    noise2 = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    noise_px = gtsam.noiseModel.Isotropic.Sigma(2, SIGMA_PX)
    out = {name: (gtsam.NonlinearFactorGraph(), gtsam.Values(base))
           for name in ("a_naive", "b_landmark", "b_landmark_sphere_huber_td", "c_generic")}
    for l, (a, uvi, lam, p_w, uv) in enumerate(lms):
        others = [k for k in range(n_frames) if k != a]
        for name in ("a_naive", "b_landmark", "b_landmark_sphere_huber_td"):
            out[name][1].insert(L(l), np.array([lam]))
        for k in others:
            out["a_naive"][0].add(projection_factor(noise2, [X(a), X(k), C(0), L(l)], uvi, uv[k]))
        track = make_track(X(a), uvi, [X(k) for k in others], uv[others],
                           np.full(2, 0.1), np.full((n_frames - 1, 2), 0.1))
        out["b_landmark"][0].add(landmark_factor(track, L(l), C(0), sigma))
        out["b_landmark_sphere_huber_td"][0].add(
            landmark_factor(track, L(l), C(0), sigma, "sphere", RobustKernel("huber"), T(0)))
        out["c_generic"][1].insert(P(l), p_w)
        for k in range(n_frames):
            px = FOCAL * uv[k] + [320.0, 240.0]
            out["c_generic"][0].add(gtsam.GenericProjectionFactorCal3_S2(
                gtsam.Point2(*px), noise_px, X(k), P(l), K, T_B_C))
    return out


def best_time(fn, repeats: int) -> float:
    fn()
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def isam2_cost(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_frames: int,
               updates: int = 3) -> tuple[float, float]:
    """(first update, mean of later updates that relinearize all variables) in seconds."""
    g = gtsam.NonlinearFactorGraph(graph)
    prior6 = gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)
    for k in range(n_frames):
        g.add(gtsam.PriorFactorPose3(X(k), values.atPose3(X(k)), prior6))
    g.add(gtsam.PriorFactorPose3(C(0), T_B_C, prior6))
    if values.exists(T(0)):
        g.add(gtsam.PriorFactorVector(T(0), np.array([0.0]), gtsam.noiseModel.Isotropic.Sigma(1, 0.01)))
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.0)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    t0 = time.perf_counter()
    isam.update(g, values)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(updates):
        isam.update()
    return first, (time.perf_counter() - t0) / updates


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--landmarks", type=int, default=200)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    poses, lms = world(args.landmarks, args.frames, np.random.default_rng(0))
    n_obs = args.landmarks * args.frames
    gs = graphs(poses, lms)
    t_build = best_time(lambda: [landmark_factor(make_track(X(a), uvi, [X(k) for k in range(args.frames)],
                                                            uv), L(l), C(0), 0.002)
                                 for l, (a, uvi, _, _, uv) in enumerate(lms)], 3)
    print(f"problem: {args.landmarks} landmarks x {args.frames} frames = {n_obs} observations")
    print(f"per-landmark factor construction (make_track + landmark_factor): "
          f"{t_build / args.landmarks * 1e6:.1f} us/landmark")
    times = {name: best_time(lambda g=g, v=v: g.linearize(v), args.repeats) for name, (g, v) in gs.items()}
    ref = times["c_generic"] / n_obs
    print(f"{'variant':32s} {'factors':>8s} {'us/obs':>8s} {'x (c)':>7s}")
    for name, t in times.items():
        per = t / n_obs
        print(f"{name:32s} {gs[name][0].size():8d} {per * 1e6:8.2f} {per / ref:7.1f}")
    print("iSAM2 (update with all variables relinearized):")
    for name in ("b_landmark", "c_generic"):
        first, later = isam2_cost(*gs[name], args.frames)
        print(f"  {name:30s} first update {first * 1e3:7.1f} ms, relinearizing update {later * 1e3:7.1f} ms")


if __name__ == "__main__":
    main()
