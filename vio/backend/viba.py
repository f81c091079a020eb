"""Visual-inertial bundle adjustment over the keyframe history (monocular VIO), the role of
ORB-SLAM3's VIBA steps after initialization (``LocalMapping`` at 5 s and 15 s: a full
inertial BA over every keyframe, with scale and gravity free), and the similarity that
carries its scale and gravity into the fixed-lag smoother (:mod:`vio.backend.regauge`).

Why: the fixed-lag smoother's scale is biased short. Not, as first thought, because its
marginal priors hold the scale direction with more confidence than the data gives:
``benchmarks/scale_information.py`` (MH_04@40 at 15 s) finds the smoother less sure of the
scale than this batch (relative sigma of the last 2.4 s of translation 1.51% vs 0.62%),
and every factor it was ever given, optimized together without marginalization, lands
within 0.06% of its scale (sigma 1.38%): the smoother is at the optimum of its own
factors, and those carry less scale information than the batch's (no td, no anchor-noise
whitening, tracks never re-anchored). Measured on generated MH_04 tracks from 40 s
(real IMU, ``benchmarks/bench_midflight.py``): the initialization's batch window has the
ground truth's scale (Umeyama 1.004) and the smoother's trajectory is 1.5-2% short for the
whole 30 s; a batch over the first 10 s of keyframes (the same IMU factors, this
module's landmark factors, no marginalization) converges to scale 0.998 both from the
ground truth and from the smoother's own trajectory (same final error), so the batch's
MAP has the right scale and the smoother does not find it. (The earlier inertial-only refinement of
:mod:`vio.backend.scale_refine` fixes the attitudes and the trajectory's shape, which the
smoother had already made consistent with its scale: it reported ~1.0.)

The batch (world ``w`` = the estimator's world; keyframes ``k = 0..N-1`` of the history):
``CombinedImuFactor`` per recorded interval, a robust projection factor (Huber at
``vision.kernel_k`` sigmas of ``vision.pixel_sigma``) per observation of each track seen
in at least ``min_obs`` keyframes (the ``max_tracks`` longest; a world point, started by
midpoint triangulation between its first and last observation from the smoother's
poses), the extrinsic fixed. Gauge: the first keyframe's position and yaw
(about world z) held at the smoother's values (1 mm, 1 mrad); roll and pitch are free
(gravity is re-estimated); its bias has the initialization's prior. Started from the
smoother's states, Levenberg-Marquardt; then tracks with an observation beyond
``vision.outlier_px`` are dropped and it runs again.

How it reaches the smoother (``RefineConfig.ba_apply``): by default (``"prior"``) as a
prior on the newest keyframe's velocity at ``s v`` (isotropic sigma ``|v|`` times the
batch's relative scale sigma), which the smoother's own factors then spread over the
window: no rebuild (when this was chosen each rebuild perturbed the smoother: an identity
similarity applied once at 5 s moved generated MH_04@40 from 0.133 to 0.102 m and real
MH_05 from 0.130 to 0.212 m; rebuilds are neutral now, ``vio.backend.smoother``). The
batch used the smoother's data, so this counts the scale information twice;
measured, it keeps the generated mid-flight excerpts within 0.2% of the path
(``RefineConfig``). Or (``"similarity"``) the correction
``c -> c_N + s R (c - c_N)`` about the newest camera centre ``c_N``
(attitudes ``R R_k``, velocities ``s R v``, inverse depths ``rho / s``), so the output does
not jump: ``s`` the least-squares ratio of the batch's and the smoother's centred camera
centres over the whole history, ``R`` the tilt part (gravity direction; the yaw is
unobservable and kept) of the chordal mean of ``R_batch R_smoother^T`` over the keyframes
of the smoother's window. Measured: moving the window to the batch's positions instead
(a jump of the batch's accumulated difference) made the generated excerpts worse as soon
as it was applied every 2 s (MH_03@50 Sim3 ATE 0.041 -> 0.126 m). It is refused
when the batch's scale is poorly determined: the relative standard deviation of the
history's translation from the batch's marginal covariance (as in the initialization's
test, :func:`vio.backend.dynamic_init.scale_sigma`) above ``ba_max_scale_sigma``, or the
change beyond ``max_scale_change`` / ``max_gravity_change_deg``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.robust import RobustKernel

log = logging.getLogger(__name__)
NAN = float("nan")
X, V, B, L = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B,
              gtsam.symbol_shorthand.L)


@dataclass(frozen=True)
class History:
    """Keyframe history since the (re)start, in keyframe order (N): stamps ``t_ns``, smoother
    poses ``T_w_b``, velocities ``v`` (N,3) m/s, biases; ``pims`` the preintegrated IMU
    of consecutive keyframes (N-1, None where bridged); ``obs`` per keyframe ``(ids (M,),
    uv (M,2))`` in normalized undistorted cam0 coordinates; ``in_window`` (N,) bool: the
    keyframes the smoother still holds."""

    t_ns: list
    T_w_b: list
    v: np.ndarray
    bias: list
    pims: list
    obs: list
    in_window: np.ndarray


@dataclass(frozen=True)
class VibaResult:
    """Outcome: the similarity ``c -> pivot + scale R_corr (c - pivot)`` (camera centres), its
    ``scale_sigma`` (relative), ``gravity_change_deg`` (angle of ``R_corr``), counts;
    ``ok`` and a ``reason`` when refused."""

    ok: bool
    reason: str
    scale: float = NAN
    R_corr: gtsam.Rot3 | None = None
    pivot: np.ndarray | None = None
    scale_sigma: float = NAN
    gravity_change_deg: float = NAN
    n_keyframes: int = 0
    n_tracks: int = 0


def _tracks(h: History, min_obs: int, max_tracks: int) -> dict[int, list[tuple[int, np.ndarray]]]:
    obs: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k, (ids, uv) in enumerate(h.obs):
        for lid, u in zip(ids, uv):
            obs.setdefault(int(lid), []).append((k, np.asarray(u, float)))
    best = sorted((l for l, o in obs.items() if len(o) >= min_obs), key=lambda l: (-len(obs[l]), l))
    return {l: obs[l] for l in best[:max_tracks]}


def _depth(T_a: gtsam.Pose3, uv_a: np.ndarray, T_b: gtsam.Pose3, uv_b: np.ndarray) -> float:
    """Depth (m) along the first camera's ray of the midpoint of two rays (cameras ``T_w_c``)."""
    ra = T_a.rotation().rotate(np.r_[uv_a, 1.0])
    rb = T_b.rotation().rotate(np.r_[uv_b, 1.0])
    d = np.linalg.lstsq(np.c_[ra, -rb], T_b.translation() - T_a.translation(), rcond=None)[0]
    return float(d[0])


def _gauge_prior(T: gtsam.Pose3) -> gtsam.NonlinearFactor:
    """Position and yaw held (1 mm, 1 mrad), roll and pitch free (0.5 rad): the rotation
    covariance in the body tangent, loose except along world z seen from the body."""
    u = T.rotation().unrotate(np.array([0.0, 0.0, 1.0]))
    C = np.zeros((6, 6))
    C[:3, :3] = 0.25 * np.eye(3) - (0.25 - 1e-6) * np.outer(u, u)
    C[3:, 3:] = 1e-6 * np.eye(3)
    return gtsam.PriorFactorPose3(X(0), T, gtsam.noiseModel.Gaussian.Covariance(C))


def _noise(sigma: float, kernel: RobustKernel | None) -> gtsam.noiseModel.Base:
    """Isotropic pixel noise (normalized units) with the robust kernel of the smoother."""
    base = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    if kernel is None or kernel.kind == "none":
        return base
    est = (gtsam.noiseModel.mEstimator.Cauchy if kernel.kind == "cauchy"
           else gtsam.noiseModel.mEstimator.Huber).Create(kernel.k)
    return gtsam.noiseModel.Robust.Create(est, base)


def build(h: History, T_b_c: gtsam.Pose3, sigma: float, kernel: RobustKernel | None,
          bias_sigmas: np.ndarray, min_obs: int, max_tracks: int, depth_range: tuple[float, float]
          ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict]:
    """The batch graph and its start (module docstring); returns also the tracks used.
    Landmarks are world points ``L(id)`` (3,) m with GTSAM's C++ projection factors (one
    per observation, extrinsic ``T_b_c`` as the body-to-sensor pose): the Python
    inverse-depth factor made each batch cost 1-2.5 s on the main thread (real MH_05 mono,
    22-54 keyframes, 257-331 tracks)."""
    g, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(_gauge_prior(h.T_w_b[0]))
    g.add(gtsam.PriorFactorConstantBias(B(0), h.bias[0], gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
    for k in range(len(h.t_ns)):
        vals.insert(X(k), h.T_w_b[k])
        vals.insert(V(k), np.asarray(h.v[k], float))
        vals.insert(B(k), h.bias[k])
        if k > 0:
            pim = h.pims[k - 1]
            if pim is not None:
                g.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
            else:   # bridged interval: only the bias continuity (the smoother had a motion prior)
                g.add(gtsam.BetweenFactorConstantBias(B(k - 1), B(k), gtsam.imuBias.ConstantBias(),
                                                      gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    cams = [T.compose(T_b_c) for T in h.T_w_b]
    noise, K = _noise(sigma, kernel), gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    used = {}
    for lid, o in _tracks(h, min_obs, max_tracks).items():
        a, uva = o[0]
        d = _depth(cams[a], uva, cams[o[-1][0]], o[-1][1])
        if not depth_range[0] <= d <= depth_range[1]:
            continue
        for k, uv in o:
            g.add(gtsam.GenericProjectionFactorCal3_S2(uv, noise, X(k), L(lid), K, T_b_c))
        vals.insert(L(lid), cams[a].transformFrom(np.r_[uva, 1.0] * d))
        used[lid] = o
    return g, vals, used


def _optimize(g: gtsam.NonlinearFactorGraph, vals: gtsam.Values, iters: int) -> gtsam.Values:
    """Levenberg-Marquardt with sparse Cholesky (5x faster than QR here, same solution on the
    generated MH_04 history; LM's damping keeps the system positive definite), QR if it fails."""
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(iters)
    try:
        p.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
        return gtsam.LevenbergMarquardtOptimizer(g, vals, p).optimize()
    except RuntimeError:
        p.setLinearSolverType("MULTIFRONTAL_QR")
        return gtsam.LevenbergMarquardtOptimizer(g, vals, p).optimize()


def _outlier_tracks(used: dict, est: gtsam.Values, T_b_c: gtsam.Pose3, limit: float) -> set[int]:
    """Tracks with an observation behind its camera or further than ``limit`` (normalized)
    from its projection."""
    bad = set()
    for lid, o in used.items():
        p_w = est.atPoint3(L(lid))
        for k, uv in o:
            q = est.atPose3(X(k)).compose(T_b_c).transformTo(p_w)
            if q[2] <= 1e-3 or np.linalg.norm(q[:2] / q[2] - uv) > limit:
                bad.add(lid)
                break
    return bad


def similarity(h: History, est: gtsam.Values, T_b_c: gtsam.Pose3
               ) -> tuple[float, gtsam.Rot3, np.ndarray]:
    """``s, R, pivot``: the correction ``c -> pivot + s R (c - pivot)`` of camera centres
    (module docstring)."""
    n = len(h.t_ns)
    Rs = [T.rotation().matrix() for T in h.T_w_b]
    Rb = [est.atPose3(X(k)).rotation().matrix() for k in range(n)]
    win = np.flatnonzero(h.in_window) if h.in_window.any() else np.arange(n)
    U, _, Vt = np.linalg.svd(sum(Rb[k] @ Rs[k].T for k in win))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(R.T @ z, z)         # the tilt part of R: the batch's vertical in our world
    ang = np.arctan2(np.linalg.norm(axis), float(z @ R.T @ z))
    tilt = gtsam.Rot3.Expmap(axis / max(np.linalg.norm(axis), 1e-12) * ang)
    xs = np.array([T.compose(T_b_c).translation() for T in h.T_w_b])
    xb = np.array([est.atPose3(X(k)).compose(T_b_c).translation() for k in range(n)])
    A, Y = (xs - xs.mean(0)) @ R.T, xb - xb.mean(0)
    s = float(np.sum(A * Y) / max(np.sum(A * A), 1e-12))
    return s, tilt, xs[-1]


def _scale_sigma(g: gtsam.NonlinearFactorGraph, est: gtsam.Values, K: int) -> float:
    """Relative standard deviation of the history's translation ``p_K - p_0`` (marginals)."""
    C = gtsam.Marginals(g, est).jointMarginalCovariance(gtsam.KeyVector([X(0), X(K)])).fullMatrix()
    T0, TK = est.atPose3(X(0)), est.atPose3(X(K))
    d = TK.translation() - T0.translation()
    n = float(np.linalg.norm(d))
    if n < 1e-6:
        return float("inf")
    u = d / n
    J = np.zeros(12)
    J[3:6], J[9:12] = -u @ T0.rotation().matrix(), u @ TK.rotation().matrix()
    return float(np.sqrt(max(J @ C @ J, 0.0))) / n


def solve(h: History, T_b_c: gtsam.Pose3, sigma: float, kernel: RobustKernel | None,
          outlier: float, bias_sigmas: np.ndarray, cfg) -> VibaResult:
    """The batch and its similarity (module docstring); ``cfg``: ``RefineConfig``."""
    n = len(h.t_ns)
    if n < cfg.min_intervals:
        return VibaResult(False, f"only {n} keyframes in the history")
    try:
        g, vals, used = build(h, T_b_c, sigma, kernel, bias_sigmas, cfg.min_obs, cfg.max_tracks,
                              (cfg.min_depth_m, cfg.max_depth_m))
        est = _optimize(g, vals, cfg.ba_iterations)
        bad = _outlier_tracks(used, est, T_b_c, outlier)
        if bad:
            keep = {l: o for l, o in used.items() if l not in bad}
            h2 = History(h.t_ns, [est.atPose3(X(k)) for k in range(n)],
                         np.array([est.atVector(V(k)) for k in range(n)]),
                         [est.atConstantBias(B(k)) for k in range(n)], h.pims,
                         [(np.array([l for l in ids if int(l) in keep], np.int64),
                           np.array([u for l, u in zip(ids, uv) if int(l) in keep]).reshape(-1, 2))
                          for ids, uv in h.obs], h.in_window)
            g, vals, used = build(h2, T_b_c, sigma, kernel, bias_sigmas, cfg.min_obs, cfg.max_tracks,
                                  (cfg.min_depth_m, cfg.max_depth_m))
            est = _optimize(g, vals, cfg.ba_iterations)
        sd = _scale_sigma(g, est, n - 1)
    except (RuntimeError, ValueError) as exc:
        lines = [ln for ln in str(exc).splitlines() if ln.strip()] or [type(exc).__name__]
        return VibaResult(False, f"batch failed: {lines[0][:100]}")
    s, R, pivot = similarity(h, est, T_b_c)
    ang = float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(R))))
    out = dict(scale=s, R_corr=R, pivot=pivot, scale_sigma=sd, gravity_change_deg=ang,
               n_keyframes=n, n_tracks=len(used))
    if not np.isfinite(s) or s <= 0:
        return VibaResult(False, f"non-finite or non-positive scale {s}", **out)
    if not sd <= cfg.ba_max_scale_sigma:
        return VibaResult(False, f"scale poorly determined (sigma {100 * sd:.2f}% > "
                                 f"{100 * cfg.ba_max_scale_sigma:.2f}%)", **out)
    if abs(np.log(s)) > np.log1p(cfg.max_scale_change):
        return VibaResult(False, f"implausible scale change {s:.3f}", **out)
    if ang > cfg.max_gravity_change_deg:
        return VibaResult(False, f"implausible gravity change {ang:.2f} deg", **out)
    return VibaResult(True, "ok", **out)
