"""Dynamic initialization for sequences that start moving (VINS-Mono's role of
visual-inertial alignment, solved here without a separate SfM stage).

1. Keyframes every ``step`` over a short window; gyro preintegration gives the
   relative rotations ``R_k`` and position increments ``dp_k`` in the first body
   frame (``b0``), for the current gyro-bias guess.
2. Linear alignment (closed form in the spirit of Martinelli's): unknowns are the
   velocity ``v0`` and gravity ``g0`` in ``b0`` and one depth per landmark. With
   ``p_k = v0 t_k + g0 t_k^2 / 2 + dp_k`` every observation gives
   ``[m_j]x R_cj^T (p_ca + R_ca m_a d - p_cj) = 0``, linear in the unknowns.
   Gravity is then fixed to its known magnitude and the rest solved again.
3. A batch Levenberg-Marquardt over the window (``CombinedImuFactor`` + landmark
   factors) refines poses, velocities, inverse depths and the IMU biases (the
   gyro bias included), starting from the aligned solution.

The result is the state of the window's first keyframe in a gravity-aligned
world with zero yaw; the pipeline then replays the window through the estimator.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.landmark import landmark_factor, make_track
from factors.robust import RobustKernel
from vio.backend.config import BackendConfig
from vio.backend.init import InitialState, gravity_aligned_rotation
from vio.imu import combined_params, integrate
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib, ImuData

log = logging.getLogger(__name__)
X, V, B, L = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B,
              gtsam.symbol_shorthand.L)


@dataclass(frozen=True)
class InitWindow:
    """Keyframes of the window: stamps (K,), features per keyframe, and the IMU
    segments between consecutive keyframes (K-1)."""

    t_ns: tuple[int, ...]
    features: tuple[FeatureFrame, ...]
    imu: tuple[ImuData, ...]


@dataclass(frozen=True)
class AlignResult:
    ok: bool
    state: InitialState | None
    reason: str
    gravity_error: float = float("nan")


def init_window(packets: list, step_s: float) -> InitWindow:
    """Keyframes every ``step_s`` from buffered packets (``vio.sync.FramePacket``),
    with the IMU between consecutive keyframes joined."""
    from vio.imu import concat
    chosen, segs, pending = [packets[0]], [], []
    for p in packets[1:]:
        pending.append(p.imu)
        if (p.t_ns - chosen[-1].t_ns) * 1e-9 >= step_s - 1e-6:
            chosen.append(p)
            segs.append(concat(pending))
            pending = []
    empty = FeatureFrame(0, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    return InitWindow(tuple(p.t_ns for p in chosen),
                      tuple(p.features if p.features is not None else empty for p in chosen),
                      tuple(segs))


def _tracks(win: InitWindow, min_obs: int = 3, max_tracks: int = 80
            ) -> dict[int, list[tuple[int, np.ndarray]]]:
    """The ``max_tracks`` longest tracks seen in at least ``min_obs`` keyframes."""
    obs: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k, fr in enumerate(win.features):
        for lid, uv in zip(fr.ids, fr.uv):
            obs.setdefault(int(lid), []).append((k, np.asarray(uv, float)))
    best = sorted((l for l, o in obs.items() if len(o) >= min_obs), key=lambda l: -len(obs[l]))
    return {l: obs[l] for l in best[:max_tracks]}


def _preintegrate(win: InitWindow, params, bias) -> tuple[list[np.ndarray], list[np.ndarray], list]:
    """Rotations ``R_k`` and position increments ``dp_k`` (frame b0, zero initial
    velocity and no gravity), plus the per-interval preintegrations."""
    R, dp, pims = [np.eye(3)], [np.zeros(3)], []
    acc_R, acc_p, acc_v = np.eye(3), np.zeros(3), np.zeros(3)
    for seg in win.imu:
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        integrate(pim, seg)
        dt = pim.deltaTij()
        acc_p = acc_p + acc_v * dt + acc_R @ pim.deltaPij()
        acc_v = acc_v + acc_R @ pim.deltaVij()
        acc_R = acc_R @ pim.deltaRij().matrix()
        R.append(acc_R.copy())
        dp.append(acc_p.copy())
        pims.append(pim)
    return R, dp, pims


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _linear_align(win: InitWindow, cam: CameraCalib, R: list, dp: list, tracks: dict,
                  fixed_g: np.ndarray | None = None):
    """Least-squares ``[v0, g0, depths]`` (or ``[v0, depths]`` with ``fixed_g``)."""
    t = np.array([(s - win.t_ns[0]) * 1e-9 for s in win.t_ns])
    Rbc, tbc = cam.T_b_c.rotation().matrix(), cam.T_b_c.translation()
    lids = list(tracks)
    ng = 0 if fixed_g is not None else 3
    n = 3 + ng + len(lids)
    rows, rhs = [], []
    for li, lid in enumerate(lids):
        (a, uva), *rest = tracks[lid]
        m_a = np.array([uva[0], uva[1], 1.0])
        Rca = R[a] @ Rbc
        for j, uvj in rest:
            m_j = np.array([uvj[0], uvj[1], 1.0])
            Aj = _skew(m_j) @ (R[j] @ Rbc).T
            row = np.zeros((3, n))
            row[:, 0:3] = Aj * (t[a] - t[j])
            const = dp[a] - dp[j] + (R[a] - R[j]) @ tbc
            if fixed_g is None:
                row[:, 3:6] = Aj * 0.5 * (t[a] ** 2 - t[j] ** 2)
            else:
                const = const + 0.5 * (t[a] ** 2 - t[j] ** 2) * fixed_g
            row[:, 3 + ng + li] = Aj @ (Rca @ m_a)
            rows.append(row)
            rhs.append(-Aj @ const)
    A, b = np.vstack(rows), np.concatenate(rhs)
    keep = np.ones(len(rows), bool)
    for _ in range(3):  # least squares, then drop gross outliers (mistracks) and re-solve
        rows_k = np.repeat(keep, 3)
        x, *_ = np.linalg.lstsq(A[rows_k], b[rows_k], rcond=None)
        res = np.linalg.norm((A @ x - b).reshape(-1, 3), axis=1)
        thr = 5.0 * np.median(res[keep]) + 1e-12
        if (res[keep] <= thr).all():
            break
        keep = res <= thr
    v0 = x[0:3]
    g0 = x[3:6] if fixed_g is None else fixed_g
    return v0, g0, dict(zip(lids, x[3 + ng:]))


def _batch_refine(win: InitWindow, cam: CameraCalib, cfg: BackendConfig,
                  R_w_b0: gtsam.Rot3, R: list, dp: list, v0: np.ndarray, g0: np.ndarray,
                  depths: dict, tracks: dict, pims: list) -> tuple[gtsam.Values, float]:
    """Batch LM over the window from the aligned initial guess (world = gravity-aligned);
    returns the solution and its mean error per factor."""
    t = np.array([(s - win.t_ns[0]) * 1e-9 for s in win.t_ns])
    Rw = R_w_b0.matrix()
    g, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    ic = cfg.init
    g.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(R_w_b0, np.zeros(3)), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([0.1, 0.1, 1e-3, 1e-3, 1e-3, 1e-3]))))
    g.add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(
        np.r_[np.full(3, ic.prior_accel_bias_sigma), np.full(3, 0.1)])))
    E = gtsam.symbol_shorthand.E(0)
    g.add(gtsam.PriorFactorPose3(E, cam.T_b_c, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    vals.insert(E, cam.T_b_c)
    for k in range(len(win.t_ns)):
        p = Rw @ (v0 * t[k] + 0.5 * g0 * t[k] ** 2 + dp[k])
        vals.insert(X(k), gtsam.Pose3(gtsam.Rot3(Rw @ R[k]), p))
        vals.insert(V(k), Rw @ (v0 + g0 * t[k]) + Rw @ _vel_increment(pims, k))
        vals.insert(B(k), gtsam.imuBias.ConstantBias())
        if k > 0:
            g.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pims[k - 1]))
    sigma = cfg.vision.pixel_sigma / cam.intrinsics[0]
    for lid, obs in tracks.items():
        d = depths.get(lid, np.nan)
        if not (np.isfinite(d) and cfg.vision.min_depth_m < d < cfg.vision.max_depth_m):
            continue
        (a, uva), *rest = obs
        tr = make_track(X(a), uva, [X(j) for j, _ in rest], np.array([uv for _, uv in rest]))
        g.add(landmark_factor(tr, L(lid), E, sigma, cfg.vision.model, RobustKernel("huber")))
        vals.insert(L(lid), np.array([1.0 / d]))
    params_lm = gtsam.LevenbergMarquardtParams()
    params_lm.setMaxIterations(30)
    est = gtsam.LevenbergMarquardtOptimizer(g, vals, params_lm).optimize()
    return est, g.error(est) / max(1, g.size())


def _vel_increment(pims: list, k: int) -> np.ndarray:
    """Velocity increment from the IMU alone up to keyframe k, in b0."""
    acc_R, acc_v = np.eye(3), np.zeros(3)
    for pim in pims[:k]:
        acc_v = acc_v + acc_R @ pim.deltaVij()
        acc_R = acc_R @ pim.deltaRij().matrix()
    return acc_v


def align(win: InitWindow, cam: CameraCalib, imu_calib: ImuCalib, cfg: BackendConfig,
          min_landmarks: int = 15, max_gravity_error: float = 0.15,
          max_mean_error: float = 20.0) -> AlignResult:
    """Estimate the first keyframe's state from a moving window (see module docstring)."""
    tracks = _tracks(win)
    if len(tracks) < min_landmarks:
        return AlignResult(False, None, f"only {len(tracks)} landmarks seen in >= 3 keyframes")
    params = combined_params(imu_calib, cfg.imu)
    g_norm = cfg.imu.gravity
    R, dp, pims = _preintegrate(win, params, gtsam.imuBias.ConstantBias())
    v0, g0, _ = _linear_align(win, cam, R, dp, tracks)
    gerr = abs(np.linalg.norm(g0) - g_norm) / g_norm
    if not np.isfinite(gerr) or gerr > max_gravity_error:
        return AlignResult(False, None, f"gravity magnitude {np.linalg.norm(g0):.2f} m/s^2 "
                                        f"inconsistent (too little excitation?)", gerr)
    g0 = g0 / np.linalg.norm(g0) * g_norm
    v0, _, depths = _linear_align(win, cam, R, dp, tracks, fixed_g=g0)
    R_w_b0 = gravity_aligned_rotation(-g0)
    try:
        est, mean_err = _batch_refine(win, cam, cfg, R_w_b0, R, dp, v0, g0, depths,
                                      tracks, pims)
    except RuntimeError as exc:
        return AlignResult(False, None, f"batch refinement failed: {str(exc).splitlines()[0]}", gerr)
    if not mean_err < max_mean_error:
        return AlignResult(False, None, f"batch refinement left a mean factor error of "
                                        f"{mean_err:.1f} (> {max_mean_error})", gerr)
    state = InitialState(win.t_ns[0], est.atPose3(X(0)), est.atVector(V(0)),
                         est.atConstantBias(B(0)), "dynamic")
    log.info("dynamic initialization: |g| error %.1f%%, v0 %s, gyro bias %s", 100 * gerr,
             np.round(state.v_w, 3), np.round(state.bias.gyroscope(), 4))
    return AlignResult(True, state, "ok", gerr)
