"""Keys, noise models and factor builders of the VIO graph.

Keys: ``X(k)`` body pose ``T_w_b`` (Pose3), ``V(k)`` velocity in the world (m/s),
``B(k)`` IMU bias, ``E(0)`` camera extrinsic ``T_b_c`` (Pose3), ``D(0)`` residual
time offset td (1-vector, s, on top of the offset applied by the sync layer),
``L(n)`` landmark inverse depths (1-vector, 1/m) in their anchor camera.
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.landmark import landmark_factor, make_track
from factors.robust import RobustKernel
from factors.stereo import make_stereo_track, stereo_factor
from vio.backend.config import BackendConfig, CalibConfig, InitConfig
from vio.backend.init import InitialState
from vio.backend.landmarks import Track

X = gtsam.symbol_shorthand.X
V = gtsam.symbol_shorthand.V
B = gtsam.symbol_shorthand.B
E = gtsam.symbol_shorthand.E
D = gtsam.symbol_shorthand.D
L = gtsam.symbol_shorthand.L

EXTRINSIC = E(0)
TD = D(0)


def state_priors(k: int, state: InitialState, cfg: InitConfig,
                 pose_sigmas: np.ndarray | None = None) -> gtsam.NonlinearFactorGraph:
    """Priors on the first keyframe (or on the restart keyframe after recovery).

    Rotation sigmas are in the body frame ([roll, pitch, yaw]-like for a level body),
    then position (m); velocity (m/s); bias [accel m/s^2, gyro rad/s].
    """
    g = gtsam.NonlinearFactorGraph()
    if pose_sigmas is None:
        pose_sigmas = np.array([cfg.prior_rp_sigma, cfg.prior_rp_sigma, cfg.prior_yaw_sigma,
                                cfg.prior_pos_sigma, cfg.prior_pos_sigma, cfg.prior_pos_sigma])
    g.add(gtsam.PriorFactorPose3(X(k), state.T_w_b, gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)))
    g.add(gtsam.PriorFactorVector(V(k), state.v_w,
                                  gtsam.noiseModel.Isotropic.Sigma(3, cfg.prior_vel_sigma)))
    bias_sigmas = np.r_[np.full(3, cfg.prior_accel_bias_sigma), np.full(3, cfg.prior_gyro_bias_sigma)]
    g.add(gtsam.PriorFactorConstantBias(B(k), state.bias,
                                        gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
    return g


def calib_priors(T_b_c: gtsam.Pose3, td0: float, cfg: CalibConfig) -> gtsam.NonlinearFactorGraph:
    """Priors on extrinsic and td: loose when estimated online, tight otherwise."""
    g = gtsam.NonlinearFactorGraph()
    if cfg.estimate_extrinsic:
        s = np.r_[np.full(3, cfg.extrinsic_rot_sigma), np.full(3, cfg.extrinsic_pos_sigma)]
    else:
        s = np.full(6, cfg.fixed_sigma)
    g.add(gtsam.PriorFactorPose3(EXTRINSIC, T_b_c, gtsam.noiseModel.Diagonal.Sigmas(s)))
    td_sigma = cfg.td_sigma if cfg.estimate_td else cfg.fixed_sigma
    g.add(gtsam.PriorFactorVector(TD, np.array([td0]), gtsam.noiseModel.Isotropic.Sigma(1, td_sigma)))
    return g


def imu_factor(k0: int, k1: int, pim: gtsam.PreintegratedCombinedMeasurements) -> gtsam.NonlinearFactor:
    """``CombinedImuFactor`` between keyframes k0 and k1."""
    return gtsam.CombinedImuFactor(X(k0), V(k0), X(k1), V(k1), B(k0), B(k1), pim)


def zero_velocity(k: int, sigma: float) -> gtsam.NonlinearFactor:
    """Zero-velocity update while the platform is still."""
    return gtsam.PriorFactorVector(V(k), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, sigma))


def build_landmark_factor(track: Track, frames: list[int], cfg: BackendConfig, sigma: float,
                          line_time_s: float) -> gtsam.NonlinearFactor:
    """The per-landmark projection factor over the given keyframes (first = anchor).

    Observation time offsets: ``row / ROWS * t_readout`` for rolling shutter (seed
    004, projection_td_factor); td recorded at observation time is 0 because the
    td variable is the residual offset on top of the sync layer's constant.
    """
    a = track.obs[frames[0]]
    rest = [track.obs[f] for f in frames[1:]]
    vmax = cfg.vision.td_velocity_max
    lm = make_track(X(frames[0]), a.uv, [X(f) for f in frames[1:]],
                    np.array([o.uv for o in rest]),
                    anchor_vel=_td_velocity(a.velocity, vmax),
                    vel=np.array([_td_velocity(o.velocity, vmax) for o in rest]),
                    anchor_offset=_row_offset(a, line_time_s),
                    offset=np.array([_row_offset(o, line_time_s) for o in rest]))
    kernel, td_key = _vision_options(cfg)
    return landmark_factor(lm, track.key, EXTRINSIC, sigma, cfg.vision.model, kernel, td_key)


def _row_offset(o, line_time_s: float) -> float:
    """Rolling-shutter delay of an observation's row (s): ``row / ROWS * t_readout`` with
    ``t_readout = ROWS * line_time`` (seed 004); 0 when the row is unknown."""
    return 0.0 if not np.isfinite(o.row) else o.row * line_time_s


def _td_velocity(vel: np.ndarray, vmax: float) -> np.ndarray:
    """The velocity multiplying td, or zero when implausible (a mistrack or a bad
    depth would dominate td: drop its td term)."""
    return vel if np.linalg.norm(vel) <= vmax else np.zeros(2)


def _vision_options(cfg: BackendConfig) -> tuple[RobustKernel | None, int | None]:
    v = cfg.vision
    return (None if v.kernel == "none" else RobustKernel(v.kernel, v.kernel_k),
            TD if v.use_td else None)


def image_velocity(uv: np.ndarray, depth: float, omega_c: np.ndarray, vel_c: np.ndarray) -> np.ndarray:
    """Normalized-plane velocity (1/s) of a static point seen at ``uv`` with depth
    ``depth`` (m) by a camera moving with angular velocity ``omega_c`` (rad/s) and
    linear velocity ``vel_c`` (m/s), both in the camera frame (the classical
    interaction matrix of image-based visual servoing)."""
    u, v = uv
    wx, wy, wz = omega_c
    vx, vy, vz = vel_c
    return np.array([(-vx + u * vz) / depth + u * v * wx - (1 + u * u) * wy + v * wz,
                     (-vy + v * vz) / depth + (1 + v * v) * wx - u * v * wy - u * wz])


def build_stereo_factor(track: Track, C: gtsam.Pose3, cfg: BackendConfig, sigma: float,
                        line_time_s: float) -> gtsam.NonlinearFactor:
    """The landmark's cam1 observations (``factors.stereo``); ``C = T_b_c1 T_b_c0^-1``."""
    frames = track.frames()
    a = track.obs[frames[0]]
    sf = track.stereo_frames()
    vmax = cfg.vision.td_velocity_max
    st = make_stereo_track(X(frames[0]), a.uv, [X(f) for f in sf],
                           np.array([track.obs[f].right_uv for f in sf]), C,
                           anchor_vel=_td_velocity(a.velocity, vmax),
                           vel=np.array([_td_velocity(track.obs[f].right_velocity, vmax) for f in sf]),
                           anchor_offset=_row_offset(a, line_time_s),
                           offset=np.array([_row_offset(track.obs[f], line_time_s) for f in sf]))
    kernel, td_key = _vision_options(cfg)
    return stereo_factor(st, track.key, EXTRINSIC, sigma, cfg.vision.model, kernel, td_key)


def reprojection_errors(track: Track, frames: list[int], values: gtsam.Values) -> np.ndarray:
    """Normalized-plane reprojection error norms of the non-anchor observations."""
    T_b_c = values.atPose3(EXTRINSIC)
    lam = float(values.atVector(track.key)[0])
    a = track.obs[frames[0]]
    T_w_ca = values.atPose3(X(frames[0])).compose(T_b_c)
    if lam <= 0:
        return np.full(len(frames) - 1, np.inf)
    p_w = T_w_ca.transformFrom(np.array([a.uv[0], a.uv[1], 1.0]) / lam)
    errs = []
    for f in frames[1:]:
        p_c = values.atPose3(X(f)).compose(T_b_c).transformTo(p_w)
        if p_c[2] <= 1e-6:
            errs.append(np.inf)
            continue
        errs.append(float(np.linalg.norm(p_c[:2] / p_c[2] - track.obs[f].uv)))
    return np.array(errs)
