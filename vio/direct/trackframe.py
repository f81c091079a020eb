"""TrackFrame (seed Algorithm 3): direct alignment of a new frame to the last keyframe.

Estimates T_kf_new (pose of the new camera in the keyframe camera, ``gtsam.Pose3``,
retract T Exp(xi), xi = [omega, v]) and the new frame's affine brightness [a, b]
from keyframe points with known inverse depths, coarse-to-fine over an image pyramid.
Each level runs Levenberg-Marquardt with Nielsen damping (``vio.direct.lm``; the
seed's lambda halving/doubling becomes Nielsen's mu update) on the 8-DoF state, with
the photometric residual of ``factors.photometric`` (host = keyframe with T = I and
T_b_c = I, target = new frame), weights W = c^2 / (c^2 + |grad|^2) /
(2 sigma_I^2 + (dr/drho)^2 V) (seed) and Huber on the whitened residual. A pattern
pixel that falls outside the new image is charged a constant whitened residual
``oob_residual`` with zero Jacobian, so moving points out of view never lowers the cost.

With a ``MotionPrior`` (the IMU-predicted relative pose and its sigmas) six more rows
``diag(1/sigma) Log(T_prior^-1 T)`` join every level's problem, as in DM-VIO's coarse
tracking with the IMU. Without it the coarse levels wander along the photometric
valley where a small rotation and a lateral translation trade off (a plane at ~1 m:
real MH_01 keyframe 29 ends 0.30 deg off from a prediction 0.004 deg off the truth,
0.03 deg from the truth itself), and the finer levels stay in the wrong basin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from factors.image_ops import BilinearImage, pyramid, scale_intrinsics, scale_pixels
from factors.photometric import HostPatch, Pinhole, make_host_patch
from factors.photometric_shutter import Shutter, rolled_bearings
from factors.photometric_warp import pixel_row_s, rows_or_pinhole
from factors.photometric_kernel import MAX_LOG_GAIN
from factors.trackframe_kernel import track_rows
from vio.conventions import pose_from_matrix
from vio.direct.config import TrackConfig
from vio.direct.lm import levenberg_marquardt

_IDENTITY = gtsam.Pose3()


@dataclass(frozen=True, eq=False)
class TrackingReference:
    """Keyframe data for tracking, per pyramid level (index 0 = full resolution).

    ``K`` intrinsics, ``patches`` host patches of the N points, ``idepth`` (N,) 1/m and
    ``idepth_var`` (N,) 1/m^2 in the keyframe camera, ``ab`` keyframe affine [a, b]."""

    K: tuple[Pinhole, ...]
    patches: tuple[HostPatch, ...]
    idepth: np.ndarray
    idepth_var: np.ndarray
    ab: np.ndarray

    @property
    def levels(self) -> int:
        return len(self.K)


@dataclass(frozen=True)
class MotionPrior:
    """Gaussian prior on ``T_kf_new`` (the IMU prediction): mean ``T`` and isotropic
    sigmas ``sigma_rot`` (rad) and ``sigma_trans`` (m) of the tangent [omega, v]."""

    T: gtsam.Pose3
    sigma_rot: float
    sigma_trans: float

    def rows(self, T: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residual (6,) ``Log(T_prior^-1 T) / sigma`` and its Jacobian (6, 8)
        along ``T Exp(h)`` (the affine columns are zero)."""
        xi = gtsam.Pose3.Logmap(self.T.between(T))
        w = np.repeat([1.0 / self.sigma_rot, 1.0 / self.sigma_trans], 3)
        J = np.zeros((6, 8))
        J[:, :6] = w[:, None] * gtsam.Pose3.LogmapDerivative(xi)
        return w * xi, J

    @classmethod
    def from_imu(cls, T_init: gtsam.Pose3, pim, dt: float, tc: TrackConfig) -> "MotionPrior | None":
        """The IMU prediction ``T_init`` (camera of the new keyframe in the previous one's,
        ``dt`` s apart; ``pim`` the preintegration over that interval) as TrackFrame's
        prior: sigmas from the preintegration covariance (rotation, position blocks) and
        the floors of ``tc`` (``TrackConfig``); None without ``imu_prior`` or readings."""
        if not tc.imu_prior or pim is None or pim.deltaTij() <= 0:
            return None
        cov = np.asarray(pim.preintMeasCov())
        s_rot = max(tc.prior_rot_sigma, float(np.sqrt(np.trace(cov[:3, :3]) / 3.0)))
        s_tr = float(np.hypot(tc.prior_trans_sigma, tc.prior_vel_sigma * dt))
        s_tr = max(s_tr, float(np.sqrt(np.trace(cov[3:6, 3:6]) / 3.0)))
        return cls(T_init, s_rot, s_tr)


@dataclass(frozen=True)
class LevelStats:
    """One pyramid level of a TrackFrame call; ``rmse`` (intensity units) the median over
    the points of their pattern RMSE."""

    level: int
    iterations: int
    evaluations: int
    initial_cost: float
    cost: float
    rmse: float
    valid_fraction: float
    stop_reason: str


@dataclass(frozen=True)
class TrackResult:
    """``T_kf_new`` pose of the new camera in the keyframe camera; ``a``, ``b`` the new
    frame's affine brightness; ``rmse`` level-0 median point RMSE (intensity units); ``iterations`` summed
    over levels; ``ok`` enough points stayed in view and the RMSE is plausible."""

    T_kf_new: gtsam.Pose3
    a: float
    b: float
    rmse: float
    iterations: int
    ok: bool
    levels: tuple[LevelStats, ...]


def image_pyramid(image: np.ndarray | Sequence[BilinearImage], levels: int) -> tuple[BilinearImage, ...]:
    """``levels`` samplers of ``image`` (H, W), level 0 full resolution, each next one
    half the size (``factors.image_ops.pyramid``); an already built pyramid (a sequence
    of ``BilinearImage``, at least ``levels`` long) is passed through."""
    if isinstance(image, np.ndarray):
        return tuple(BilinearImage(img) for img in pyramid(image, levels))
    if len(image) < levels:
        raise ValueError(f"image pyramid has {len(image)} levels, {levels} needed")
    return tuple(image[:levels])


def make_reference(image: np.ndarray | Sequence[BilinearImage], uv: np.ndarray, idepth: np.ndarray, K: Pinhole,
                   idepth_var: np.ndarray | None = None, ab: tuple[float, float] = (0.0, 0.0),
                   config: TrackConfig = TrackConfig()) -> TrackingReference:
    """Sample the keyframe ``image`` (H, W, or its ``image_pyramid``) around pixels
    ``uv`` (N, 2) on every level."""
    uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
    idepth = np.asarray(idepth, dtype=np.float64).reshape(-1)
    if uv.shape[0] != idepth.shape[0] or uv.shape[1] != 2:
        raise ValueError(f"make_reference: uv {uv.shape} and idepth {idepth.shape} disagree")
    var = np.zeros_like(idepth) if idepth_var is None else np.asarray(idepth_var, float).reshape(-1)
    Ks, patches = [], []
    for lev, img in enumerate(image_pyramid(image, config.levels)):
        Kl = Pinhole(*scale_intrinsics(K.fx, K.fy, K.cx, K.cy, lev))
        Ks.append(Kl)
        patches.append(make_host_patch(img, scale_pixels(uv, lev), Kl))
    return TrackingReference(tuple(Ks), tuple(patches), idepth, var, np.asarray(ab, float))


def _shutter_args(ref: TrackingReference, lev: int, shutter: Shutter | None) -> tuple:
    """The kernel's rolling-shutter arguments at level ``lev``: (bearings moved to the
    keyframe's row 0, their rho part sv (N, 3), the new frame's twist (omega, v), line
    time, the new frame's row model at level 0: rows are full-resolution sensor rows); no
    shutter: the plain bearings, zeros and line time 0."""
    b = ref.patches[lev].bearing
    if shutter is None or shutter.line_time_s <= 0.0:
        return b, np.zeros((len(ref.idepth), 3)), np.zeros(3), np.zeros(3), 0.0, np.zeros(9)
    lt = float(shutter.line_time_s)
    bw, sv = rolled_bearings(b, pixel_row_s(lt, ref.patches[0].uv, shutter.host_rows), shutter.host)
    tw = np.asarray(shutter.target, float)
    return bw, sv, tw[:3].copy(), tw[3:].copy(), lt, rows_or_pinhole(shutter.target_rows, ref.K[0])


def _level_problem(ref: TrackingReference, lev: int, target: BilinearImage, cfg: TrackConfig,
                   prior: MotionPrior | None = None, shutter: Shutter | None = None):
    """Residual function x = (T_kf_new, ab) -> (whitened r, J (m, 8)) of one level, the
    ``prior`` rows last; ``shutter``: the keyframe's (host) and new frame's (target)
    rolling shutter."""
    patch, K = ref.patches[lev], ref.K[lev]
    N, P = patch.intensity.shape
    var = ref.idepth_var if cfg.use_idepth_var else np.zeros(N)
    bearing, *rolling = _shutter_args(ref, lev, shutter)
    args = (np.ascontiguousarray(bearing), np.ascontiguousarray(patch.intensity),
            np.ascontiguousarray(patch.grad_sq), np.ascontiguousarray(patch.valid),
            np.ascontiguousarray(ref.idepth, float), np.ascontiguousarray(var, float))
    Kv = np.array([K.fx, K.fy, K.cx, K.cy])
    stack = target._stack
    ab_i = np.asarray(ref.ab, float)
    r_w, J = np.empty(N * P), np.empty((N * P, 8))
    r_raw, valid = np.empty((N, P)), np.empty((N, P), bool)

    def evaluate(x) -> None:
        T, ab = x
        Ti = T.inverse()       # keyframe camera -> new camera
        # the factors' gain bound: a diverged affine a must not overflow (inf intensities)
        s = math.exp(min(max(float(ab[0]) - ab_i[0], -MAX_LOG_GAIN), MAX_LOG_GAIN))
        track_rows(*args, Ti.rotation().matrix(), Ti.translation(), Kv, stack, s, ab_i[1], float(ab[1]),
                   cfg.grad_c ** 2, 2.0 * cfg.sigma_I ** 2, cfg.oob_residual, r_w, J, r_raw, valid, *rolling)

    def fun(x):
        evaluate(x)
        if prior is None:
            return r_w.copy(), J.copy()
        rp, Jp = prior.rows(x[0])
        return np.concatenate([r_w, rp]), np.concatenate([J, Jp])

    def rmse(x):
        """Median over the points of their pattern RMSE (robust to the outlier points a
        real scene always has: occlusions, wrong stereo depths, specularities) and the
        fraction of valid residuals."""
        evaluate(x)
        n = valid.sum(1)
        per = np.sqrt((r_raw ** 2).sum(1) / np.maximum(n, 1))[n > 0]
        if not per.size:     # no point inside (a keyframe without points: darkness, no texture)
            return float("inf"), float(valid.mean()) if valid.size else 0.0
        return float(np.median(per)), float(valid.mean())

    return fun, rmse


def _retract(x, h):
    return x[0].retract(h[:6]), x[1] + h[6:]


def body_pose(T_w_cp: gtsam.Pose3, T_cp_c: gtsam.Pose3, T_b_c: gtsam.Pose3) -> gtsam.Pose3:
    """``T_w_b`` of a frame aligned at ``T_cp_c`` (``TrackResult.T_kf_new``) to the keyframe
    whose camera is at ``T_w_cp``, re-orthonormalized: composing the keyframe's rotation
    three times tripled its rounding error at every keyframe (1e-16 -> 0.5% shear by
    keyframe 28 of real MH_01, then divergence)."""
    return pose_from_matrix(T_w_cp.compose(T_cp_c).compose(T_b_c.inverse()).matrix())


def track_frame(ref: TrackingReference, image: np.ndarray | Sequence[BilinearImage],
                T_kf_new_init: gtsam.Pose3 = _IDENTITY, ab_init: tuple[float, float] | None = None,
                config: TrackConfig = TrackConfig(), prior: MotionPrior | None = None,
                shutter: Shutter | None = None) -> TrackResult:
    """Align ``image`` (H, W, or its ``image_pyramid``) to the keyframe ``ref``, starting from ``T_kf_new_init`` and
    ``ab_init`` (default: the keyframe's affine), with an optional motion ``prior``;
    ``shutter``: both images' rolling shutter (``factors.photometric_shutter.Shutter``, host = the
    keyframe camera's twist, target = the new camera's)."""
    cfg = config
    if ref.levels < cfg.levels:
        raise ValueError(f"reference has {ref.levels} levels, config asks for {cfg.levels}")
    ab0 = ref.ab if ab_init is None else np.asarray(ab_init, float)
    x = (T_kf_new_init, ab0.astype(float).copy())
    pyr = image_pyramid(image, cfg.levels)
    stats, total = [], 0
    for lev in reversed(range(cfg.levels)):
        fun, rmse = _level_problem(ref, lev, pyr[lev], cfg, prior, shutter)
        max_it = cfg.iters[cfg.levels - 1 - lev]
        res = levenberg_marquardt(fun, x, cfg.lm(max_it), retract=_retract,
                                  n_plain=0 if prior is None else 6)
        x = res.x
        total += res.iterations
        e, frac = rmse(x)
        stats.append(LevelStats(lev, res.iterations, res.evaluations, res.initial_cost, res.cost,
                                e, frac, res.stop_reason))
    final = stats[-1]
    ok = bool(final.valid_fraction >= cfg.min_valid_fraction and final.rmse <= cfg.max_rmse
              and np.all(np.isfinite(x[1])))
    return TrackResult(x[0], float(x[1][0]), float(x[1][1]), final.rmse, total, ok, tuple(stats))
