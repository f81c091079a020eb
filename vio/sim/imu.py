"""IMU measurements from the analytic trajectory, with EuRoC-style noise.

Model (body = IMU frame), sample k at time ``t_k``:
``gyro_k = omega_b(t_k) + bg_k + n_g``, ``accel_k = R_w_b^T (a_w - g_w) + ba_k + n_a``
with ``g_w = (0, 0, -gravity)``. White noise is discrete Gaussian with
``sigma = density * sqrt(rate)``; biases follow a random walk
``b_{k+1} = b_k + random_walk * sqrt(dt) * N(0, I)``. ``bg_k``/``ba_k`` are the
biases that ground-truth row k reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.sim.config import SimConfig
from vio.sim.trajectory import Trajectory


@dataclass(frozen=True)
class ImuSim:
    """Simulated samples at ``t_s`` (N,) seconds since start: ``gyro`` (N,3) rad/s,
    ``accel`` (N,3) m/s^2 (measured), ``bg``/``ba`` (N,3) the true biases."""

    t_s: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    bg: np.ndarray
    ba: np.ndarray


def _random_walk(rng: np.random.Generator, n: int, init: np.ndarray, step_sigma: float) -> np.ndarray:
    steps = rng.standard_normal((n, 3)) * step_sigma
    steps[0] = 0.0
    return init + np.cumsum(steps, axis=0)


def simulate_imu(traj: Trajectory, t_s: np.ndarray, cfg: SimConfig) -> ImuSim:
    """Measurements at times ``t_s`` (N,) (seconds since start, uniform at ``cfg.imu_rate_hz``).

    Uses its own random stream (``[seed, 4]``) so the result does not depend on
    what else is simulated.
    """
    rng = np.random.default_rng([cfg.seed, 4])
    t = np.asarray(t_s, float)
    n = t.size
    s = traj.sample(t)
    f_b = np.einsum("nji,nj->ni", s.R_w_b, s.a_w + np.array([0.0, 0.0, cfg.gravity]))
    bg0 = rng.standard_normal(3) * cfg.gyro_bias_init_sigma
    ba0 = rng.standard_normal(3) * cfg.accel_bias_init_sigma
    dt = 1.0 / cfg.imu_rate_hz
    on = 1.0 if cfg.imu_noise else 0.0
    bg = _random_walk(rng, n, bg0, on * cfg.gyro_random_walk * np.sqrt(dt))
    ba = _random_walk(rng, n, ba0, on * cfg.accel_random_walk * np.sqrt(dt))
    sg = on * cfg.gyro_noise_density * np.sqrt(cfg.imu_rate_hz)
    sa = on * cfg.accel_noise_density * np.sqrt(cfg.imu_rate_hz)
    gyro = s.omega_b + bg + rng.standard_normal((n, 3)) * sg
    accel = f_b + ba + rng.standard_normal((n, 3)) * sa
    return ImuSim(t, gyro, accel, bg, ba)
