"""Static initialization: stillness detection and gravity / gyro-bias alignment.

At rest the accelerometer measures ``f_b = R_w_b^T [0, 0, g]`` (specific force
opposing gravity), so its mean fixes roll and pitch; yaw is unobservable and set
to zero. The gyro mean over the still window is the gyro bias (V1_01: about
0.077 rad/s about z). The accelerometer bias cannot be separated from gravity
at rest and starts at zero with a loose prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.backend.config import InitConfig
from vio.io.types import ImuData


@dataclass(frozen=True)
class InitialState:
    """The first keyframe's state: ``T_w_b`` (yaw 0, gravity along -z of the world),
    ``v_w`` m/s, IMU bias, and how it was found. ``rp_sigma`` (rad) / ``vel_sigma``
    (m/s): the initializer's own roll-pitch / velocity prior sigmas (None: the
    ``InitConfig`` defaults); ``td_s``: the camera-IMU offset beyond the sync layer's that
    the initializer found (s; None: none, the estimator's own prior mean); ``scale_sigma``:
    the relative standard deviation of the window's metric scale (a dynamic
    initialization's batch, ``vio.backend.dynamic_init.scale_sigma``; None otherwise)."""

    t_ns: int
    T_w_b: gtsam.Pose3
    v_w: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    method: str
    rp_sigma: float | None = None
    vel_sigma: float | None = None
    td_s: float | None = None
    scale_sigma: float | None = None


@dataclass(frozen=True)
class Stillness:
    """IMU statistics over a window (rad/s, m/s^2) and the verdict."""

    gyro_std: float
    accel_std: float
    still: bool


def imu_stillness(imu: ImuData, cfg: InitConfig, block: int = 10) -> Stillness:
    """Still when the ``block``-sample means (50 ms at 200 Hz) of gyro and accel stay
    within ``max_gyro_std`` / ``max_accel_std`` of their window mean. Block means
    suppress rotor vibration (V1_01 at rest: ~0.3 m/s^2 raw jitter) that does not
    move the platform."""
    n = len(imu) // block * block
    if n < 2 * block:
        return Stillness(np.inf, np.inf, False)
    g = imu.gyro[:n].reshape(-1, block, 3).mean(1)
    a = imu.accel[:n].reshape(-1, block, 3).mean(1)
    gdev = float(np.linalg.norm(g - g.mean(0), axis=1).max())
    adev = float(np.linalg.norm(a - a.mean(0), axis=1).max())
    return Stillness(gdev, adev, gdev < cfg.max_gyro_std and adev < cfg.max_accel_std)


def gravity_aligned_rotation(f_b: np.ndarray) -> gtsam.Rot3:
    """``R_w_b`` with zero yaw that maps the measured specific force onto +z."""
    f = np.asarray(f_b, float) / np.linalg.norm(f_b)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(f, z)
    s, c = np.linalg.norm(axis), float(f @ z)
    if s < 1e-12:
        R = gtsam.Rot3() if c > 0 else gtsam.Rot3.Rx(np.pi)
    else:
        R = gtsam.Rot3.Expmap(axis / s * np.arctan2(s, c))
    M = R.matrix()
    yaw = np.arctan2(M[1, 0], M[0, 0])
    return gtsam.Rot3.Rz(-yaw).compose(R)


def static_init(imu: ImuData, t_ns: int) -> InitialState:
    """Initial state from a still IMU window ending at ``t_ns``."""
    f = imu.accel.mean(0)
    R = gravity_aligned_rotation(f)
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), imu.gyro.mean(0))
    return InitialState(int(t_ns), gtsam.Pose3(R, np.zeros(3)), np.zeros(3), bias, "static")
