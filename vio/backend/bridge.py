"""The IMU-gap bridge's factors, and vision's share: keyframe poses from the window's points.

Between two keyframes an IMU gap separates, the IMU factor is replaced by the
constant-velocity motion prior of ``factors.motion_prior`` and the biases' random walk
(:func:`bridge_factors`).

Across an IMU gap the new keyframe has only the constant-velocity motion prior
(``factors.motion_prior``) besides vision. With the IMU a few mistracked observations
lose against the preintegrated motion; without it they can win: on the real V1_01
tracks (0.5-s gap at 7 s) three tracks that jump at one keyframe pulled the Huber
solution 1.2 m away, the outlier check then dropped 9 of the 13 good landmarks, and the
run ended at 0.12-0.19 m instead of 0.024 m.

So while bridged keyframes are in the window, each new keyframe is first located by
RANSAC PnP on the window's landmarks (their current world points) and its observations
of them, started at the motion prior's prediction; observations PnP rejects are left out
of this keyframe, and for a bridged keyframe the PnP pose (with the predicted velocity)
is its initial value (the keyframes after the gap keep their IMU prediction). With too
few landmarks or inliers the keyframe keeps the prediction and every observation.
(Measured on real V1_01 features, ``benchmarks/bench_faults.py --at 7``: 0.5-s gap
0.118 -> 0.070 m; at 15 s and 23 s the gaps stay at 0.025-0.030 m.)

IMU readings that are there but wrong (an accelerometer bias step, saturation) are
bridged the same way once vision contradicts them (:func:`imu_contradicted`,
``BridgeConfig.imu_check``): the keyframe interval gets the motion prior instead of its
IMU factor, the keyframe starts at the PnP pose with the previous keyframe's velocity,
and a warning names the keyframes. Left in, a 6 m/s^2 offset for 1 s outweighs the
Huber-weighted landmarks, whose observations then fail the outlier check: at five places
of real MH_01 stereo / hybrid and real MH_05 mono 205-659 mm / 0.96-4.4 m / 2.4-7.7 m;
bridged 8-17 mm / 7-15 mm / 0.07-1.7 m (``benchmarks/README.md``, stop 57).
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from factors.motion_prior import motion_prior_factor
from vio.backend.graph import TD, B, V, X, imu_factor
from vio.backend.stereo_init import pnp_pose
from vio.io.types import FeatureFrame

log = logging.getLogger(__name__)


def bridge_factors(k0: int, k1: int, dt_s: float, accel_density: float, gyro_density: float,
                   bias_walk: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """What stands in for the IMU factor between keyframes k0 and k1 across an IMU gap:
    the constant-velocity motion prior (``factors.motion_prior``; densities in
    m/s^2/sqrt(Hz) and rad/s/sqrt(Hz)) and the biases' random walk over ``dt_s``
    (``bias_walk`` (6,): accelerometer then gyro sigmas per sqrt(s))."""
    dt = max(float(dt_s), 1e-3)
    walk = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(bias_walk, float) * np.sqrt(dt))
    return [motion_prior_factor([X(k0), V(k0), X(k1), V(k1)], dt, accel_density, gyro_density),
            gtsam.BetweenFactorConstantBias(B(k0), B(k1), gtsam.imuBias.ConstantBias(), walk)]


def gyro_rotation_factor(k0: int, k1: int, pim: gtsam.PreintegratedCombinedMeasurements,
                         bias_sigma: float) -> gtsam.NonlinearFactor:
    """The gyro's share of an interval whose IMU factor is held back (the gravity
    re-alignment after a gap, ``vio.backend.realign``): the relative attitude of keyframes
    k0 and k1 from ``pim``'s preintegrated rotation, which a tilted world does not affect.
    Sigma per axis: the preintegration's plus ``bias_sigma`` (rad/s) times the interval;
    the translation is left free (1 km)."""
    dt = max(pim.deltaTij(), 1e-3)
    c = np.diag(np.asarray(pim.preintMeasCov())[:3, :3])
    sig = np.sqrt(np.maximum(c, 0.0) + (bias_sigma * dt) ** 2)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[sig, np.full(3, 1e3)])
    return gtsam.BetweenFactorPose3(X(k0), X(k1), gtsam.Pose3(pim.deltaRij(), np.zeros(3)), noise)


def motion_factors(est, k0: int, k1: int, t_ns: int, contradicted: bool = False) -> tuple[list, bool]:
    """What ties the ``Estimator`` ``est``'s keyframe k1 to k0: the IMU factor, or across
    an IMU gap, while the re-alignment holds the IMU back and where vision ``contradicted``
    the IMU (:func:`imu_contradicted`) (``held``) the motion prior and bias walk of
    :func:`bridge_factors` (with the gyro's relative attitude once the IMU is back after
    a gap). Counts the bridged interval and ends the bridge in ``est``."""
    bridged = est._bridge_t is not None
    held = est.realign.holding(bridged, est.kf_t[k0], t_ns)   # vio.backend.realign
    if not (held or contradicted):
        return [imu_factor(k0, k1, est.pim)], False
    # the still readings served the prediction only (vio.imu.integrate_still)
    fs = _interval_bridge(est, k0, k1, t_ns)
    if not held:
        return fs, True
    if bridged:
        est.bridged += 1
        log.info("t=%d ns: keyframes %d-%d bridged across an IMU gap (%.2f s, motion prior)",
                 t_ns, k0, k1, (t_ns - est.kf_t[k0]) * 1e-9)
        est._bridge_t = None
    else:   # the IMU is back, the world may be tilted: vio.backend.realign
        fs.append(gyro_rotation_factor(k0, k1, est.pim, est.cfg.realign.gyro_sigma))
        est.realign.record(k0, k1, est.pim)
    return fs, True


def _interval_bridge(est, k0: int, k1: int, t_ns: int) -> list[gtsam.NonlinearFactor]:
    """:func:`bridge_factors` of ``est``'s keyframe interval k0 -> k1 (ending at ``t_ns``)."""
    bc = est.cfg.bridge
    return bridge_factors(k0, k1, (t_ns - est.kf_t[k0]) * 1e-9, bc.accel_density, bc.gyro_density, est.bias_walk)


def _report(est, k0: int, k1: int, why: str, *args) -> None:
    """Count keyframe interval k0 -> k1 as contradicted and say so: a warning at the first
    interval of a run of them, then at info level (``why`` % ``args``: what contradicted)."""
    est.imu_contradictions += 1
    (log.warning if est.contradicted_k != k0 else log.info)(
        "keyframes %d-%d: " + why + ": the interval's IMU readings contradict vision and are not used "
        "(motion prior instead; interval #%d)", k0, k1, *args, est.imu_contradictions)
    est.contradicted_k = k1


def replace_imu_factor(est, g: gtsam.NonlinearFactorGraph, k0: int, k1: int, t_ns: int) -> list:
    """Keyframe k1's interval bridged after all: its IMU factor, ``g``'s first factor, replaced
    by :func:`bridge_factors` (the motion prior in its slot, the bias walk appended, so the
    positions the other factors recorded hold), when a factor source's own alignment
    contradicted the IMU (``FactorSource.imu_contradicted``: direct mode's TrackFrame).
    Counts the interval and warns as :func:`imu_contradicted` does; returns the factors."""
    fs = _interval_bridge(est, k0, k1, t_ns)
    g.replace(0, fs[0])
    for f in fs[1:]:
        g.add(f)
    _report(est, k0, k1, "the photometric alignment is away from the IMU prediction")
    est.contradicted_t = t_ns
    return fs


def _gated(pts: dict[int, np.ndarray], fr: FeatureFrame, T_w_c: gtsam.Pose3, thresh: float) -> FeatureFrame:
    """``fr`` without the observations of landmarks in ``pts`` (id -> world point) that
    camera pose ``T_w_c`` re-projects farther than ``thresh`` (normalized) or behind it."""
    T_c_w = T_w_c.inverse()
    keep = np.ones(len(fr.ids), bool)
    for i, (lid, uv) in enumerate(zip(fr.ids, fr.uv)):
        p = pts.get(int(lid))
        if p is None:
            continue
        q = T_c_w.transformFrom(p)
        if not (q[2] > 0 and np.linalg.norm(q[:2] / q[2] - uv) <= thresh):
            keep[i] = False
    return fr if keep.all() else fr.subset(keep)


def locate(ids_w: np.ndarray, p_w: np.ndarray, fr: FeatureFrame, pred: gtsam.Pose3, T_b_c: gtsam.Pose3,
           thresh: float, min_inliers: int, pred_thresh: float = np.inf) -> tuple[gtsam.Pose3 | None, FeatureFrame]:
    """``T_w_b`` of the frame ``fr`` (normalized cam0 observations) by RANSAC PnP against
    the landmarks ``ids_w`` (N,) at world points ``p_w`` (N, 3), from the predicted body
    pose ``pred``; ``thresh``: inlier error (normalized units). Returns (pose or None,
    ``fr`` without the observations of landmarks PnP rejected; when PnP fails, without
    those the prediction re-projects farther than ``pred_thresh``)."""
    pts = {int(i): np.asarray(p, float) for i, p in zip(ids_w, p_w)}
    T_w_c0 = pred.compose(T_b_c)
    pose_c, n = pnp_pose(pts, fr, T_w_c0, thresh, min_inliers)
    if pose_c is None:
        return None, (fr if not np.isfinite(pred_thresh) else _gated(pts, fr, T_w_c0, pred_thresh))
    return pose_c.compose(T_b_c.inverse()), _gated(pts, fr, pose_c, thresh)


def gate_bridged(est, features: FeatureFrame, pred: gtsam.NavState,
                 keep_pose: bool = False) -> tuple[gtsam.NavState, FeatureFrame]:
    """A keyframe's initial state and observations while bridged keyframes are in the
    window (module docstring); ``keep_pose``: only the observations are gated, the
    initial state stays ``pred`` (an IMU prediction)."""
    vc = est.cfg.vision
    ids, pts = est.landmarks_w()
    if len(ids) < est.cfg.bridge.pnp_min_inliers:
        return pred, features
    thresh = vc.outlier_px / est.cam.intrinsics[0]
    bc = est.cfg.bridge
    T, out = locate(ids, pts, features, pred.pose(), est.extrinsic(), thresh, bc.pnp_min_inliers,
                    bc.pred_gate_px / est.cam.intrinsics[0])
    if T is None:
        log.info("keyframe %d (bridged window): PnP failed on %d window landmarks; %d observation(s) "
                 "farther than %.0f px from the prediction left out", est.k + 1, len(ids),
                 len(features.ids) - len(out.ids), bc.pred_gate_px)
        return pred, out
    dropped = len(features.ids) - len(out.ids)
    log.info("keyframe %d (bridged window) located by PnP on %d window landmarks (%.3f m from "
             "its prediction); %d observation(s) left out", est.k + 1, len(ids),
             float(np.linalg.norm(T.translation() - pred.pose().translation())), dropped)
    return (pred if keep_pose else gtsam.NavState(T, pred.velocity())), out


def _within(est, t: int | None, t_ns: int) -> bool:
    """Whether ``t`` (ns; None: never) is at most ``BridgeConfig.imu_check_hold_s`` before ``t_ns``."""
    return t is not None and t_ns - t <= est.cfg.bridge.imu_check_hold_s * 1e9


def within_hold(est, t_ns: int) -> bool:
    """Whether an interval a factor source's alignment contradicted ended at most
    ``BridgeConfig.imu_check_hold_s`` before ``t_ns``."""
    return _within(est, est.contradicted_t, t_ns)


def contradicts(bc, dist_m: float, ang_rad: float, dt_s: float = 0.0, held: bool = False) -> bool:
    """Whether an alignment ``dist_m`` / ``ang_rad`` from the IMU prediction over ``dt_s``
    contradicts the IMU (``BridgeConfig`` ``bc``; the landmark check's PnP pose, direct
    mode's TrackFrame): at least ``imu_check_min_m`` (times ``(dt_s / imu_check_ref_s)^2``
    over an interval longer than ``imu_check_ref_s``) and at most ``imu_check_max_deg``;
    ``held`` (within ``imu_check_hold_s`` of a contradicted interval) a residual
    acceleration ``2 d / dt^2`` of at least ``imu_check_hold_accel``: the held intervals
    are short and the IMU's own error over one is a few mm."""
    if not bc.imu_check:
        return False
    if held:
        return 2.0 * dist_m / max(dt_s, 1e-3) ** 2 >= bc.imu_check_hold_accel
    return (dist_m >= bc.imu_check_min_m * long_interval(bc, dt_s)
            and float(np.degrees(ang_rad)) <= bc.imu_check_max_deg)


def long_interval(bc, dt_s: float) -> float:
    """How much farther from the IMU prediction over ``dt_s`` seconds a visual alignment may
    land before it is out of the ordinary (``BridgeConfig`` ``bc``): 1 up to
    ``imu_check_ref_s``, then ``(dt_s / imu_check_ref_s)^2``, as the prediction's own error
    grows (a camera gap: 1.2 s on real MH_01 left a right prediction 3 cm off)."""
    return max(1.0, dt_s / bc.imu_check_ref_s) ** 2


def imu_held(est, t_ns: int) -> bool:
    """Whether the interval ending at ``t_ns`` is bridged because it ends within the hold
    (:func:`within_hold`); counted and logged."""
    held = within_hold(est, t_ns)
    t = est.contradicted_t
    if held:
        est.imu_contradictions += 1
        log.info("keyframes %d-%d: held without the IMU factor (%.2f s after an interval vision contradicted; "
                 "interval #%d)", est.k, est.k + 1, (t_ns - t) * 1e-9, est.imu_contradictions)
    return held


def imu_contradicted(est, features: FeatureFrame | None, pred: gtsam.NavState,
                     shift: gtsam.Pose3 | None = None) -> gtsam.Pose3 | None:
    """The new keyframe's ``T_w_b`` by RANSAC PnP on the window's landmarks
    (``Estimator.check_points``) when vision contradicts the IMU prediction ``pred``
    (``BridgeConfig.imu_check``), else None.

    The IMU prediction over a keyframe interval is good to a few pixels wherever the
    readings are: on clean real MH_01 stereo, MH_05 mono and V1_01 features it re-projects
    at least 80 / 44 / 50 % of the observations within ``outlier_px`` at 99 % of the
    keyframes. An accelerometer offset of 6 m/s^2 for 0.5 s on a constant-velocity stereo
    render re-projects 0-6 % while PnP explains 63-100 % at 0.1-0.7 m from the prediction;
    with the IMU factor kept, its preintegrated motion outweighs the Huber-weighted
    vision, the observations fail the outlier check and the run ends 0.98 m off with no
    warning. ``shift``: the body's motion from the keyframe's time to the images' exposure
    (the td estimate not yet in the keyframe's time): PnP poses the camera at the exposure,
    and at 1.5 m/s 25 ms of td are 3.75 cm."""
    found = _pnp_contradicts(est, features, pred, shift, est.check_points)
    if found is None:
        return None
    est.check_fired_t = features.t_ns
    _report(est, est.k, est.k + 1, "the IMU prediction " + _EVIDENCE, *found[1])
    return found[0]


def frame_state(est, features: FeatureFrame | None, pred: gtsam.NavState,
                shift: gtsam.Pose3 | None = None) -> gtsam.NavState:
    """The output state of a frame between keyframes: its IMU prediction ``pred``, or where
    vision contradicts it as :func:`imu_contradicted` decides at keyframes, the PnP pose
    on the window's landmarks (``pred``'s velocity kept); counted in
    ``est.frame_contradictions``. Nothing reaches the graph: the next keyframe is checked
    on its own. Between the keyframes of an accelerometer fault (real MH_01 stereo,
    +6 m/s^2 from frame 40) the prediction drifted 44-148 mm while the keyframes stayed
    within 7 mm. ``shift``: as for :func:`imu_contradicted`."""
    found = _pnp_contradicts(est, features, pred, shift, est.frame_points) if est.cfg.bridge.frame_check else None
    if found is None:
        return pred
    est.frame_contradictions += 1
    log.info("t=%d ns: the IMU-propagated pose " + _EVIDENCE + ": the frame's output is the PnP pose",
             features.t_ns, *found[1])
    return gtsam.NavState(found[0], pred.velocity())


def exposure_shift(est, pred: gtsam.NavState, bias: gtsam.imuBias.ConstantBias, gyro: np.ndarray | None,
                   frame, features: FeatureFrame | None) -> gtsam.Pose3:
    """The body's motion (T_b(t)_b(t + d)) from a frame's time ``t`` to its images'
    exposure (:func:`shift_by`), ``d`` = the td estimate less what the frame's time holds
    (``Estimator.td_obs`` of the packet ``frame``): what :func:`imu_contradicted` and
    :func:`frame_state` move ``pred`` by."""
    if gyro is None or not est.values.exists(TD):
        return gtsam.Pose3()
    return shift_by(float(est.values.atVector(TD)[0]) - est.td_obs(frame), pred, bias, gyro, features,
                    est.cam.line_time_s)


def shift_by(d: float, pred: gtsam.NavState, bias: gtsam.imuBias.ConstantBias, gyro: np.ndarray,
             features: FeatureFrame | None, line_time_s: float) -> gtsam.Pose3:
    """The body's motion over ``d`` s plus the rolling shutter's readout (``line_time_s``
    per row) to ``features``' median row, at ``pred``'s velocity and the (bias-corrected)
    ``gyro`` rate (rad/s, body)."""
    rows = None if features is None else features.row[np.isfinite(features.row)]
    if line_time_s and rows is not None and len(rows):
        d += line_time_s * float(np.median(rows))
    if not np.isfinite(d):
        return gtsam.Pose3()
    w = np.asarray(gyro, float) - bias.gyroscope()
    return gtsam.Pose3(gtsam.Rot3.Expmap(w * d), pred.pose().rotation().unrotate(pred.velocity()) * d)


_EVIDENCE = "re-projects %.0f %% of %d window-landmark observations, PnP %d at %.3f m / %.2f deg from it"
"""What :func:`_pnp_contradicts` found, as the checks log it."""


def _pnp_contradicts(est, features: FeatureFrame | None, pred: gtsam.NavState, shift: gtsam.Pose3 | None,
                     landmarks) -> tuple | None:
    """Where vision contradicts the IMU prediction ``pred`` moved by ``shift`` to the images'
    exposure (:func:`imu_contradicted`): (``T_w_b`` by RANSAC PnP on the window's landmarks
    (``landmarks()``: ids (N,), world points (N, 3)), back at ``pred``'s time; the
    :data:`_EVIDENCE` values: the share (%) of ``features``' observations of them the
    prediction re-projects within ``outlier_px``, their count, PnP's inliers among them,
    its distance (m) and angle (deg) from the prediction); else None."""
    bc = est.cfg.bridge
    if not bc.imu_check or features is None or len(features.ids) < bc.imu_check_min_inliers:
        return None
    T_pred = pred.pose() if shift is None else pred.pose().compose(shift)
    ids, pts = landmarks()
    if len(ids) < bc.imu_check_min_inliers:
        return None
    order = np.argsort(ids)
    pos = np.minimum(np.searchsorted(ids[order], features.ids), len(ids) - 1)
    seen = ids[order[pos]] == features.ids
    n = int(seen.sum())
    if n < bc.imu_check_min_inliers:
        return None
    T_b_c = est.extrinsic()
    thresh = est.cfg.vision.outlier_px / est.cam.intrinsics[0]
    T_c_w = T_pred.compose(T_b_c).inverse()
    q = pts[order[pos[seen]]] @ T_c_w.rotation().matrix().T + T_c_w.translation()
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(q[:, :2] / q[:, 2:] - features.uv[seen], axis=1)
    frac = float(np.mean((q[:, 2] > 0) & (err <= thresh)))
    if frac > (bc.imu_check_hold_frac if _within(est, est.check_fired_t, features.t_ns) else bc.imu_check_max_frac):
        return None
    T, out = locate(ids, pts, features, T_pred, T_b_c, thresh, bc.imu_check_min_inliers)
    if T is None:
        return None
    n_in = int(np.isin(out.ids, ids).sum())
    d = float(np.linalg.norm(T.translation() - T_pred.translation()))
    rot = float(np.linalg.norm(gtsam.Rot3.Logmap(T_pred.rotation().between(T.rotation()))))
    if n_in < max(bc.imu_check_min_inliers, bc.imu_check_min_frac * n) or not contradicts(bc, d, rot):
        return None
    if shift is not None:
        T = T.compose(shift.inverse())        # back to the prediction's time
    return T, (100 * frac, n, n_in, d, float(np.degrees(rot)))
