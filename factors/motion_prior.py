"""Constant-velocity motion prior between two keyframe states (the IMU-gap bridge).

Across an IMU gap there is no measurement to preintegrate. The body is modelled as
moving with white acceleration (density ``q_a``, m/s^2/sqrt(Hz)) and white rotation rate
(density ``q_w``, rad/s/sqrt(Hz)) over the interval ``dt`` between keyframes i and j:

    r_R = Log(R_i^T R_j)                    rotation random walk,  cov q_w^2 dt I
    r_p = p_j - p_i - v_i dt    (world)     \\  per axis:
    r_v = v_j - v_i             (world)     /   cov q_a^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]

(the Wiener-process-acceleration prior of a constant-velocity model). Position and
attitude are independent here: a gap bridged by preintegrating fictitious "still"
readings (``R^T g`` and zero rate) instead ties the predicted position to the start
attitude through the gravity term ``g dt^2 / 2``, so that a tilt allowed by the rate
noise moves the predicted position by decimetres and lets vision trade one for the
other (real V1_01, 0.5-s gap at 7 s: keyframes 1 m and 5 m/s off within 0.2 s).

Keys ``[T_w_bi (Pose3), v_i (3), T_w_bj (Pose3), v_j (3)]``; residual ``[r_R, r_p, r_v]``
(9,). Jacobians are exact for GTSAM's retraction ``T Exp([omega, v])``
(``tests/cases_motion_prior.py``).
"""

from __future__ import annotations

from typing import Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_r^{-1}(phi)`` (3, 3) of SO(3): ``Log(Exp(phi) Exp(d)) = phi + J_r^{-1}(phi) d + O(d^2)``."""
    th = float(np.linalg.norm(phi))
    W = _hat(phi)
    if th < 1e-6:
        return np.eye(3) + 0.5 * W + W @ W / 12.0
    c = 1.0 / th ** 2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th))
    return np.eye(3) + 0.5 * W + c * (W @ W)


def motion_prior_residual(args: list, dt: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual (9,) and Jacobians ``[(9, 6), (9, 3), (9, 6), (9, 3)]`` in key order.

    ``args``: ``[T_w_bi, v_i (3,), T_w_bj, v_j (3,)]`` (poses ``gtsam.Pose3``, velocities
    m/s in the world frame); ``dt`` (s): the interval from i to j."""
    Ti, vi, Tj, vj = args[0], np.asarray(args[1], float), args[2], np.asarray(args[3], float)
    Ri, Rj = Ti.rotation().matrix(), Tj.rotation().matrix()
    pi, pj = np.asarray(Ti.translation(), float), np.asarray(Tj.translation(), float)
    E = Ri.T @ Rj
    phi = np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(E)), float)
    Jinv = right_jacobian_inverse(phi)
    r = np.concatenate([phi, pj - pi - vi * dt, vj - vi])
    I3, Z3 = np.eye(3), np.zeros((3, 3))
    # pose i rotated by Exp(d): Log(Exp(-d) E) = phi - J_r^{-1}(phi) E^T d; pose j: phi + J_r^{-1} d
    J_Ti = np.block([[-Jinv @ E.T, Z3], [Z3, -Ri], [Z3, Z3]])
    J_vi = np.vstack([Z3, -dt * I3, -I3])
    J_Tj = np.block([[Jinv, Z3], [Z3, Rj], [Z3, Z3]])
    J_vj = np.vstack([Z3, Z3, I3])
    return r, [J_Ti, J_vi, J_Tj, J_vj]


def motion_prior_covariance(dt: float, accel_density: float, gyro_density: float) -> np.ndarray:
    """Covariance (9, 9) of ``[r_R, r_p, r_v]`` over ``dt`` seconds (module docstring)."""
    C = np.zeros((9, 9))
    C[:3, :3] = gyro_density ** 2 * dt * np.eye(3)
    q = accel_density ** 2
    C[3:6, 3:6] = q * dt ** 3 / 3.0 * np.eye(3)
    C[3:6, 6:9] = C[6:9, 3:6] = q * dt ** 2 / 2.0 * np.eye(3)
    C[6:9, 6:9] = q * dt * np.eye(3)
    return C


def motion_prior_factor(keys: Sequence[int], dt: float, accel_density: float, gyro_density: float,
                        health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """The prior as a ``gtsam.CustomFactor`` over ``keys = [X_i, V_i, X_j, V_j]``;
    ``dt`` > 0 (s), densities > 0."""
    if not (dt > 0 and accel_density > 0 and gyro_density > 0):
        raise ValueError(f"motion prior needs dt, accel_density, gyro_density > 0, got "
                         f"{dt}, {accel_density}, {gyro_density}")
    noise = gtsam.noiseModel.Gaussian.Covariance(motion_prior_covariance(dt, accel_density, gyro_density))
    return custom_factor(noise, keys, ["pose3", 3, "pose3", 3],
                         lambda args: motion_prior_residual(args, dt), health)
