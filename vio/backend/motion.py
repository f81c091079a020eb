"""The camera motion of every window keyframe, for the predicted image velocities of the
td term (``vio.backend.td_velocity``, ``vio.backend.point_tracks``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.landmarks import cross3

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator


def motion_table(est: "Estimator", k: int, pred: gtsam.NavState,
                 pose: Callable[[int], gtsam.Pose3]) -> tuple:
    """Per window keyframe f (``est.kf_t``; k is the new one, at the prediction ``pred``):
    ``R_w_c`` (K, 3, 3), ``t_w_c`` (K, 3), and the camera's angular / linear velocity in
    the camera frame (K, 3) from the bias-corrected gyro and the estimated velocity, zero
    at keyframes flagged still (their images carry no timing information; on the ground
    with motors running the gyro's vibration read as motion let td wander 0 -> 7.8 ms on
    MH_04 before take-off); ``pos`` maps f to its row. ``pose(f)``: ``T_w_b`` of f.
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
        w_b = (est.rates.rate(f, td) if f in est.rates else np.zeros(3)) - b.gyroscope()
        v_b = T_w_b.rotation().unrotate(v_w) + cross3(w_b, p_c)
        if f in est.still_kf:
            w_b, v_b = np.zeros(3), np.zeros(3)
        T_w_c = T_w_b.compose(T_b_c)
        R.append(T_w_c.rotation().matrix()), t.append(T_w_c.translation())
        w.append(R_c_b @ w_b), v.append(R_c_b @ v_b)
    return ({f: i for i, f in enumerate(frames)}, np.array(R), np.array(t), np.array(w), np.array(v))
