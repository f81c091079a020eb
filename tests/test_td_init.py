"""The camera-IMU offset at a dynamic initialization (``vio.backend.td_init``)."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from vio.backend.config import TdSearchConfig
from vio.backend.td_init import pair_residuals, refine_minimum, search_td, shift_state
from vio.imu import ImuNoiseConfig, combined_params
from vio.io.types import ImuCalib, ImuData

CALIB = ImuCalib(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3, 200.0)
BG = np.array([-0.002, 0.021, 0.077])


def _shaking(seed: int, seconds: float = 2.0, amp: float = 1.5, hz: float = 2.0):
    """Gyro (200 Hz, ``BG`` added) of a body rotating with rates ``amp`` rad/s at
    ~``hz`` on each axis, and its true orientation at every sample (midpoint rule)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * 200) + 1) * 0.005
    ph = rng.uniform(0, 2 * np.pi, 3)
    f = hz * rng.uniform(0.7, 1.3, 3)
    w = amp * np.sin(2 * np.pi * f * t[:, None] + ph)
    R = [np.eye(3)]
    for k in range(len(t) - 1):
        R.append(R[-1] @ gtsam.Rot3.Expmap(0.5 * (w[k] + w[k + 1]) * 0.005).matrix())
    imu = ImuData((t * 1e9).astype(np.int64), w + BG, np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    return imu, np.array(R)


def _pairs(R: np.ndarray, kf_idx: np.ndarray, delta_samples: int, noise_deg: float, seed: int):
    """Visual body rotations between keyframes 3 and 5 apart, taken at the samples
    ``delta_samples`` after the keyframes' stamps (the true offset), with noise."""
    rng = np.random.default_rng(seed)
    out = []
    for s in (3, 5):
        for i in range(len(kf_idx) - s):
            a, b = kf_idx[i] + delta_samples, kf_idx[i + s] + delta_samples
            Rn = gtsam.Rot3.Expmap(rng.normal(0, np.radians(noise_deg), 3)).matrix()
            out.append((i, i + s, R[a].T @ R[b] @ Rn))
    return out


@pytest.mark.parametrize("delta_ms", [-20, 0, 10, 25])
def test_search_recovers_the_offset_of_a_shaking_window(delta_ms):
    """Keyframes every 0.1 s over 2 s of hand-held-like rotation, visual rotations with
    0.2-degree noise: the remainder within 1.5 ms (grid step 2.5 ms), the bias within
    0.005 rad/s; a true 0 is reported as 0 (not significant) or within 1.5 ms."""
    imu, R = _shaking(seed=3)
    kf = np.arange(12, len(R) - 12, 20)               # 50 ms of IMU beyond both ends
    pairs = _pairs(R, kf, delta_ms // 5, 0.2, seed=4)
    res = search_td(imu, imu.t_ns[kf], pairs, np.zeros(3), TdSearchConfig())
    assert abs(res.best_s - delta_ms * 1e-3) < 1.5e-3
    assert np.abs(res.bg - BG).max() < 0.005
    if delta_ms:
        assert res.td_s == res.best_s and res.sigma_s < 1e-3 and res.gain > 100
    else:
        assert abs(res.td_s) < 1.5e-3


@pytest.mark.parametrize("delta_ms", [-30, 0, 25])
@pytest.mark.parametrize("bg_off", [[0.1, -0.08, 0.06], [0.15, 0.1, -0.1]])
def test_search_starts_from_a_wrong_bias(delta_ms, bg_off):
    """A starting bias 0.1-0.15 rad/s off (one fitted with the offset unmodelled) leaves
    no pair within the 1.5-degree tolerance: the wide-tolerance start still finds the
    offset and the bias; started from it alone (``wide_tol_factor`` 1) the search reports
    a wrong minimum (at true 0 it even applies -11 ms)."""
    imu, R = _shaking(seed=3)
    kf = np.arange(12, len(R) - 12, 20)
    pairs = _pairs(R, kf, delta_ms // 5, 0.2, seed=4)
    res = search_td(imu, imu.t_ns[kf], pairs, BG + bg_off, TdSearchConfig())
    assert abs(res.best_s - delta_ms * 1e-3) < 1.5e-3 and np.abs(res.bg - BG).max() < 0.005
    assert res.n_inliers == res.n_pairs
    assert (res.td_s == res.best_s) if delta_ms else abs(res.td_s) < 1.5e-3
    old = search_td(imu, imu.t_ns[kf], pairs, BG + bg_off, TdSearchConfig(wide_tol_factor=1.0))
    assert abs(old.best_s - delta_ms * 1e-3) > 5e-3 and old.n_inliers <= 3


def test_parabola_refines_between_grid_points():
    """A 3-ms grid around a true 10 ms (grid points 9 and 12 ms): the parabola through the
    cost minimum and its neighbours lands within 0.5 ms."""
    imu, R = _shaking(seed=3)
    kf = np.arange(12, len(R) - 12, 20)
    res = search_td(imu, imu.t_ns[kf], _pairs(R, kf, 2, 0.2, seed=4), np.zeros(3),
                    TdSearchConfig(step_s=0.003, search_s=0.045))
    assert abs(res.best_s - 0.010) < 5e-4 and res.td_s == res.best_s


def test_an_offset_beyond_the_grid_is_seen_but_not_applied():
    """A true 25 ms searched over +-20 ms: the minimum lies on the grid's edge, so no
    curvature, no sigma and nothing applied, but its gain still reports that the rotations
    see an offset (the dynamic initialization then walks its batch from there), where a
    true 0 in the same window reports none."""
    imu, R = _shaking(seed=3)
    kf = np.arange(12, len(R) - 12, 20)
    cfg = TdSearchConfig(search_s=0.02)
    far = search_td(imu, imu.t_ns[kf], _pairs(R, kf, 5, 0.2, seed=4), np.zeros(3), cfg)
    assert far.best_s == pytest.approx(0.02) and far.td_s == 0.0 and far.sigma_s == float("inf")
    assert far.gain >= cfg.try_gain
    none = search_td(imu, imu.t_ns[kf], _pairs(R, kf, 0, 0.2, seed=4), np.zeros(3), cfg)
    assert none.gain < cfg.try_gain


@pytest.mark.parametrize("x0, truth", [(0.0203, 0.0252), (-0.029, -0.0245), (0.0, 0.0)])
def test_refine_minimum_walks_to_the_parabola_vertex(x0, truth):
    """The batch td walk (``refine_minimum``) on an exact parabola: the vertex to the
    float, from a start a few steps away; the curvature and the drop as given."""
    calls = []

    def cost(x):
        calls.append(x)
        return 263.0 + 5e5 * (x - truth) ** 2

    x, a, drop = refine_minimum(cost, x0, 0.005, 0.03)
    n_calls = len(calls)
    assert abs(x - truth) < 1e-9 and abs(a - 5e5) < 1e-3
    assert abs(drop - (cost(x0) - cost(x0 + round((truth - x0) / 0.005) * 0.005))) < 1e-9
    assert n_calls <= 3 + abs(round((truth - x0) / 0.005)) + 1


def test_refine_minimum_stops_at_its_range_and_at_unevaluable_points():
    """A minimum beyond the walk's range ends at the range with no curvature (not a
    bracketed minimum); an inf neighbour (IMU not covering the shift) is never chosen."""
    x, a, _ = refine_minimum(lambda x: (x - 0.1) ** 2, 0.0, 0.005, 0.02)
    assert abs(x - 0.02) < 1e-12 and a == 0.0
    x, a, drop = refine_minimum(lambda x: np.inf if x > 0.001 else (x - 0.01) ** 2, 0.0, 0.005, 0.03)
    assert x == 0.0 and a == 0.0 and drop == 0.0


def test_refine_minimum_brackets_a_minimum_on_its_range_edge():
    """With ``bracket``, a minimum on the range's edge (a batch walked from 0 over +-30 ms
    when the true offset is 30 ms) gets its curvature from one step beyond, so a sigma;
    one further beyond still ends at the edge with none."""
    para = lambda v: lambda x: 50.0 + 5e5 * (x - v) ** 2   # noqa: E731
    x, a, _ = refine_minimum(para(0.0305), 0.0, 0.005, 0.03)
    assert abs(x - 0.03) < 1e-12 and a == 0.0                # without: no curvature
    x, a, _ = refine_minimum(para(0.0305), 0.0, 0.005, 0.03, bracket=True)
    assert abs(x - 0.0305) < 1e-9 and abs(a - 5e5) < 1e-3
    x, a, _ = refine_minimum(para(-0.0295), 0.0, 0.005, 0.03, bracket=True)
    assert abs(x + 0.0295) < 1e-9 and abs(a - 5e5) < 1e-3
    x, a, _ = refine_minimum(para(0.1), 0.0, 0.005, 0.03, bracket=True)
    assert abs(x - 0.03) < 1e-12 and a == 0.0


def test_constant_rotation_leaves_the_offset_unobservable():
    """A constant rate: shifting every keyframe by delta rotates nothing between them, so
    no remainder is applied."""
    imu, R = _shaking(seed=1, amp=0.0)
    imu = replace(imu, gyro=imu.gyro + [0.3, -0.2, 0.5])
    w = np.array([0.3, -0.2, 0.5])
    R = np.array([gtsam.Rot3.Expmap(w * t * 1e-9).matrix() for t in imu.t_ns])
    kf = np.arange(12, len(R) - 12, 20)
    res = search_td(imu, imu.t_ns[kf], _pairs(R, kf, 4, 0.2, seed=2), np.zeros(3), TdSearchConfig())
    assert res.td_s == 0.0


def test_wrong_pairs_do_not_move_the_offset():
    """A quarter of the visual rotations 8-20 degrees off (failed essential matrices)."""
    imu, R = _shaking(seed=5)
    kf = np.arange(12, len(R) - 12, 20)
    pairs = _pairs(R, kf, 5, 0.2, seed=6)
    rng = np.random.default_rng(7)
    for m in rng.choice(len(pairs), len(pairs) // 4, replace=False):
        ax = rng.normal(size=3)
        i, j, Rij = pairs[m]
        pairs[m] = (i, j, Rij @ gtsam.Rot3.Expmap(ax / np.linalg.norm(ax) * np.radians(rng.uniform(8, 20))).matrix())
    res = search_td(imu, imu.t_ns[kf], pairs, np.zeros(3), TdSearchConfig())
    assert abs(res.td_s - 0.025) < 1.5e-3


def test_pair_residuals_vanish_at_the_truth():
    imu, R = _shaking(seed=8)
    kf = np.arange(12, len(R) - 12, 20)
    pairs = _pairs(R, kf, 3, 0.0, seed=0)
    t = (imu.t_ns - imu.t_ns[0]) * 1e-9
    ti = np.array([t[kf[i]] for i, _, _ in pairs])
    tj = np.array([t[kf[j]] for _, j, _ in pairs])
    Rv = np.array([p[2] for p in pairs])
    r = pair_residuals(t, imu.gyro, BG, 0.015, ti, tj, Rv)
    assert np.abs(r).max() < 1e-9
    assert np.abs(pair_residuals(t, imu.gyro, BG, 0.0, ti, tj, Rv)).max() > 1e-3


@pytest.mark.parametrize("dt_ms", [-25, 40])
def test_shift_state_round_trip_and_motion(dt_ms):
    """Carrying a state to another time (either direction) and back returns it."""
    imu, _ = _shaking(seed=2, seconds=0.5)
    params = combined_params(CALIB, ImuNoiseConfig())
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), BG)
    T = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.1, 0.05), np.array([1.0, 2.0, 3.0]))
    v = np.array([0.5, -0.2, 0.1])
    t0 = int(imu.t_ns[40])
    t1 = t0 + dt_ms * 1_000_000
    T1, v1 = shift_state(T, v, bias, imu, t0, t1, params)
    T2, v2 = shift_state(T1, v1, bias, imu, t1, t0, params)
    assert np.allclose(T2.matrix(), T.matrix(), atol=1e-9) and np.allclose(v2, v, atol=1e-9)


@pytest.mark.parametrize("bad", [{"wide_tol_factor": 0.5}, {"refused_try_gain": 10.0},
                                 {"refused_try_gain": -1.0}, {"walk_gain": 9.5}, {"walk_gain": -0.1}])
def test_search_config_rejects_out_of_range_values(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        TdSearchConfig(**bad)
