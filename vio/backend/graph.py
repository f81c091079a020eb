"""Keys, noise models and factor builders of the VIO graph.

Keys: ``X(k)`` body pose ``T_w_b`` (Pose3), ``V(k)`` velocity in the world (m/s),
``B(k)`` IMU bias, ``E(0)`` camera extrinsic ``T_b_c`` (Pose3), ``D(0)`` residual
time offset td (1-vector, s, on top of the offset applied by the sync layer),
``L(n)`` landmark inverse depths (1-vector, 1/m) in their anchor camera, ``A(k)`` the
photometric keyframes' affine brightness [a, b] (``vio.direct.source``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.landmark import landmark_anchor_jacobian, landmark_factor, make_track
from factors.anchor_noise import AnchorWhitening
from factors.jit import njit as _njit
from factors.track_kernel import whitening
from factors.reanchor import depth_transfer_member
from factors.stack import Member
from factors.robust import RobustKernel
from factors.stereo import StereoRig, make_stereo_track, stereo_anchor_jacobian, stereo_factor
from factors.stereo import stereo_rig  # noqa: F401  (callers use graph.stereo_rig)
from vio.backend.config import BackendConfig, CalibConfig, InitConfig
from vio.backend.init import InitialState
from vio.backend.landmarks import Track


X = gtsam.symbol_shorthand.X
V = gtsam.symbol_shorthand.V
B = gtsam.symbol_shorthand.B
E = gtsam.symbol_shorthand.E
D = gtsam.symbol_shorthand.D
L = gtsam.symbol_shorthand.L
P = gtsam.symbol_shorthand.P   # world-point landmarks (vio.backend.point_tracks)
A = gtsam.symbol_shorthand.A   # a keyframe's affine brightness [a, b] (vio.direct's factor source)

EXTRINSIC = E(0)
TD = D(0)
# the place a factor holds in an update's graph until the update's factors are built
# together and put there with NonlinearFactorGraph.replace (vio.backend.tracks,
# vio.backend.point_tracks); never reaches the smoother
SLOT = gtsam.PriorFactorVector(0, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 1.0))


def state_priors(k: int, state: InitialState, cfg: InitConfig,
                 pose_sigmas: np.ndarray | None = None) -> gtsam.NonlinearFactorGraph:
    """Priors on the first keyframe (or on the restart keyframe after recovery).

    Default pose prior: roll/pitch ``prior_rp_sigma`` and yaw ``prior_yaw_sigma`` (rad)
    about the *world* axes, position ``prior_pos_sigma`` (m); the covariance is rotated
    into the body-frame tangent of ``Pose3`` (``R^T S R``). A body-frame diagonal would
    pin the wrong axis: EuRoC's IMU x axis points up, so body "yaw" is a tilt, and the
    start's tilt error (accel bias not yet separable from gravity) stayed locked in.
    ``pose_sigmas`` (6,): isotropic-per-block body-frame sigmas instead (recovery).
    Velocity (m/s) and bias [accel m/s^2, gyro rad/s] priors are diagonal. The state's
    own ``rp_sigma`` / ``vel_sigma`` (an initializer's covariance) replace the defaults.
    """
    g = gtsam.NonlinearFactorGraph()
    if pose_sigmas is None:
        R = state.T_w_b.rotation().matrix()
        cov = np.zeros((6, 6))
        rp = cfg.prior_rp_sigma if state.rp_sigma is None else state.rp_sigma
        cov[:3, :3] = R.T @ np.diag([rp, rp, cfg.prior_yaw_sigma]) ** 2 @ R
        cov[3:, 3:] = np.eye(3) * cfg.prior_pos_sigma ** 2
        pose_noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    else:
        pose_noise = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)
    g.add(gtsam.PriorFactorPose3(X(k), state.T_w_b, pose_noise))
    vel = cfg.prior_vel_sigma if state.vel_sigma is None else state.vel_sigma
    g.add(gtsam.PriorFactorVector(V(k), state.v_w, gtsam.noiseModel.Isotropic.Sigma(3, vel)))
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


@dataclass(frozen=True)
class LinPoint:
    """The estimate a landmark factor's constant anchor-noise whitening is computed at
    (``VisionConfig.anchor_noise``): inverse depth ``lam`` (1/m), ``T_b_c``, body poses
    ``T_w_b`` by keyframe index, residual ``td`` (s)."""

    lam: float
    T_b_c: gtsam.Pose3
    poses: dict[int, gtsam.Pose3]
    td: float


def _whitening(anchor_jacobian, track, at: LinPoint | None, body_poses: list[gtsam.Pose3],
               cfg: BackendConfig, td_key: int | None) -> AnchorWhitening | None:
    """W of :func:`factors.anchor_noise.anchor_whitening` for a landmark or stereo track at
    ``at`` (``body_poses``: anchor first, then the track's other body keys in order);
    ``anchor_jacobian``: ``landmark_anchor_jacobian`` or ``stereo_anchor_jacobian``."""
    if at is None or not cfg.vision.anchor_noise:
        return None
    args = [np.array([at.lam]), at.T_b_c, *body_poses] + ([np.array([at.td])] if td_key is not None else [])
    # closed-form 2x2 eigen-decomposition (factors.track_kernel.whitening): equal to
    # factors.anchor_noise.anchor_whitening to rounding, without eigh's ~25 us of overhead
    return whitening(anchor_jacobian(args, track, cfg.vision.model, td_key is not None))


def build_landmark_factor(track: Track, frames: list[int], cfg: BackendConfig, sigma: float,
                          line_time_s: float, vel: np.ndarray | None = None,
                          at: LinPoint | None = None) -> gtsam.NonlinearFactor:
    """The per-landmark projection factor over the given keyframes (first = anchor).
    ``vel`` (n, 2): image velocities of the observations in ``frames`` for the td
    term (default: the measured ones); ``at``: the current estimate, for the anchor-noise
    whitening (none without it).

    Observation time offsets: ``row / ROWS * t_readout`` for rolling shutter (seed
    004, projection_td_factor); td recorded at observation time is 0 because the
    td variable is the residual offset on top of the sync layer's constant.
    """
    obs = [track.obs[f] for f in frames]
    vel, off = _cam0_shifts(track, frames, obs, vel, cfg.vision.td_velocity_max, line_time_s)
    lm = make_track(X(frames[0]), obs[0].uv, [X(f) for f in frames[1:]],
                    np.array([o.uv for o in obs[1:]]), anchor_vel=vel[0], vel=vel[1:],
                    anchor_offset=off[0], offset=off[1:])
    kernel, td_key = _vision_options(cfg)
    W = _whitening(landmark_anchor_jacobian, lm, at, [at.poses[f] for f in frames] if at else [], cfg, td_key)
    return landmark_factor(lm, track.key, EXTRINSIC, sigma, cfg.vision.model, kernel, td_key, whiten=W)


def _cam0_shifts(track: Track, frames: list[int], obs: list, vel: np.ndarray | None, vmax: float,
                 line_time_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The cam0 td velocities (n, 2) (measured where ``vel`` is None, capped at ``vmax``)
    and row offsets (n,) of ``obs`` in ``frames``, recorded with ``Track.set_shifts`` for the
    outlier check (:func:`reprojection_errors`)."""
    vel = _td_velocity(np.array([o.velocity for o in obs]) if vel is None else vel, vmax)
    off = _row_offsets(obs, line_time_s)
    track.set_shifts(frames, np.concatenate([np.array([o.uv for o in obs], float).reshape(-1, 2), vel,
                                             np.asarray(off, float)[:, None]], axis=1))
    return vel, off


def _row_offsets(obs: list, line_time_s: float) -> np.ndarray:
    """Time offset of each observation (s): the rolling-shutter delay of its row,
    ``row / ROWS * t_readout`` with ``t_readout = ROWS * line_time`` (seed 004; 0 when the
    row is unknown), minus the td its keyframe time already holds (``Obs.td_obs``)."""
    return row_offsets(np.array([o.row for o in obs], float), np.array([o.td_obs for o in obs], float),
                       line_time_s)


def row_offsets(rows: np.ndarray, td_obs: np.ndarray, line_time_s: float) -> np.ndarray:
    """:func:`_row_offsets` of the observations' rows (NaN: unknown) and ``td_obs`` (s)."""
    return np.where(np.isfinite(rows), rows * line_time_s, 0.0) - td_obs


def td_value(values: gtsam.Values) -> float:
    """The td variable's value (s; 0 without one): what the factors' observation shifts
    (``Track.shifted_uv``) take."""
    return float(values.atVector(TD)[0]) if values.exists(TD) else 0.0


def _td_velocity(vel: np.ndarray, vmax: float) -> np.ndarray:
    """The velocities (n, 2) multiplying td, zeroed where implausible (a mistrack or a
    bad depth would dominate td: drop its td term)."""
    vel = np.array(vel, float).reshape(-1, 2)
    _zero_fast_rows(vel, float(vmax))
    return vel


@_njit
def _zero_fast_rows(vel: np.ndarray, vmax: float) -> None:
    """``vel[~(|vel| <= vmax)] = 0`` row-wise (NaN rows too), compiled (~4 us -> ~0.5 us)."""
    for i in range(vel.shape[0]):
        if not np.sqrt(vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1]) <= vmax:
            vel[i, 0] = 0.0
            vel[i, 1] = 0.0


def _vision_options(cfg: BackendConfig) -> tuple[RobustKernel | None, int | None]:
    v = cfg.vision
    return _kernel_and_td(v.kernel, v.kernel_k, bool(v.use_td))


@functools.lru_cache(maxsize=16)
def _kernel_and_td(kernel: str, k: float | None, use_td: bool) -> tuple[RobustKernel | None, int | None]:
    """(robust kernel, td key) of the vision options (cached: asked for every landmark factor)."""
    return (None if kernel == "none" else RobustKernel(kernel, k), TD if use_td else None)


def image_velocity(uv: np.ndarray, depth: np.ndarray, omega_c: np.ndarray,
                   vel_c: np.ndarray) -> np.ndarray:
    """Normalized-plane velocities (n, 2) (1/s) of static points seen at ``uv`` (n, 2)
    with depths ``depth`` (n,) (m) by cameras moving with angular velocities
    ``omega_c`` (n, 3) (rad/s) and linear velocities ``vel_c`` (n, 3) (m/s), both in
    the camera frame (the classical interaction matrix of image-based visual
    servoing). Single points broadcast: (2,), scalar, (3,), (3,) give (2,)."""
    uv, omega_c, vel_c = np.asarray(uv, float), np.asarray(omega_c, float), np.asarray(vel_c, float)
    depth = np.asarray(depth, float)
    if uv.ndim == 2 and omega_c.shape == vel_c.shape == (len(uv), 3) and depth.shape == (len(uv),):
        out = np.empty((len(uv), 2))   # the same arithmetic compiled: ~7x faster on ~10 rows
        _image_velocity_rows(np.ascontiguousarray(uv), np.ascontiguousarray(depth),
                             np.ascontiguousarray(omega_c), np.ascontiguousarray(vel_c), out)
        return out
    u, v = uv[..., 0], uv[..., 1]
    wx, wy, wz = omega_c[..., 0], omega_c[..., 1], omega_c[..., 2]
    vx, vy, vz = vel_c[..., 0], vel_c[..., 1], vel_c[..., 2]
    return np.stack([(-vx + u * vz) / depth + u * v * wx - (1 + u * u) * wy + v * wz,
                     (-vy + v * vz) / depth + (1 + v * v) * wx - u * v * wy - u * wz], axis=-1)


@_njit
def _image_velocity_rows(uv: np.ndarray, depth: np.ndarray, w: np.ndarray, vel: np.ndarray,
                         out: np.ndarray) -> None:
    """:func:`image_velocity` row by row (n, 2) <- (n, 2), (n,), (n, 3), (n, 3)."""
    for i in range(uv.shape[0]):
        u, v = uv[i, 0], uv[i, 1]
        wx, wy, wz = w[i, 0], w[i, 1], w[i, 2]
        vx, vy, vz = vel[i, 0], vel[i, 1], vel[i, 2]
        out[i, 0] = (-vx + u * vz) / depth[i] + u * v * wx - (1 + u * u) * wy + v * wz
        out[i, 1] = (-vy + v * vz) / depth[i] + (1 + v * v) * wx - u * v * wy - u * wz


def build_depth_transfer(old_key: int, new_key: int, old_anchor: int, new_anchor: int,
                         uv_old: np.ndarray, lam_old: float, shift: tuple | None,
                         cfg: BackendConfig) -> Member:
    """``factors.reanchor`` residual (a ``factors.stack`` member) between a landmark's old
    key (anchored in ``old_anchor`` with observation ``uv_old``, estimate ``lam_old``) and
    its new key; ``shift``: the old anchor observation's ``(vel, offset)`` from
    ``Track.td_shift`` (None: unshifted)."""
    _, td_key = _vision_options(cfg)
    vel, off = shift if shift is not None else (np.zeros(2), 0.0)
    keys = [old_key, new_key, EXTRINSIC, X(old_anchor), X(new_anchor)] + ([td_key] if td_key is not None else [])
    return depth_transfer_member(keys, uv_old, lam_old, cfg.vision.reanchor_sigma,
                                 vel if td_key is not None else None, float(off))


def build_stereo_factor(track: Track, C: gtsam.Pose3 | StereoRig, cfg: BackendConfig, sigma: float,
                        line_time_s: float, vel: np.ndarray | None = None,
                        rvel: np.ndarray | None = None, at: LinPoint | None = None,
                        frames: list[int] | None = None) -> gtsam.NonlinearFactor:
    """All observations of a stereo landmark in one factor (``factors.stereo``, mixed
    track): cam0 of the non-anchor keyframes and cam1 of every keyframe that matched
    it; ``C = T_b_c1 T_b_c0^-1`` (or its ``stereo_rig``). One Python callback per linearization instead of a
    cam0 and a cam1 factor. ``vel`` / ``rvel`` (n, 2): cam0 / cam1 velocities of the
    observations in ``frames`` (anchor first; default: the track's frames) for the td term
    (default: the measured ones; ``rvel`` rows of frames without a cam1 match are ignored)."""
    frames = track.frames() if frames is None else frames
    obs = [track.obs[f] for f in frames]
    vmax = cfg.vision.td_velocity_max
    vel, off = _cam0_shifts(track, frames, obs, vel, vmax, line_time_s)
    st_i = [i for i, o in enumerate(obs) if o.right_uv is not None]
    keys = [X(f) for f in frames[1:]] + [X(frames[i]) for i in st_i]
    uv = np.array([o.uv for o in obs[1:]] + [obs[i].right_uv for i in st_i]).reshape(-1, 2)
    rvel = _td_velocity(np.array([obs[i].right_velocity for i in st_i]) if rvel is None
                        else np.asarray(rvel)[st_i], vmax)
    st = make_stereo_track(X(frames[0]), obs[0].uv, keys, uv, C, anchor_vel=vel[0],
                           vel=np.vstack([vel[1:], rvel]), anchor_offset=off[0],
                           offset=np.r_[off[1:], row_offsets(np.array([obs[i].right_time_row for i in st_i]),
                                                            np.array([obs[i].td_obs for i in st_i]),
                                                            line_time_s)],
                           right=[False] * (len(frames) - 1) + [True] * len(st_i))
    kernel, td_key = _vision_options(cfg)
    by_key = {X(f): at.poses[f] for f in frames} if at else {}
    bodies = [by_key[k] for k in (st.anchor_key, *st.keys)] if at else []
    W = _whitening(stereo_anchor_jacobian, st, at, bodies, cfg, td_key)
    return stereo_factor(st, track.key, EXTRINSIC, sigma, cfg.vision.model, kernel, td_key, whiten=W)


def camera_table(values: gtsam.Values, frames: list[int]) -> tuple[dict, np.ndarray, np.ndarray]:
    """``pos`` (keyframe -> row), ``R_w_c`` (K, 3, 3) and ``t_w_c`` (K, 3) of cam0 at the
    given keyframes in ``values``."""
    T_b_c = values.atPose3(EXTRINSIC)
    Ts = [values.atPose3(X(f)).compose(T_b_c) for f in frames]
    return ({f: i for i, f in enumerate(frames)}, np.array([T.rotation().matrix() for T in Ts]),
            np.array([T.translation() for T in Ts]))


def anchor_cameras(values: gtsam.Values, frames) -> dict[int, gtsam.Pose3]:
    """``T_w_c`` of cam0 at each keyframe of ``frames`` that ``values`` holds (anchors
    whose keyframe left the window are left out)."""
    T_b_c = values.atPose3(EXTRINSIC)
    return {f: values.atPose3(X(f)).compose(T_b_c) for f in frames if f is not None and values.exists(X(f))}


def reprojection_errors(track: Track, frames: list[int], values: gtsam.Values,
                        table: tuple | None = None) -> np.ndarray:
    """Normalized-plane reprojection error norms of the non-anchor observations, each
    observation moved to its keyframe's time as the factor moves it (``track.td_shift``
    and the td estimate; unshifted where the track has no factor yet): an unshifted
    check would see ``td * vel`` as error and reject the fast, td-informative points,
    keeping those whose noise happens to cancel it (a bias of td towards zero).
    ``table``: a :func:`camera_table` covering ``frames`` (built here if None)."""
    lam = float(values.atVector(track.key)[0])
    if lam <= 0:
        return np.full(len(frames) - 1, np.inf)
    pos, R, t = table if table is not None else camera_table(values, frames)
    idx = np.array([pos[f] for f in frames])
    td = td_value(values)
    uv_all = np.array([track.shifted_uv(f, td) for f in frames])
    a = uv_all[0]
    p_w = R[idx[0]] @ (np.array([a[0], a[1], 1.0]) / lam) + t[idx[0]]
    p_c = np.einsum("nji,nj->ni", R[idx[1:]], p_w - t[idx[1:]])
    uv = uv_all[1:].reshape(-1, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_c[:, :2] / p_c[:, 2:3] - uv, axis=1)
    return np.where(p_c[:, 2] > 1e-6, err, np.inf)


def worst_reprojection_errors(tracks: list[Track], values: gtsam.Values, table: tuple,
                              lams: np.ndarray | None = None) -> np.ndarray:
    """For each track, the largest of its :func:`reprojection_errors` over all its frames
    (0 where it has no observation besides the first), computed for all tracks at once:
    one pass of array arithmetic instead of ~10 small numpy calls per track. ``table``: a
    :func:`camera_table` covering every frame of the tracks; each track's inverse depth
    must be positive (the caller rejects the others); ``lams`` (n,): the inverse depths
    (default: the tracks' keys in ``values``)."""
    pos, R, t = table
    td = td_value(values)
    lam = np.empty(len(tracks)) if lams is None else np.asarray(lams, float)
    blocks, frames_all, first, n = [], [], [], 0
    for i, tr in enumerate(tracks):
        if lams is None:
            lam[i] = values.atVector(tr.key)[0]
        frames = tr.frames()
        first.append(n)
        n += len(frames)
        frames_all += frames
        blocks.append(tr.shift_rows[1] if tr.shift_rows is not None and tr.shift_rows[0] == tuple(frames)
                      else _shift_rows(tr, frames))
    out = np.zeros(len(tracks))
    if not n:
        return out
    rows = np.concatenate(blocks)
    uv, vel, off = rows[:, 0:2], rows[:, 2:4], rows[:, 4]
    uv = np.where(~np.isnan(off)[:, None], uv - (td + off)[:, None] * vel, uv)
    fpos, first = np.array([pos[f] for f in frames_all]), np.array(first)
    owner = np.repeat(np.arange(len(tracks)), np.diff(np.r_[first, n]))
    a = uv[first]
    ia = fpos[first]
    # (stacked matmul: the same bits as the per-track R @ m; einsum differs in the last ulp)
    p_w = (R[ia] @ (np.c_[a, np.ones(len(a))] / lam[:, None])[:, :, None])[:, :, 0] + t[ia]
    tgt = np.ones(len(fpos), bool)
    tgt[first] = False
    idx, own = fpos[tgt], owner[tgt]
    p_c = np.einsum("nji,nj->ni", R[idx], p_w[own] - t[idx])
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_c[:, :2] / p_c[:, 2:3] - uv[tgt], axis=1)
    err = np.where(p_c[:, 2] > 1e-6, err, np.inf)
    np.maximum.at(out, own, err)
    return out


def _shift_rows(tr: Track, frames: list[int]) -> np.ndarray:
    """(n, 5) ``uv``, td ``vel``, ``offset`` of ``tr``'s observations in ``frames`` as its
    factor shifts them (``td_shift``); an unshifted one has vel 0 and offset NaN."""
    out = np.empty((len(frames), 5))
    for i, f in enumerate(frames):
        s = tr.td_shift.get(f)
        out[i, 0:2] = tr.obs[f].uv
        out[i, 2:4], out[i, 4] = (0.0, np.nan) if s is None else (s[0], s[1])
    return out
