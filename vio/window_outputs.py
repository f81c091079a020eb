"""The initialization window's outputs at the estimate its replay ends with.

An initialization (dynamic, stereo) is decided at the end of a buffered window, then the
window's frames are replayed through the estimator and all of them are output at once
(``vio.start.Start._replay``). Replayed frame by frame, the first ones would carry the estimate of
a window that had barely begun (the first keyframe alone, then two, ...), although no
output leaves before the replay's end: real MH_01 mono had 18-19 mm of error at 0.5-1.5 s
against 5-10 mm afterwards. Each window frame therefore gets the state the smoother holds
once the whole window is in: a keyframe its own ``X, V, B``; a frame between keyframes the
preceding keyframe's state propagated with the frame packets' IMU, as the online output of
a frame after initialization is (``Estimator.predict``). Frames: ``T_w_b`` body in world,
``v_w`` m/s in world.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Sequence

import gtsam
import numpy as np

from vio.backend.graph import B, V, X
from vio.imu import integrate

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator


def window_estimates(est: "Estimator", outs: Sequence, packets: Sequence) -> list:
    """``outs`` (``FrameOutput``, one per packet of ``packets``, the replayed window in time
    order) with ``T_w_b``, ``v_w`` and ``bias`` from ``est``'s current estimate. Left as they
    are: frames before the first keyframe still in the window, and every frame when the
    window holds an IMU gap (its bridge does not propagate the IMU)."""
    if any(p.imu_gaps for p in packets):
        return list(outs)
    kf = {t: k for k, t in est.kf_t.items()}
    vals = est.values
    res, start, pim = [], None, None
    for out, pkt in zip(outs, packets):
        k = kf.get(out.t_ns)
        if k is not None and vals.exists(X(k)) and vals.exists(V(k)) and vals.exists(B(k)):
            T, v, b = vals.atPose3(X(k)), np.asarray(vals.atVector(V(k)), float), vals.atConstantBias(B(k))
            start, pim = (gtsam.NavState(T, v), b), gtsam.PreintegratedCombinedMeasurements(est.params, b)
            res.append(dataclasses.replace(out, T_w_b=T, v_w=v, bias=b))
            continue
        if pim is None:
            res.append(out)
            continue
        integrate(pim, pkt.imu)
        nav = pim.predict(*start)
        res.append(dataclasses.replace(out, T_w_b=nav.pose(), v_w=np.asarray(nav.velocity(), float), bias=start[1]))
    return res
