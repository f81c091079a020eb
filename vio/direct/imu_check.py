"""Direct mode's check of the IMU prediction: TrackFrame again from a visual guess.

Direct mode has no landmarks for ``vio.backend.bridge.imu_contradicted``'s PnP, and its
TrackFrame (``vio.direct.source``) starts at the IMU prediction with the prediction as a
prior: wrong readings (+6 m/s^2 on the accelerometer for 1 s on real MH_01) leave it at
rmse 50-80, "failed", and the IMU factor outweighs the photometric factors (2.1-2.8 m).

So where TrackFrame fails, it runs once more without the prior from the previous keyframe
interval's camera motion scaled to this interval (a visual constant-velocity guess, as
DSO's CoarseTracker tries). Real MH_01 under that offset: the first two keyframes of the
fault converge this way (rmse 8.0 / 5.6) 8-11 cm from the IMU prediction. A converged
retry at least ``BridgeConfig.imu_check_min_m`` from the prediction and within
``imu_check_max_deg`` of its attitude contradicts the IMU: the source reports it
(``PhotometricSource.imu_contradicted``) and the estimator bridges the interval as it does
for the landmark check.

Where TrackFrame converges with the prior but still that far from the prediction, its pose
is the prior's compromise with vision, and the prior is the contradicted IMU: it runs once
more the same way, and that result, where it fits the images at least as well (level-0
rmse), is X(k)'s guess (within 3 cm of the prediction after all, the IMU is not
contradicted). On the 4-s half-resolution render of
``tests/test_direct_mode.py`` with +6 m/s^2 from 2.0 s, the prior's alignment of the
fault's first keyframe (0.25 s, 0.25 m from the prediction) stopped 6 cm from the
prediction and 0.30 m from the truth at rmse 17.2; the window kept that step to the end
(80 mm ATE). Without the prior: 2 mm from the truth at rmse 3.5, 22.6 mm ATE (the frames
before that keyframe, IMU-propagated, 20-170 mm).
"""

from __future__ import annotations

import gtsam
import numpy as np

from vio.backend.graph import X
from vio.direct.trackframe import body_pose, track_frame


def visual_guess(T_w_c0: gtsam.Pose3, T_w_c1: gtsam.Pose3, t0_ns: int, t1_ns: int, t_ns: int) -> gtsam.Pose3:
    """The camera pose at ``t_ns`` relative to the camera at ``t1_ns`` (T_c1_c) if it keeps
    the motion from ``T_w_c0`` (at ``t0_ns``) to ``T_w_c1`` (at ``t1_ns``): rotation
    vector and translation scaled by the ratio of the intervals."""
    rel = T_w_c0.between(T_w_c1)
    s = (t_ns - t1_ns) / max(t1_ns - t0_ns, 1)
    return gtsam.Pose3(gtsam.Rot3.Expmap(gtsam.Rot3.Logmap(rel.rotation()) * s), rel.translation() * s)


def free_alignment(cfg, kfs: dict, vals: gtsam.Values, prev, kd, T_w_cp: gtsam.Pose3,
                   T_b_c: gtsam.Pose3, ab: np.ndarray, ref=None, shutter=None) -> tuple | None:
    """TrackFrame of the keyframe ``kd`` against ``prev`` (its camera at ``T_w_cp``, affine
    ``ab``; ``ref`` its TrackFrame reference, default its own points; ``shutter`` their
    rolling shutter) without the IMU prior, from :func:`window_guess` (``cfg``:
    ``DirectConfig``): (its converged result, the body pose T_w_b), or None (no guess, a
    numerical failure, no convergence)."""
    guess = window_guess(kfs, vals, prev, T_w_cp, T_b_c, kd.t_ns)
    if guess is None:
        return None
    ref = prev.reference(ab, cfg) if ref is None else ref
    try:
        res = track_frame(ref, kd.pyramid(cfg.track.levels), guess, ab, cfg.track, None, shutter)
    except (ArithmeticError, np.linalg.LinAlgError):
        return None
    return (res, body_pose(T_w_cp, res.T_kf_new, T_b_c)) if res.ok else None


def pose_offset(T_pred: gtsam.Pose3, T: gtsam.Pose3) -> tuple[float, float]:
    """Distance (m) and angle (rad) of ``T`` from ``T_pred``."""
    d = T_pred.between(T)
    return float(np.linalg.norm(d.translation())), float(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation())))


def window_guess(kfs: dict, vals: gtsam.Values, prev, T_w_cp: gtsam.Pose3, T_b_c: gtsam.Pose3,
                 t_ns: int) -> gtsam.Pose3 | None:
    """:func:`visual_guess` of the keyframe at ``t_ns`` relative to ``prev`` (its camera at
    ``T_w_cp``) from the keyframe of ``kfs`` (index -> ``KeyframeData``) before ``prev`` in
    ``vals``; None without one."""
    before = [f for f, fd in kfs.items() if f < prev.k and fd.in_graph and vals.exists(X(f))]
    if not before:
        return None
    pp = kfs[max(before)]
    return visual_guess(vals.atPose3(X(pp.k)).compose(T_b_c), T_w_cp, pp.t_ns, prev.t_ns, t_ns)

