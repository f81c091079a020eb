"""Divergence monitor of the estimator, and the IMU-gap bridge parameters.

After every keyframe update the estimator asks :class:`HealthMonitor` whether the new
state is plausible. A state is divergent when

- its speed exceeds ``max_speed`` (m/s);
- a bias has left its prior: ``|b - b0| > bias_k * sqrt(prior^2 + walk^2 * (t - t0))``
  per axis, with ``b0`` the bias at the (re)start ``t0``, ``prior`` the initial bias
  sigma and ``walk`` the random walk the smoother itself assumes (so the allowance
  grows as the bias may legitimately wander);
- the feature inlier ratio (landmarks kept / landmarks before the outlier check)
  stays below ``min_inlier_ratio`` for ``inlier_keyframes`` keyframes in a row, with at
  least ``min_landmarks`` landmarks;
- the newest IMU factor's whitened squared error exceeds ``max_imu_chi2`` (15 degrees
  of freedom: the IMU and the rest of the window disagree wildly).

The estimator then restarts the smoother softly (``Estimator._restart``, as after a
solver failure): same world frame, the current pose held by a tight prior (no jump
in the output), velocity and bias from the last healthy keyframe at least
``lookback_s`` old, velocity with ``restart_vel_sigma``. No check runs for
``cooldown_keyframes`` keyframes after a (re)start.

On the clean real data (V1_01 features, MH_05 mono, MH_01 stereo) the largest values
seen are far inside these limits (see ``benchmarks/bench_faults.py``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np


@dataclass(frozen=True)
class HealthConfig:
    """Divergence limits and the soft restart (see the module docstring)."""

    enabled: bool = True
    max_speed: float = 30.0
    bias_k: float = 10.0
    min_inlier_ratio: float = 0.3
    inlier_keyframes: int = 3
    min_landmarks: int = 10
    max_imu_chi2: float = 1e4
    cooldown_keyframes: int = 10
    lookback_s: float = 0.5
    restart_vel_sigma: float = 0.5


@dataclass(frozen=True)
class BridgeConfig:
    """The motion prior standing in for the IMU factor across an IMU gap: constant
    velocity and attitude, driven by white acceleration of ``accel_density``
    (m/s^2/sqrt(Hz)) and white rotation rate of ``gyro_density`` (rad/s/sqrt(Hz)), so its
    sigmas grow with the gap (position ~ accel_density * T^1.5 / sqrt(3)); integrated in
    steps of ``step_s``. The biases keep their random walk across it."""

    accel_density: float = 1.0
    gyro_density: float = 0.5
    step_s: float = 0.005


@dataclass(frozen=True)
class _Healthy:
    t_ns: int
    v_w: np.ndarray
    bias: gtsam.imuBias.ConstantBias


class HealthMonitor:
    """Checks keyframe states against :class:`HealthConfig`. ``bias_prior`` (6,):
    initial sigmas [accel m/s^2, gyro rad/s]; ``bias_walk`` (6,): their random walks per
    sqrt(s) (as the smoother models them)."""

    def __init__(self, cfg: HealthConfig, bias_prior: np.ndarray, bias_walk: np.ndarray) -> None:
        self.cfg = cfg
        self.bias_prior = np.asarray(bias_prior, float)
        self.bias_walk = np.asarray(bias_walk, float)
        self._b0 = np.zeros(6)
        self._t0 = 0
        self._quiet = 0
        self._low_inliers = 0
        self._good: deque[_Healthy] = deque()

    def reset(self, t_ns: int, bias: gtsam.imuBias.ConstantBias) -> None:
        """A (re)start at ``t_ns`` with ``bias``: the bias test's reference."""
        self._b0, self._t0 = bias.vector().copy(), t_ns
        self._quiet = self.cfg.cooldown_keyframes
        self._low_inliers = 0
        self._good.clear()

    def check(self, t_ns: int, v_w: np.ndarray, bias: gtsam.imuBias.ConstantBias,
              n_landmarks: int, n_removed: int, imu_chi2: float) -> str | None:
        """The reason the state at ``t_ns`` is divergent, or None (then it is recorded
        as healthy)."""
        c = self.cfg
        if not c.enabled:
            return None
        reason = self._reason(t_ns, np.asarray(v_w, float), bias.vector(), n_landmarks, n_removed,
                              imu_chi2)
        if self._quiet > 0:
            self._quiet -= 1
            reason = None if reason is None or not reason.startswith("non-finite") else reason
        if reason is None:
            self._good.append(_Healthy(t_ns, np.asarray(v_w, float).copy(), bias))
            while len(self._good) > 1 and (t_ns - self._good[1].t_ns) * 1e-9 >= c.lookback_s:
                self._good.popleft()
        return reason

    def _reason(self, t_ns: int, v: np.ndarray, b: np.ndarray, n_lm: int, n_rm: int,
                chi2: float) -> str | None:
        c = self.cfg
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(b)) and np.isfinite(chi2)):
            return "non-finite state"
        speed = float(np.linalg.norm(v))
        if speed > c.max_speed:
            return f"speed {speed:.1f} m/s > {c.max_speed:g}"
        sig = np.sqrt(self.bias_prior ** 2 + self.bias_walk ** 2 * max(t_ns - self._t0, 0) * 1e-9)
        z = np.abs(b - self._b0) / sig
        if z.max() > c.bias_k:
            i = int(np.argmax(z))
            return (f"{'accelerometer' if i < 3 else 'gyro'} bias {b[i]:.3f} is {z[i]:.0f} sigmas "
                    f"from its prior")
        total = n_lm + n_rm
        ratio = n_lm / total if total else 1.0
        self._low_inliers = self._low_inliers + 1 if total >= c.min_landmarks and ratio < c.min_inlier_ratio else 0
        if self._low_inliers >= c.inlier_keyframes:
            return f"feature inlier ratio {ratio:.2f} < {c.min_inlier_ratio:g} for {self._low_inliers} keyframes"
        if chi2 > c.max_imu_chi2:
            return f"IMU factor error {chi2:.3g} > {c.max_imu_chi2:g}"
        return None

    def fallback(self) -> tuple[np.ndarray, gtsam.imuBias.ConstantBias] | None:
        """Velocity and bias of the last healthy keyframe at least ``lookback_s`` old
        (else the oldest healthy one); None when none is known."""
        return (self._good[0].v_w, self._good[0].bias) if self._good else None
