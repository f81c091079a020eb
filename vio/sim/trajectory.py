"""Smooth analytic 6-DoF body (IMU) trajectory with exact derivatives.

Position (``SimConfig.motion == "loop"``, the default): a perturbed elliptic loop around the room centre,
``p(t) = c + [rx cos(alpha), ry sin(alpha), 0] + sum_k A_k sin(w_k t + phi_k)``,
``alpha = alpha0 + Omega t``. Orientation: ``R_w_b = Rz(psi) Ry(theta) Rx(phi) R0``
where ``R0`` makes the body z axis (the optical axis of the EuRoC cameras) horizontal
along world x and body x point up (as on the EuRoC MAV); ``psi`` follows the loop
angle plus sinusoidal sweeps, ``theta``/``phi`` are small sinusoids (pitch/roll).

Times ``t`` are float seconds relative to the sequence start (``SimConfig.t0_ns``).
Body angular velocity: for ``R = R1 R2 R3 R0`` with ``R_i^T dR_i = [w_i]x``,
``omega_b = R0^T (R3^T R2^T w1 + R3^T w2 + w3)``.

``motion == "constant_velocity"``: zero radii, a linear term along x and centimetre
wiggles (see :func:`_constant_velocity`); the orientation model is the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.sim.config import SimConfig

# body axes expressed in the world at zero yaw/pitch/roll: x up, z forward (+x_w)
R0 = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class Sines:
    """``f(t) = c0 + c1 t + sum_k amp_k sin(omega_k t + phase_k)`` with derivatives."""

    c0: float
    c1: float
    amp: np.ndarray
    omega: np.ndarray
    phase: np.ndarray

    def eval(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """The ``order``-th derivative (0, 1 or 2) at times ``t`` (N,) -> (N,)."""
        arg = np.outer(t, self.omega) + self.phase
        if order == 0:
            return self.c0 + self.c1 * t + np.sin(arg) @ self.amp
        if order == 1:
            return self.c1 + np.cos(arg) @ (self.amp * self.omega)
        return -np.sin(arg) @ (self.amp * self.omega ** 2)


@dataclass(frozen=True)
class TrajectorySample:
    """States at N times: ``R_w_b`` (N,3,3), ``p_w`` (N,3) m, ``v_w`` (N,3) m/s,
    ``a_w`` (N,3) m/s^2 (kinematic acceleration), ``omega_b`` (N,3) rad/s (body frame)."""

    R_w_b: np.ndarray
    p_w: np.ndarray
    v_w: np.ndarray
    a_w: np.ndarray
    omega_b: np.ndarray


def _rz(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rx(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


@dataclass(frozen=True)
class Trajectory:
    """Loop centre ``center`` (3,), radii ``rx, ry``; ``alpha`` loop angle; ``pos`` the
    per-axis perturbations (3 ``Sines``, centre included in ``c0``); ``yaw_extra``,
    ``pitch``, ``roll`` angle functions (rad)."""

    center: np.ndarray
    rx: float
    ry: float
    alpha: Sines
    pos: tuple[Sines, Sines, Sines]
    yaw_extra: Sines
    pitch: Sines
    roll: Sines

    def sample(self, t_s: np.ndarray | float) -> TrajectorySample:
        """Evaluate every state at times ``t_s`` (seconds since start), vectorized."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        al, dal, ddal = (self.alpha.eval(t, k) for k in range(3))
        ca, sa = np.cos(al), np.sin(al)
        loop = [np.stack([self.rx * ca, self.ry * sa, 0 * t], -1),
                np.stack([-self.rx * sa * dal, self.ry * ca * dal, 0 * t], -1),
                np.stack([-self.rx * (ca * dal ** 2 + sa * ddal),
                          self.ry * (-sa * dal ** 2 + ca * ddal), 0 * t], -1)]
        p, v, a = (loop[k] + np.stack([s.eval(t, k) for s in self.pos], -1) for k in range(3))
        psi = al + self.yaw_extra.eval(t)
        dpsi = dal + self.yaw_extra.eval(t, 1)
        th, dth = self.pitch.eval(t), self.pitch.eval(t, 1)
        ph, dph = self.roll.eval(t), self.roll.eval(t, 1)
        R1, R2, R3 = _rz(psi), _ry(th), _rx(ph)
        R = R1 @ R2 @ R3 @ R0
        zeros = np.zeros_like(t)
        w1 = np.stack([zeros, zeros, dpsi], -1)
        w2 = np.stack([zeros, dth, zeros], -1)
        w3 = np.stack([dph, zeros, zeros], -1)
        R3t, R2t = np.swapaxes(R3, 1, 2), np.swapaxes(R2, 1, 2)
        w = np.einsum("nij,nj->ni", R3t, np.einsum("nij,nj->ni", R2t, w1) + w2) + w3
        omega_b = w @ R0  # R0^T w for each row
        return TrajectorySample(R, p, v, a, omega_b)

    def pose_at(self, t_s: float) -> gtsam.Pose3:
        """``T_w_b`` at time ``t_s`` (seconds since start)."""
        s = self.sample(t_s)
        return gtsam.Pose3(gtsam.Rot3(s.R_w_b[0]), s.p_w[0])

    def velocity(self, t_s: float) -> np.ndarray:
        """World-frame velocity (3,) m/s."""
        return self.sample(t_s).v_w[0]

    def angular_velocity(self, t_s: float) -> np.ndarray:
        """Body-frame angular velocity (3,) rad/s."""
        return self.sample(t_s).omega_b[0]

    def specific_force(self, t_s: np.ndarray, gravity: float) -> np.ndarray:
        """Accelerometer truth ``R_w_b^T (a_w - g_w)``, ``g_w = (0, 0, -gravity)``, (N,3)."""
        s = self.sample(t_s)
        f_w = s.a_w + np.array([0.0, 0.0, gravity])
        return np.einsum("nji,nj->ni", s.R_w_b, f_w)


def _sines(rng: np.random.Generator, n: int, amp: float, f_lo: float, f_hi: float,
           c0: float = 0.0, c1: float = 0.0) -> Sines:
    """``n`` random sinusoids with total amplitude ``amp`` and frequencies in Hz."""
    w = rng.dirichlet(np.ones(n)) * amp if n else np.zeros(0)
    return Sines(c0, c1, w, 2 * np.pi * rng.uniform(f_lo, f_hi, n), rng.uniform(0, 2 * np.pi, n))


def _constant_velocity(cfg: SimConfig, rng: np.random.Generator) -> Trajectory:
    """A straight pass along world x at ``speed_mps`` from ``wall_margin_m``, half-way
    across y, looking at the y = Ly wall (yaw 90 deg) with the loop's yaw sweeps and
    pitch/roll. Position wiggles of 1-1.5 cm at 0.1-0.2 Hz: the kinematic acceleration
    stays within ~0.03 m/s^2, too little for an IMU-only scale (``DynamicInitConfig.
    min_excitation``)."""
    _, Ly, Lz = cfg.room_size
    z_mid = min(max(0.45 * Lz, 0.6), Lz - 0.6)
    pos = (_sines(rng, 2, 0.015, 0.1, 0.2, cfg.wall_margin_m, cfg.speed_mps),
           _sines(rng, 2, 0.015, 0.1, 0.2, Ly / 2),
           _sines(rng, 2, 0.01, 0.1, 0.2, z_mid))
    alpha = Sines(np.pi / 2, 0.0, np.zeros(0), np.zeros(0), np.zeros(0))
    f_yaw = 0.2
    yaw_amp = np.deg2rad(cfg.yaw_sweep_dps) / (2 * np.pi * f_yaw)
    yaw_extra = _sines(rng, 2, yaw_amp, 0.8 * f_yaw, 1.2 * f_yaw, rng.uniform(-0.3, 0.3))
    pitch = _sines(rng, 2, 0.15, 0.1, 0.4, rng.uniform(0.0, 0.2))
    roll = _sines(rng, 2, 0.1, 0.1, 0.4)
    return Trajectory(np.array([cfg.room_size[0] / 2, Ly / 2, z_mid]), 0.0, 0.0, alpha, pos,
                      yaw_extra, pitch, roll)


def make_trajectory(cfg: SimConfig) -> Trajectory:
    """The seed-determined trajectory of ``cfg`` (its own random stream): the default
    elliptic loop, or a straight pass (``cfg.motion == "constant_velocity"``)."""
    rng = np.random.default_rng([cfg.seed, 1])
    if cfg.motion == "constant_velocity":
        return _constant_velocity(cfg, rng)
    Lx, Ly, Lz = cfg.room_size
    pert = min(0.15, 0.1 * min(Lx, Ly))
    rx = max(Lx / 2 - cfg.wall_margin_m - pert, 0.2)
    ry = max(Ly / 2 - cfg.wall_margin_m - pert, 0.2)
    omega = cfg.speed_mps / (0.5 * (rx + ry)) * rng.choice([-1.0, 1.0])
    alpha = Sines(rng.uniform(0, 2 * np.pi), omega, np.zeros(0), np.zeros(0), np.zeros(0))
    z_mid = min(max(0.45 * Lz, 0.6), Lz - 0.6)
    z_amp = max(0.0, min(0.25, z_mid - 0.5, Lz - 0.5 - z_mid))
    pos = (_sines(rng, 2, pert, 0.15, 0.5, Lx / 2),
           _sines(rng, 2, pert, 0.15, 0.5, Ly / 2),
           _sines(rng, 2, z_amp, 0.1, 0.3, z_mid))
    f_yaw = 0.2
    yaw_amp = np.deg2rad(cfg.yaw_sweep_dps) / (2 * np.pi * f_yaw)
    # look outward from the loop centre, within +-35 deg, with sweeps of ~yaw_amp
    yaw_extra = _sines(rng, 2, yaw_amp, 0.8 * f_yaw, 1.2 * f_yaw,
                       rng.uniform(-0.6, 0.6))
    pitch = _sines(rng, 2, 0.15, 0.1, 0.4, rng.uniform(0.0, 0.2))
    roll = _sines(rng, 2, 0.1, 0.1, 0.4)
    return Trajectory(np.array([Lx / 2, Ly / 2, z_mid]), rx, ry, alpha, pos, yaw_extra, pitch, roll)
