"""Stereo-inertial initialization from the first stereo pair, whatever the motion.

The stereo baseline fixes metric scale at once, so no IMU excitation is needed (the
anchors: VINS-Fusion's stereo start, which poses frames by PnP and aligns the gyro bias,
and ORB-SLAM3's stereo-inertial inertial-only optimization with the scale held at 1):

1. Structure: the cam0/cam1 matches (``FeatureFrame.right_uv``) of the window's first
   frame are triangulated in its camera c0 (``landmarks.stereo_depth``).
2. Visual poses: every later frame of the window is posed by RANSAC PnP (normalized
   coordinates) and a Levenberg-Marquardt refinement against those points and the
   stereo points of the frames posed before it (moved into c0), then all poses and
   points by a stereo bundle adjustment, giving ``T_b0_bk`` with metric translation
   (frames: b0 the first body frame).
3. Gyro bias: Gauss-Newton on ``sum_k |Log(dR_k(bg)^T R_bk^T R_bk+1)|^2`` with the
   preintegrated rotations' first-order bias correction.
4. Velocity and gravity: with the gyro bias fixed, the preintegrated increments (zero
   accelerometer bias) give per interval ``p_j - p_i - R_i dp_ij = v_i dt + g dt^2 / 2``
   and ``R_i dv_ij = v_j - v_i - g dt``, linear in the velocities ``v_k`` and gravity
   ``g`` (all in b0), solved by weighted least squares. Even at constant velocity the
   accelerometer's gravity is separated from the (known, metric) motion.
5. Acceptance: enough posed frames and PnP inliers, ``|g|`` within
   ``max_gravity_error`` of the nominal value (the accelerometer bias along gravity
   hides in it), the gravity direction's standard deviation below
   ``max_gravity_sigma_deg`` (from the least squares' covariance) and the first
   velocity's below ``max_v0_sigma``. Otherwise the pipeline waits for a longer window.

The result is the first frame's state in a gravity-aligned world with zero yaw, with
prior sigmas from the alignment's covariance and the accelerometer bias along gravity
from the ``|g|`` mismatch (the only component separable from tilt here); the pipeline starts the smoother there and
replays the window, so every frame from the first stereo pair on gets a pose, and the
smoother's stereo and IMU factors then refine gravity, velocity and biases.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np

from vio.backend.config import BackendConfig, StereoInitConfig
from vio.backend.dynamic_init import InitWindow
from vio.backend.graph import image_velocity
from vio.backend.gyro_init import gyro_bias
from vio.backend.init import InitialState, gravity_aligned_rotation
from vio.backend.landmarks import stereo_depth
from vio.errors import one_line
from vio.imu import combined_params, concat, mean_gyro
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib

log = logging.getLogger(__name__)
NAN = float("nan")


@dataclass(frozen=True)
class StereoAlignResult:
    """Outcome of :func:`stereo_align`. ``gravity_sigma_deg``: standard deviation of the
    gravity direction; ``v0_sigma`` (m/s): largest standard deviation of the first
    velocity; ``gravity_error``: relative ``|g|`` error before it is fixed; ``n_posed``:
    frames posed by PnP; ``n_points``: stereo points of the first frame. NaN where not
    reached."""

    ok: bool
    state: InitialState | None
    reason: str
    n_points: int = 0
    n_posed: int = 0
    gravity_sigma_deg: float = NAN
    v0_sigma: float = NAN
    gravity_error: float = NAN


def stereo_points(fr: FeatureFrame, T_c0_c1: gtsam.Pose3, min_depth: float, max_depth: float
                  ) -> dict[int, np.ndarray]:
    """Landmark id -> point (3,) in cam0 (m) of the frame's stereo matches with a depth
    in ``[min_depth, max_depth]``."""
    out: dict[int, np.ndarray] = {}
    if fr.right_uv is None:
        return out
    for lid, uv, ruv in zip(fr.ids, fr.uv, fr.right_uv):
        if not np.all(np.isfinite(ruv)):
            continue
        z = stereo_depth(uv, ruv, T_c0_c1)
        if np.isfinite(z) and min_depth <= z <= max_depth:
            out[int(lid)] = np.array([uv[0], uv[1], 1.0]) * z
    return out


def pnp_pose(points: dict[int, np.ndarray], fr: FeatureFrame, guess: gtsam.Pose3 | None,
             thresh: float, min_inliers: int) -> tuple[gtsam.Pose3 | None, int]:
    """``T_c0_cj`` of frame ``fr`` from ``points`` (id -> point in cam0 of frame 0) by RANSAC
    PnP on normalized coordinates (``thresh``: inlier error, normalized) and an LM
    refinement on the inliers; (None, n) with fewer than ``min_inliers`` inliers."""
    common = [(points[int(l)], uv) for l, uv in zip(fr.ids, fr.uv) if int(l) in points]
    if len(common) < max(min_inliers, 6):
        return None, len(common)
    obj = np.array([c[0] for c in common], np.float64)
    img = np.array([c[1] for c in common], np.float64)
    K = np.eye(3)
    ok, rvec, tvec, inl = False, None, None, None
    if guess is not None:
        T = guess.inverse()   # T_cj_c0
        rvec = cv2.Rodrigues(T.rotation().matrix())[0]
        tvec = T.translation().reshape(3, 1).copy()
    try:   # OpenCV 5's robust estimators assert on some near-degenerate sets
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, rvec, tvec, guess is not None,
                                                 iterationsCount=100, reprojectionError=thresh,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < min_inliers:
            return None, 0 if inl is None else len(inl)
        idx = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, None, rvec, tvec)
    except cv2.error:
        return None, 0
    R = cv2.Rodrigues(rvec)[0]
    return gtsam.Pose3(gtsam.Rot3(R), tvec.ravel()).inverse(), len(idx)


def refine_poses(points: dict[int, np.ndarray], frames, poses: list[gtsam.Pose3],
                 T_c0_c1: gtsam.Pose3, sigma: float, huber: float) -> list[gtsam.Pose3]:
    """Stereo bundle adjustment of the camera poses ``T_c0_cj`` (first one fixed) and the
    points (in c0) from every cam0 and cam1 observation of them (normalized
    coordinates, noise ``sigma``, Huber kernel at ``huber``; GTSAM's C++ projection
    factors). Each frame's own stereo pair re-measures the depths that PnP took from
    the frame where each point was first triangulated."""
    Xk, Pk = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.P
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber / sigma),
                                           gtsam.noiseModel.Isotropic.Sigma(2, sigma))
    g, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(gtsam.PriorFactorPose3(Xk(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for j, (fr, T) in enumerate(zip(frames, poses)):
        vals.insert(Xk(j), T)
        right = fr.right_uv if fr.right_uv is not None else np.full((len(fr.ids), 2), np.nan)
        for lid, uv, ruv in zip(fr.ids, fr.uv, right):
            if int(lid) not in points:
                continue
            g.add(gtsam.GenericProjectionFactorCal3_S2(uv, noise, Xk(j), Pk(int(lid)), K))
            if np.all(np.isfinite(ruv)):
                g.add(gtsam.GenericProjectionFactorCal3_S2(ruv, noise, Xk(j), Pk(int(lid)), K, T_c0_c1))
    for lid, p in points.items():
        vals.insert(Pk(lid), p)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(20)
    try:
        est = gtsam.LevenbergMarquardtOptimizer(g, vals, params).optimize()
    except RuntimeError as exc:    # cheirality or an indeterminate system: keep PnP
        log.info("stereo initialization: bundle adjustment failed (%s)", one_line(exc))
        return poses
    return [est.atPose3(Xk(j)) for j in range(len(poses))]


def alignment_system(pims: list, R_b: np.ndarray, p_b: np.ndarray, bg: np.ndarray,
                     gravity: np.ndarray, cfg: StereoInitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Weighted linear system ``A x = b`` over ``x = [v_0..v_K-1, g]`` (3K+3, b0 frame)
    from visual poses (``R_b`` (K,3,3), ``p_b`` (K,3) m) and the preintegrations at gyro
    bias ``bg`` (``gravity``: the params' n_gravity). Rows are weighted by
    ``pos_sigma_m`` (position) and ``accel_sigma * dt`` (velocity)."""
    K = len(p_b)
    n = 3 * K + 3
    A, b = [], []
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
    I3 = np.eye(3)
    for i, pim in enumerate(pims):
        j, dt = i + 1, pim.deltaTij()
        ns = pim.predict(gtsam.NavState(), bias)
        dp = ns.position() - 0.5 * dt * dt * gravity
        dv = ns.velocity() - dt * gravity
        wp, wv = 1.0 / cfg.pos_sigma_m, 1.0 / (cfg.accel_sigma * dt + 1e-3)
        Ap, Av = np.zeros((3, n)), np.zeros((3, n))
        Ap[:, 3 * i:3 * i + 3], Ap[:, 3 * K:] = dt * I3, 0.5 * dt * dt * I3
        Av[:, 3 * j:3 * j + 3], Av[:, 3 * i:3 * i + 3], Av[:, 3 * K:] = I3, -I3, -dt * I3
        A += [wp * Ap, wv * Av]
        b += [wp * (p_b[j] - p_b[i] - R_b[i] @ dp), wv * R_b[i] @ dv]
    return np.vstack(A), np.concatenate(b)


def velocity_gravity(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Velocities (K,3) and gravity (3,) (b0) solving :func:`alignment_system`, and the
    covariance (3K+3, 3K+3) of ``[v_0..v_K-1, g]``, inflated by the a posteriori variance
    factor when the residuals exceed the rows' weights."""
    H = A.T @ A
    cov = np.linalg.inv(H)
    x = cov @ (A.T @ b)
    dof = A.shape[0] - A.shape[1]
    if dof > 0:   # a posteriori variance factor: never trust the weights more than the fit
        cov *= max(1.0, float(np.sum((A @ x - b) ** 2)) / dof)
    return x[:-3].reshape(-1, 3), x[-3:], cov


def velocities_given_gravity(A: np.ndarray, b: np.ndarray, g0: np.ndarray) -> np.ndarray:
    """Velocities (K,3) of :func:`alignment_system` with gravity fixed at ``g0`` (b0)."""
    return np.linalg.lstsq(A[:, :-3], b - A[:, -3:] @ g0, rcond=None)[0].reshape(-1, 3)


def _visual_poses(win, cam: CameraCalib, T_c0_c1: gtsam.Pose3, cfg: BackendConfig
                  ) -> tuple[list[gtsam.Pose3 | None], int, int, dict]:
    """``T_b0_bk`` per keyframe of the window (None where PnP failed), the number of
    first-frame stereo points, the smallest inlier count and the map (landmark id -> point
    in the first frame's cam0, m). Each frame is posed against
    the map of every earlier posed frame's stereo points (in c0), so the window may last
    longer than the first frame's points stay in view (close range: 0.45 s on real
    MH_01 from frame 200, where posing against the first frame alone never started)."""
    sc, vc = cfg.init.stereo, cfg.vision
    pts = stereo_points(win.features[0], T_c0_c1, vc.min_depth_m, vc.max_stereo_depth_m)
    points = dict(pts)
    T_b_c = cam.T_b_c
    cams: list[gtsam.Pose3 | None] = [gtsam.Pose3()]
    guess, worst = gtsam.Pose3(), len(pts)
    fx = cam.intrinsics[0]
    for fr in win.features[1:]:
        T_c0_cj, n_in = pnp_pose(points, fr, guess, sc.pnp_px / fx, sc.min_inliers)
        worst = min(worst, n_in)
        cams.append(T_c0_cj)
        if T_c0_cj is None:
            continue
        guess = T_c0_cj
        for lid, p in stereo_points(fr, T_c0_c1, vc.min_depth_m, vc.max_stereo_depth_m).items():
            if lid not in points:
                points[lid] = T_c0_cj.transformFrom(p)
    if all(c is not None for c in cams) and len(pts) >= sc.min_points:
        cams = refine_poses(points, win.features, cams, T_c0_c1, vc.pixel_sigma / fx, sc.pnp_px / fx)
    poses = [None if c is None else T_b_c.compose(c).compose(T_b_c.inverse()) for c in cams]
    return poses, len(pts), worst, points


def rolled_back(win, cam: CameraCalib, T_c0_c1: gtsam.Pose3, poses: list[gtsam.Pose3], v_b0: np.ndarray,
                bg: np.ndarray, points: dict):
    """``win`` with every observation moved back to its frame's row-0 time, the time of the
    frame's state (a rolling shutter of ``cam.line_time_s``): uv - s * (image velocity), s
    = row * line_time, the velocity of the point (``points``, in the first frame's cam0;
    at infinity where not mapped) seen by the camera's twist: the gyro's mean over the
    readout less ``bg`` (``vio.imu.KeyframeRates``) and the body velocity ``v_b0`` (K, 3,
    in the first body frame) of the frame at ``poses`` (``T_b0_bk``); cam1 observations
    at their own rows with cam1's twist."""
    lt = cam.line_time_s
    imu = win.imu_all if win.imu_all is not None else concat(list(win.imu))
    T_b_c = cam.T_b_c
    R_c_b, p_b_c = T_b_c.rotation().matrix().T, T_b_c.translation()
    R_10, t_01 = T_c0_c1.rotation().matrix().T, T_c0_c1.translation()
    readout = int(round(cam.readout_s * 1e9))
    frames = []
    for k, fr in enumerate(win.features):
        t0 = int(min(max(fr.t_ns, imu.t_ns[0]), imu.t_ns[-1]))
        w_b = mean_gyro(imu, t0, int(min(t0 + readout, imu.t_ns[-1]))) - bg
        v_b = poses[k].rotation().unrotate(v_b0[k])
        w0, v0 = R_c_b @ w_b, R_c_b @ (v_b + np.cross(w_b, p_b_c))
        T_ck_c0 = poses[k].compose(T_b_c).inverse().compose(T_b_c)       # first cam0 -> cam0 of k
        z0 = np.array([T_ck_c0.transformFrom(points[int(i)])[2] if int(i) in points else 1e6 for i in fr.ids])
        z0 = np.where(z0 > 0.05, z0, 1e6)
        uv = _moved(fr.uv, z0, w0, v0, fr.row * lt)
        ruv = fr.right_uv
        if ruv is not None:
            rows = fr.row if fr.right_row is None else np.where(np.isfinite(fr.right_row), fr.right_row, fr.row)
            z1 = np.maximum(z0 - t_01[2], 0.05)        # ~ the depth in cam1 (a sideways baseline)
            ruv = _moved(ruv, z1, R_10 @ w0, R_10 @ (v0 + np.cross(w0, t_01)), rows * lt)
        frames.append(FeatureFrame(fr.t_ns, fr.ids, uv, fr.velocity, fr.row, ruv, fr.right_velocity, fr.right_row))
    return InitWindow(win.t_ns, tuple(frames), win.imu, win.imu_all)


def _moved(uv: np.ndarray, depth: np.ndarray, w: np.ndarray, v: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Normalized observations ``uv`` (n, 2) moved back by ``s`` (n,, s; NaN: not moved)."""
    n = len(uv)
    vel = image_velocity(uv, depth, np.tile(w, (n, 1)), np.tile(v, (n, 1))) if n else np.zeros((0, 2))
    return uv - np.where(np.isfinite(s), s, 0.0)[:, None] * vel


def stereo_align(win, cam: CameraCalib, T_c0_c1: gtsam.Pose3, imu_calib: ImuCalib,
                 cfg: BackendConfig, rolled: bool = False) -> StereoAlignResult:
    """The first keyframe's state of ``win`` (``dynamic_init.InitWindow``) from stereo
    structure, PnP poses and a linear IMU alignment (see module docstring). With a rolling
    shutter an accepted alignment is solved again on the observations moved back to their
    frames' row 0 by its own motion (``rolled_back``; ``rolled``: this is that second pass)."""
    from vio.backend.vi_align import preintegrate_window
    sc = cfg.init.stereo
    poses, n_pts, worst, points = _visual_poses(win, cam, T_c0_c1, cfg)
    n_posed = sum(p is not None for p in poses)
    if n_pts < sc.min_points:
        return StereoAlignResult(False, None, f"only {n_pts} stereo points in the first frame", n_pts)
    if n_posed < len(poses):
        return StereoAlignResult(False, None, f"PnP failed in {len(poses) - n_posed} of {len(poses)} "
                                 f"frames (fewest inliers {worst})", n_pts, n_posed)
    params = combined_params(imu_calib, cfg.imu)
    gravity = np.asarray(params.n_gravity, float)
    pims = preintegrate_window(win, params)
    R_b = np.array([p.rotation().matrix() for p in poses])
    p_b = np.array([p.translation() for p in poses])
    bg = gyro_bias(pims, [(k, k + 1, R_b[k].T @ R_b[k + 1]) for k in range(len(pims))])
    A, b = alignment_system(pims, R_b, p_b, bg, gravity, sc)
    v, g, cov = velocity_gravity(A, b)
    g_norm = cfg.imu.gravity
    gerr = abs(np.linalg.norm(g) - g_norm) / g_norm
    u = g / np.linalg.norm(g)
    P = np.eye(3) - np.outer(u, u)
    g_cov = P @ cov[-3:, -3:] @ P
    gsig = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(g_cov).max(), 0.0)) / np.linalg.norm(g)))
    vsig = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))
    diag = dict(n_points=n_pts, n_posed=n_posed, gravity_sigma_deg=gsig, v0_sigma=vsig,
                gravity_error=gerr)
    if not gerr <= sc.max_gravity_error:
        return StereoAlignResult(False, None, f"|g| off by {100 * gerr:.1f}%", **diag)
    if not gsig <= sc.max_gravity_sigma_deg:
        return StereoAlignResult(False, None, f"gravity direction poorly determined "
                                 f"(sigma {gsig:.2f} deg)", **diag)
    if not vsig <= sc.max_v0_sigma:
        return StereoAlignResult(False, None, f"velocity poorly determined (sigma {vsig:.3f} m/s)",
                                 **diag)
    g0 = g_norm * u
    v = velocities_given_gravity(A, b, g0)
    if cam.line_time_s > 0.0 and not rolled:
        return stereo_align(rolled_back(win, cam, T_c0_c1, poses, v, bg, points), cam, T_c0_c1, imu_calib,
                            cfg, rolled=True)
    R_w_b0 = gravity_aligned_rotation(-g0)
    rp_sigma = max(sc.min_rp_sigma, 2.0 * np.radians(gsig))
    state = InitialState(win.t_ns[0], gtsam.Pose3(R_w_b0, np.zeros(3)), R_w_b0.rotate(v[0]),
                         gtsam.imuBias.ConstantBias((g_norm - np.linalg.norm(g)) * u, bg), "stereo",
                         rp_sigma=rp_sigma, vel_sigma=max(sc.min_vel_sigma, 2.0 * vsig))
    log.info("stereo initialization over %.2f s: gravity sigma %.2f deg, |g| error %.1f%%, "
             "v0 %s m/s (sigma %.3f), gyro bias %s", (win.t_ns[-1] - win.t_ns[0]) * 1e-9, gsig,
             100 * gerr, np.round(state.v_w, 3), vsig, np.round(bg, 4))
    return StereoAlignResult(True, state, "ok", **diag)
