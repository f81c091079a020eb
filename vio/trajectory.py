"""Trajectory utilities: interpolation of stamped poses, TUM files."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np

from vio.conventions import tum_row
from vio.io.types import GroundTruth


def interpolate_pose(gt: GroundTruth, t_ns: int) -> gtsam.Pose3:
    """``T_w_b`` at ``t_ns``: linear in position, slerp in rotation. ``ValueError``
    outside the trajectory's span."""
    if t_ns < gt.t_ns[0] or t_ns > gt.t_ns[-1]:
        raise ValueError(f"t={t_ns} outside the trajectory [{gt.t_ns[0]}, {gt.t_ns[-1]}]")
    p, R = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, np.array([t_ns], dtype=np.int64))
    return gtsam.Pose3(gtsam.Rot3(R[0]), p[0])


def interpolate_poses(gt_t: np.ndarray, p: np.ndarray, q_wxyz: np.ndarray,
                   t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_w_b`` at times ``t_ns`` (K,) inside the span of ``gt_t``: (p_w (K, 3), R_w_b (K, 3, 3)).

    Position linear, rotation slerp between the bracketing rows."""
    i = np.clip(np.searchsorted(gt_t, t_ns, "right") - 1, 0, len(gt_t) - 2)
    a = ((t_ns - gt_t[i]) / (gt_t[i + 1] - gt_t[i]))[:, None]
    pos = p[i] + a * (p[i + 1] - p[i])
    q0, q1 = q_wxyz[i], q_wxyz[i + 1]
    d = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(d < 0, -q1, q1)
    th = np.arccos(np.clip(np.abs(d), -1.0, 1.0))
    s = np.sin(th)
    small = s < 1e-12
    s = np.where(small, 1.0, s)
    w0 = np.where(small, 1 - a, np.sin((1 - a) * th) / s)
    w1 = np.where(small, a, np.sin(a * th) / s)
    q = w0 * q0 + w1 * q1
    return pos, quat_to_rot(q / np.linalg.norm(q, axis=1, keepdims=True))


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (K, 4) wxyz -> rotation matrices (K, 3, 3)."""
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def interpolate_vector(t_src: np.ndarray, values: np.ndarray, t_ns: int) -> np.ndarray:
    """Linear interpolation of (N, k) ``values`` at ``t_ns``."""
    tf = (t_src - t_src[0]).astype(np.float64)
    x = float(t_ns - t_src[0])
    return np.array([np.interp(x, tf, values[:, k]) for k in range(values.shape[1])])


def write_tum(path: str | Path, stamps_ns: list[int] | np.ndarray, poses: list[gtsam.Pose3]) -> None:
    """Write ``t[s] tx ty tz qx qy qz qw`` lines."""
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(stamps_ns, poses):
            f.write(tum_row(int(t), T) + "\n")


def gyro_time_offset_ns(gt: GroundTruth, imu_t_ns: np.ndarray, gyro: np.ndarray,
                        search_ms: float = 20.0, step_ms: float = 0.25) -> int:
    """Clock offset of a ground truth w.r.t. the IMU, from angular velocity (ns).

    Returns ``o`` such that the GT sample stamped ``t`` was taken at IMU time
    ``t + o``: the body angular velocity differentiated from the GT quaternions
    is compared with the gyro (mean removed, absorbing the bias) over a grid of
    shifts, and the best shift is refined with a parabola. EuRoC's ground truth
    is off by about -2 ms on V1_02, V2_01 and MH_04 and +2.5 ms on V1_03.
    """
    q = gt.q_wxyz
    dt = np.diff(gt.t_ns) * 1e-9
    qc = q[:-1] * np.array([1.0, -1.0, -1.0, -1.0])
    w0, v0 = qc[:, :1], qc[:, 1:]
    w1, v1 = q[1:, :1], q[1:, 1:]
    rel_w = w0 * w1 - np.sum(v0 * v1, axis=1, keepdims=True)
    rel_v = w0 * v1 + w1 * v0 + np.cross(v0, v1)
    rel_v *= np.sign(rel_w + 1e-300)
    omega = 2.0 * rel_v / dt[:, None]
    t_mid = gt.t_ns[:-1] + (np.diff(gt.t_ns) // 2)
    keep = (dt > 0) & (dt < 0.05) & (t_mid > imu_t_ns[0] + 1e8) & (t_mid < imu_t_ns[-1] - 1e8)
    t_mid, omega = t_mid[keep], omega[keep]
    if t_mid.size < 100:
        raise ValueError("too little overlap between ground truth and IMU to align clocks")
    sel = np.linspace(0, t_mid.size - 1, min(t_mid.size, 20000)).astype(int)
    t_mid, omega = t_mid[sel], omega[sel]
    tf = (imu_t_ns - imu_t_ns[0]).astype(np.float64)
    shifts = np.arange(-search_ms, search_ms + 1e-9, step_ms)
    cost = []
    for s in shifts:
        x = (t_mid - imu_t_ns[0]).astype(np.float64) + s * 1e6
        g = np.stack([np.interp(x, tf, gyro[:, k]) for k in range(3)], axis=1)
        e = g - omega
        e -= e.mean(0)
        cost.append(float((e ** 2).mean()))
    i = int(np.argmin(cost))
    best = shifts[i]
    if 0 < i < len(cost) - 1:
        c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best += 0.5 * (c0 - c2) / den * step_ms
    return int(round(best * 1e6))
