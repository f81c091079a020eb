"""The motion of every window keyframe, for the predicted image velocities of the td term
(``vio.backend.td_velocity``, ``vio.backend.point_tracks``) and the photometric factors'
exposure times (``vio.direct.source``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.landmarks import cross3

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator


def body_motion(est: "Estimator", f: int, T_w_b: gtsam.Pose3, v_w: np.ndarray,
                bias: gtsam.imuBias.ConstantBias, td: float) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe f's angular velocity (rad/s: the bias-corrected mean gyro over its exposure
    offset and a rolling shutter's readout, ``vio.imu.KeyframeRates``; ``td`` the TD
    variable's value) and linear velocity
    (m/s, ``v_w`` rotated into the body), both in the body frame; zero at keyframes flagged
    still (their images carry no timing information; on the ground with motors running the
    gyro's vibration read as motion let td wander 0 -> 7.8 ms on MH_04 before take-off)."""
    if f in est.still_kf:
        return np.zeros(3), np.zeros(3)
    w_b = (est.rates.rate(f, td, est.cam.readout_s) if f in est.rates else np.zeros(3)) - bias.gyroscope()
    return w_b, T_w_b.rotation().unrotate(v_w)


def motion_table(est: "Estimator", k: int, pred: gtsam.NavState,
                 pose: Callable[[int], gtsam.Pose3]) -> tuple:
    """Per window keyframe f (``est.kf_t``; k is the new one, at the prediction ``pred``):
    ``R_w_c`` (K, 3, 3), ``t_w_c`` (K, 3), and the camera's angular / linear velocity in
    the camera frame (K, 3) from the body's (``body_motion``: zero at keyframes flagged
    still); ``pos`` maps f to its row. ``pose(f)``: ``T_w_b`` of f.
    Returns (pos, R, t, w, v)."""
    vals = est.values
    T_b_c = vals.atPose3(graph.EXTRINSIC)
    R_c_b = T_b_c.rotation().matrix().T
    p_c = T_b_c.translation()
    frames = sorted(est.kf_t)
    td = float(vals.atVector(graph.TD)[0])
    R, t, w, v = [], [], [], []
    for f in frames:
        T_w_b = pose(f)
        v_w = pred.velocity() if f == k else vals.atVector(graph.V(f))
        b = vals.atConstantBias(graph.B(k - 1 if f == k else f))
        w_b, v_b = body_motion(est, f, T_w_b, v_w, b, td)
        v_b = v_b + cross3(w_b, p_c)
        T_w_c = T_w_b.compose(T_b_c)
        R.append(T_w_c.rotation().matrix()), t.append(T_w_c.translation())
        w.append(R_c_b @ w_b), v.append(R_c_b @ v_b)
    return ({f: i for i, f in enumerate(frames)}, np.array(R), np.array(t), np.array(w), np.array(v))
