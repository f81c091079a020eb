"""Recover a known camera-IMU time offset with the td factors (seed 004).

Simulation: a body moving smoothly (sinusoidal translation and rotation), a camera at a
known extrinsic, 40 points. Frame k is stamped ``t_k`` but exposed at ``t_k + TD`` (plus
``row / ROWS * T_READOUT`` for the rolling-shutter variant). Observations get 0.3 px of
noise; image velocities come from backward differences of consecutive observations, as
a front end computes them. Poses at the stamps are known (tight priors), inverse depths
start 10% off and td starts at 0; both are estimated.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_projection import C, L, T, X
from factors.landmark import landmark_factor, make_track
from factors.td_projection import TdObservation, td_projection_factor

TD = 0.008  # s
FPS, N_FRAMES, N_POINTS = 20.0, 30, 40
F, CX, CY, ROWS = 460.0, 320.0, 240.0, 480
PIX_SIGMA = 0.3
T_B_C = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2), np.array([0.05, -0.02, 0.01]))


def body_pose(t: float) -> gtsam.Pose3:
    """Smooth body trajectory: ~0.4 m/s, ~40 deg/s."""
    w = np.array([0.25 * np.sin(1.7 * t), 0.2 * np.sin(2.3 * t + 0.5), 0.35 * np.sin(1.9 * t)])
    p = np.array([0.4 * t, 0.3 * np.sin(2.1 * t), 0.15 * np.sin(2.9 * t)])
    return gtsam.Pose3(gtsam.Rot3.Expmap(w), p)


def observe(p_w: np.ndarray, t: float, readout: float) -> np.ndarray | None:
    """Normalized observation of p_w in the image stamped t (exposed at t + TD + row time)."""
    uv = None
    row = CY
    for _ in range(4):  # rolling shutter: exposure time depends on the row it lands on
        p = body_pose(t + TD + row / ROWS * readout).compose(T_B_C).transformTo(p_w)
        if p[2] < 0.5:
            return None
        uv = p[:2] / p[2]
        row = F * uv[1] + CY
    if not (np.abs(F * uv[0]) < CX - 5 and 5 < row < ROWS - 5):
        return None
    return uv


def simulate(rng: np.random.Generator, readout: float):
    """Per point: (stamps index list, uv (m,2) noisy, vel (m,2), rows (m,)) and true inv depth."""
    stamps = np.arange(N_FRAMES) / FPS
    T0 = body_pose(0.0).compose(T_B_C)
    tracks = []
    while len(tracks) < N_POINTS:
        uvi, lam = rng.uniform([-0.5, -0.35], [0.5, 0.35]), rng.uniform(1 / 7, 1 / 3)
        p_w = T0.transformFrom(np.append(uvi, 1) / lam)
        obs = [observe(p_w, t, readout) for t in stamps]
        if any(o is None for o in obs):
            continue
        uv = np.array(obs) + rng.normal(size=(N_FRAMES, 2)) * PIX_SIGMA / F
        vel = np.empty_like(uv)
        vel[1:] = np.diff(uv, axis=0) * FPS  # backward differences, as a front end does
        vel[0] = vel[1]
        rows = F * uv[:, 1] + CY
        tracks.append((uv, vel, rows, p_w))
    return stamps, tracks


def _base_graph(stamps) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    tight = gtsam.noiseModel.Isotropic.Sigma(6, 1e-7)
    for k, t in enumerate(stamps):
        graph.add(gtsam.PriorFactorPose3(X(k), body_pose(t), tight))
        values.insert(X(k), body_pose(t))
    graph.add(gtsam.PriorFactorPose3(C(0), T_B_C, tight))
    values.insert(C(0), T_B_C)
    values.insert(T(0), np.array([0.0]))
    return graph, values


def estimate_td(readout: float, per_landmark: bool, model: str, seed: int = 3) -> float:
    rng = np.random.default_rng(seed)
    stamps, tracks = simulate(rng, readout)
    graph, values = _base_graph(stamps)
    sigma = PIX_SIGMA / F
    for l, (uv, vel, rows, p_w) in enumerate(tracks):
        a = l % 5  # anchors spread over the first frames
        lam = 1.0 / body_pose(stamps[a]).compose(T_B_C).transformTo(p_w)[2]
        values.insert(L(l), np.array([lam * rng.uniform(0.9, 1.1)]))
        row_time = rows / ROWS * readout
        others = [k for k in range(N_FRAMES) if k != a]
        if per_landmark:
            track = make_track(X(a), uv[a], [X(k) for k in others], uv[others], vel[a],
                               vel[others], row_time[a], row_time[others])
            graph.add(landmark_factor(track, L(l), C(0), sigma, model, None, T(0)))
            continue
        noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
        oi = TdObservation.create(uv[a], vel[a], rows[a], ROWS, readout)
        for k in others:
            oj = TdObservation.create(uv[k], vel[k], rows[k], ROWS, readout)
            graph.add(td_projection_factor(noise, [X(a), X(k), C(0), L(l), T(0)], oi, oj, model))
    res = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return float(res.atVector(T(0))[0])


@pytest.mark.parametrize(("model", "per_landmark"), [("pinhole", True), ("sphere", True),
                                                     ("sphere", False)])
def test_td_recovered_global_shutter(model: str, per_landmark: bool) -> None:
    td = estimate_td(0.0, per_landmark, model)
    assert abs(td - TD) < 0.5e-3, f"td estimate {td * 1e3:.3f} ms vs true {TD * 1e3:.1f} ms"


@pytest.mark.parametrize("model", ["pinhole", "sphere"])
def test_td_recovered_rolling_shutter(model: str) -> None:
    td = estimate_td(0.03, True, model)
    assert abs(td - TD) < 0.5e-3, f"td estimate {td * 1e3:.3f} ms vs true {TD * 1e3:.1f} ms"


def test_ignoring_rolling_shutter_biases_td() -> None:
    """Control: treating a 30 ms rolling shutter as global shifts td by ~readout/2."""
    rng = np.random.default_rng(3)
    stamps, tracks = simulate(rng, 0.03)
    graph, values = _base_graph(stamps)
    for l, (uv, vel, _, p_w) in enumerate(tracks):
        lam = 1.0 / body_pose(0.0).compose(T_B_C).transformTo(p_w)[2]
        values.insert(L(l), np.array([lam]))
        track = make_track(X(0), uv[0], [X(k) for k in range(1, N_FRAMES)], uv[1:], vel[0], vel[1:])
        graph.add(landmark_factor(track, L(l), C(0), PIX_SIGMA / F, "pinhole", None, T(0)))
    td = float(gtsam.LevenbergMarquardtOptimizer(graph, values).optimize().atVector(T(0))[0])
    assert abs(td - (TD + 0.015)) < 3e-3
