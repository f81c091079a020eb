"""Predicted image velocities of a landmark's observations, for the td term
(``VisionConfig.td_velocity = "predicted"``; called per track by
``vio.backend.track_arrays.track_rows``).

The velocities are predicted from the state (keyframe velocity, bias-corrected gyro,
landmark depth; ``vio.backend.motion.motion_table``) instead of measured: independent of
the pixel noise of the observations the factor compares, so the td estimate is not biased
towards zero by noise (see ``VisionConfig.td_velocity``). The angular rate is the mean
gyro over [t_k, t_k + td] (``vio.imu.KeyframeRates``). The cam1 prediction also keeps
the static stereo pair (cam0 and cam1 at one instant) free of td: both of its
observations then shift consistently with td, as they must, whereas noisy measured
velocities turn every pair into a pull of td towards zero. Where a prediction is further
than the gate from the measurement (a wrong depth, or a mistracked observation), the
observation gets no td term.

One compiled pass per landmark: the point from the anchor ray and inverse depth, its
depth in each observing camera (cam0 and, with stereo, cam1), the image velocity of a
static point seen by the moving camera (``vio.backend.graph.image_velocity``), and the
gate against the measured velocity. Replaces ~25 small numpy calls per landmark; the
arithmetic is the same, so the results equal the numpy formulation to rounding.
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.jit import njit as _njit


def rig_c1(T_c0_c1: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
    """``(R_c1_c0 (3, 3), t_c0_c1 (3,))`` of the rig, as
    ``vio.backend.track_arrays.track_rows`` takes it (writable arrays: one Numba signature)."""
    return np.ascontiguousarray(T_c0_c1.rotation().matrix().T), np.array(T_c0_c1.translation())


@_njit
def _velocity(u: float, v: float, z: float, w: np.ndarray, vel: np.ndarray, out: np.ndarray) -> None:
    """Image velocity (2,) of a static point at normalized ``(u, v)``, depth ``z`` (m), seen
    by a camera with angular ``w`` (3,) and linear ``vel`` (3,) velocity (camera frame)."""
    out[0] = (-vel[0] + u * vel[2]) / z + u * v * w[0] - (1 + u * u) * w[1] + v * w[2]
    out[1] = (-vel[1] + v * vel[2]) / z + (1 + v * v) * w[0] - u * v * w[1] - u * w[2]


@_njit
def _gate(p: np.ndarray, meas: np.ndarray, gate: float, out: np.ndarray) -> None:
    dx, dy = p[0] - meas[0], p[1] - meas[1]
    if np.sqrt(dx * dx + dy * dy) < gate:
        out[0], out[1] = p[0], p[1]
    else:
        out[0], out[1] = 0.0, 0.0


@_njit
def predicted_velocities(idx: np.ndarray, uv: np.ndarray, meas: np.ndarray, has_r: np.ndarray,
                         ruv: np.ndarray, rmeas: np.ndarray, R: np.ndarray, t: np.ndarray,
                         w: np.ndarray, v: np.ndarray, lam: float, R10: np.ndarray,
                         t01: np.ndarray, min_depth: float, gate: float, vel: np.ndarray,
                         rvel: np.ndarray) -> None:
    """Fill ``vel`` (n, 2) and ``rvel`` (n, 2) (zeros where no prediction passes).

    Observation o is made in window row ``idx[o]`` (``idx[0]``: the anchor, whose cam0
    ray ``uv[0]`` at inverse depth ``lam`` gives the point); ``R`` (K, 3, 3) / ``t``
    (K, 3): ``R_w_c`` / ``t_w_c`` of cam0; ``w`` / ``v`` (K, 3): cam0 angular / linear
    velocity in cam0; ``meas`` (n, 2) the measured cam0 velocities; cam1 where ``has_r``:
    ``ruv``, ``rmeas`` (n, 2), ``R10`` = ``R_c1_c0`` (3, 3), ``t01`` = ``t_c0_c1`` (3,).
    A prediction counts where the depth exceeds ``min_depth`` and it is within ``gate``
    (1/s) of the measurement."""
    i0 = idx[0]
    a = np.array([uv[0, 0] / lam, uv[0, 1] / lam, 1.0 / lam])
    pw = np.empty(3)
    for r in range(3):
        pw[r] = R[i0, r, 0] * a[0] + R[i0, r, 1] * a[1] + R[i0, r, 2] * a[2] + t[i0, r]
    pc, p, wc, vc, w1, v1 = (np.empty(3), np.empty(2), np.empty(3), np.empty(3), np.empty(3),
                             np.empty(3))
    for o in range(uv.shape[0]):
        f = idx[o]
        for c in range(3):
            pc[c] = (R[f, 0, c] * (pw[0] - t[f, 0]) + R[f, 1, c] * (pw[1] - t[f, 1])
                     + R[f, 2, c] * (pw[2] - t[f, 2]))
        if pc[2] > min_depth:
            _velocity(uv[o, 0], uv[o, 1], pc[2], w[f], v[f], p)
            _gate(p, meas[o], gate, vel[o])
        else:
            vel[o, 0], vel[o, 1] = 0.0, 0.0
        rvel[o, 0], rvel[o, 1] = 0.0, 0.0
        if not has_r[o]:
            continue
        z1 = 0.0
        for c in range(3):
            z1 += (pc[c] - t01[c]) * R10[2, c]
        if not z1 > min_depth:
            continue
        wc[:] = w[f]
        vc[0] = v[f, 0] + (wc[1] * t01[2] - wc[2] * t01[1])
        vc[1] = v[f, 1] + (wc[2] * t01[0] - wc[0] * t01[2])
        vc[2] = v[f, 2] + (wc[0] * t01[1] - wc[1] * t01[0])
        for r in range(3):
            w1[r] = R10[r, 0] * wc[0] + R10[r, 1] * wc[1] + R10[r, 2] * wc[2]
            v1[r] = R10[r, 0] * vc[0] + R10[r, 1] * vc[1] + R10[r, 2] * vc[2]
        _velocity(ruv[o, 0], ruv[o, 1], z1, w1, v1, p)
        _gate(p, rmeas[o], gate, rvel[o])


@_njit
def point_velocities(idx: np.ndarray, R: np.ndarray, t: np.ndarray, w: np.ndarray, v: np.ndarray,
                     p_w: np.ndarray, meas: np.ndarray, min_depth: float, gate: float, vmax: float,
                     out: np.ndarray) -> None:
    """Fill ``out`` (n, 2) with the predicted image velocities of the world point ``p_w``
    (3,) in the cam0 of window rows ``idx`` (n,) (``R``, ``t``, ``w``, ``v`` as in
    :func:`predicted_velocities`): ``dp_c/dt = -w x p_c - v``, the projection's derivative;
    zero where the point is closer than ``min_depth`` or the prediction is further than
    ``gate`` from the measured (capped) velocity ``meas`` (n, 2), or faster than ``vmax``.
    ``vio.backend.point_tracks.PointTracks._velocities``' numpy arithmetic, compiled."""
    pc, dp = np.empty(3), np.empty(3)
    for o in range(idx.shape[0]):
        f = idx[o]
        d0, d1, d2 = p_w[0] - t[f, 0], p_w[1] - t[f, 1], p_w[2] - t[f, 2]
        for b in range(3):
            pc[b] = R[f, 0, b] * d0 + R[f, 1, b] * d1 + R[f, 2, b] * d2
        dp[0] = -(w[f, 1] * pc[2] - w[f, 2] * pc[1]) - v[f, 0]
        dp[1] = -(w[f, 2] * pc[0] - w[f, 0] * pc[2]) - v[f, 1]
        dp[2] = -(w[f, 0] * pc[1] - w[f, 1] * pc[0]) - v[f, 2]
        z = pc[2]
        front = z >= min_depth
        zs = z if front else 1.0
        p0 = (dp[0] * zs - pc[0] * dp[2]) / zs ** 2
        p1 = (dp[1] * zs - pc[1] * dp[2]) / zs ** 2
        ex, ey = p0 - meas[o, 0], p1 - meas[o, 1]
        if not (front and np.sqrt(ex * ex + ey * ey) <= gate):
            p0, p1 = 0.0, 0.0
        if not np.sqrt(p0 * p0 + p1 * p1) <= vmax:
            p0, p1 = 0.0, 0.0
        out[o, 0], out[o, 1] = p0, p1


@_njit
def points_velocities(start: np.ndarray, idx: np.ndarray, R: np.ndarray, t: np.ndarray, w: np.ndarray,
                      v: np.ndarray, p_w: np.ndarray, meas: np.ndarray, min_depth: float, gate: float,
                      vmax: float, out: np.ndarray) -> None:
    """:func:`point_velocities` of each point ``p_w[i]`` (N, 3) over its observations
    ``start[i]:start[i + 1]`` (rows of ``idx``, ``meas`` and ``out``)."""
    for i in range(p_w.shape[0]):
        a, b = start[i], start[i + 1]
        point_velocities(idx[a:b], R, t, w, v, p_w[i], meas[a:b], min_depth, gate, vmax, out[a:b])
