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
    i = int(np.searchsorted(gt.t_ns, t_ns, side="right")) - 1
    if i < 0 or t_ns > gt.t_ns[-1]:
        raise ValueError(f"t={t_ns} outside the trajectory [{gt.t_ns[0]}, {gt.t_ns[-1]}]")
    if i == len(gt) - 1 or gt.t_ns[i] == t_ns:
        return gt.pose(i)
    s = float(t_ns - gt.t_ns[i]) / float(gt.t_ns[i + 1] - gt.t_ns[i])
    R0, R1 = gt.pose(i).rotation(), gt.pose(i + 1).rotation()
    R = R0.compose(gtsam.Rot3.Expmap(s * gtsam.Rot3.Logmap(R0.between(R1))))
    p = (1 - s) * gt.p_w[i] + s * gt.p_w[i + 1]
    return gtsam.Pose3(R, p)


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
