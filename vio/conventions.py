"""The project's conventions in code: time units, quaternion order, pose layout.

* ``T_a_b``: pose of frame b in frame a (``p_a = T_a_b * p_b``).
* ``gtsam.Pose3`` tangent ``[omega, v]``, retraction ``T * Exp(xi)`` (body-frame
  perturbation, translation included). Seed derivations (VINS-Mono) perturb the
  translation in the world frame and quaternions by half angles; every Jacobian in
  ``factors/`` is re-derived for GTSAM and checked numerically.
* Timestamps: integer nanoseconds (int64) at I/O boundaries.
* Quaternions: files use EuRoC order (w, x, y, z) or TUM order (x, y, z, w); in
  memory we hold ``gtsam.Rot3``/``gtsam.Pose3`` only.
"""

from __future__ import annotations

import gtsam
import numpy as np

NS_PER_S = 1_000_000_000


def ns_to_s(t_ns: np.ndarray | int) -> np.ndarray | float:
    """Integer nanoseconds -> float seconds (array or scalar)."""
    if isinstance(t_ns, np.ndarray):
        return t_ns.astype(np.float64) / NS_PER_S
    return int(t_ns) / NS_PER_S


def s_to_ns(t_s: np.ndarray | float) -> np.ndarray | int:
    """Float seconds -> integer nanoseconds, rounded to the nearest ns."""
    if isinstance(t_s, np.ndarray):
        return np.round(t_s * NS_PER_S).astype(np.int64)
    return int(round(float(t_s) * NS_PER_S))


def rot_from_quat_wxyz(q: np.ndarray) -> gtsam.Rot3:
    """Rotation from a quaternion in (w, x, y, z) order; normalizes it."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q)
    return gtsam.Rot3.Quaternion(q[0], q[1], q[2], q[3])


def quat_wxyz_from_rot(R: gtsam.Rot3) -> np.ndarray:
    """(w, x, y, z) quaternion of a rotation, with w >= 0."""
    q = R.toQuaternion()
    out = np.array([q.w(), q.x(), q.y(), q.z()])
    return -out if out[0] < 0 else out


def pose_from_tq(t: np.ndarray, q_wxyz: np.ndarray) -> gtsam.Pose3:
    """``Pose3`` from a translation and a (w, x, y, z) quaternion."""
    return gtsam.Pose3(rot_from_quat_wxyz(q_wxyz), np.asarray(t, dtype=float))


def pose_from_matrix(T: np.ndarray) -> gtsam.Pose3:
    """``Pose3`` from a 4x4 homogeneous matrix; re-orthonormalizes the rotation."""
    T = np.asarray(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), T[:3, 3])


def tum_row(t_ns: int, T_w_b: gtsam.Pose3) -> str:
    """One TUM line: ``t[s] tx ty tz qx qy qz qw``."""
    w, x, y, z = quat_wxyz_from_rot(T_w_b.rotation())
    p = T_w_b.translation()
    return (f"{t_ns // NS_PER_S}.{t_ns % NS_PER_S:09d} "
            f"{p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}")
