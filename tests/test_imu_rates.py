"""Keyframe rates for the td term: the mean gyro over [t_k, t_k + td] (and a rolling
shutter's readout), refined as IMU arrives."""

from __future__ import annotations

import numpy as np
import pytest

from vio.imu import KeyframeRates, mean_gyro
from vio.io.types import ImuData

MS = 1_000_000


def _imu(t0_ms: float, t1_ms: float, f=lambda t: np.c_[np.sin(40 * t), t, np.cos(7 * t)]) -> ImuData:
    """200-Hz readings of the rate signal ``f`` (t in s) on [t0, t1] ms."""
    t = np.arange(int(t0_ms * MS), int(t1_ms * MS) + 1, 5 * MS, dtype=np.int64)
    w = f(t * 1e-9)
    return ImuData(t, w, np.zeros_like(w))


def test_mean_gyro_is_the_integral_of_the_interpolated_readings():
    imu = _imu(0, 100)
    # linear readings: exact mean of the line over an interval that cuts sample gaps
    lin = _imu(0, 100, lambda t: np.c_[3 * t, -t, 2 + 0 * t])
    np.testing.assert_allclose(mean_gyro(lin, 12 * MS, 33 * MS), [3 * 0.0225, -0.0225, 2.0], atol=1e-12)
    # against a dense trapezoid of the interpolant
    s = np.linspace(12 * MS, 33 * MS, 20001)
    dense = np.stack([np.interp(s, imu.t_ns, imu.gyro[:, a]) for a in range(3)], 1)
    trap = (0.5 * (dense[1:] + dense[:-1])).mean(0)   # equal steps: trapezoid mean
    np.testing.assert_allclose(mean_gyro(imu, 12 * MS, 33 * MS), trap, atol=1e-7)
    # zero-length interval: the interpolated reading
    np.testing.assert_allclose(mean_gyro(imu, 12 * MS, 12 * MS),
                               [np.interp(12 * MS, imu.t_ns, imu.gyro[:, a]) for a in range(3)])


@pytest.mark.parametrize("td_ms", [5.0, -7.0, 0.0])
def test_keyframe_rate_is_the_mean_over_the_offset_interval(td_ms):
    r = KeyframeRates(margin_s=0.1)
    full = _imu(0, 200)
    r.add_imu(_imu(0, 100))
    w_at = full.gyro[20]                           # reading at the 100-ms keyframe
    r.add_keyframe(3, 100 * MS, w_at)
    lo, hi = sorted((100 * MS, int((100 + td_ms) * MS)))
    if td_ms > 0:                                  # the interval is in the next packet
        np.testing.assert_array_equal(r.rate(3, td_ms * 1e-3), w_at)
        r.add_imu(_imu(100, 150))
    np.testing.assert_allclose(r.rate(3, td_ms * 1e-3), mean_gyro(full, lo, hi), atol=1e-12)
    # follows the td estimate (exact rotation td * rate at any td), not fixed once
    np.testing.assert_allclose(r.rate(3, 2 * td_ms * 1e-3),
                               mean_gyro(full, *sorted((100 * MS, int((100 + 2 * td_ms) * MS)))),
                               atol=1e-12)
    r.drop(3)
    assert 3 not in r


def test_keyframe_rate_cut_at_the_history_and_history_trimmed():
    r = KeyframeRates(margin_s=0.02)
    full = _imu(0, 300)
    r.add_imu(_imu(0, 100))
    r.add_keyframe(0, 100 * MS, full.gyro[20])
    r.add_keyframe(1, 103 * MS, full.gyro[20])
    # half covered: cut at the last sample (100 ms) -> [100, 100] for kf 1 is outside
    np.testing.assert_allclose(r.rate(1, -0.01), mean_gyro(full, 93 * MS, 100 * MS), atol=1e-12)
    r.add_imu(_imu(100, 300))
    r.drop(0)                                      # history now from 103 - 20 ms on
    np.testing.assert_allclose(r.rate(1, -0.01), mean_gyro(full, 93 * MS, 103 * MS), atol=1e-12)
    # an interval the history no longer holds falls back to the reading
    r.add_keyframe(2, 50 * MS, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(r.rate(2, 0.005), [1.0, 2.0, 3.0])


def test_keyframe_rate_offset_by_td_obs():
    """A keyframe whose time already holds ``td_obs`` of the offset (the sync layer's fed-back
    estimate): its rate is the mean over [t_k, t_k + td - td_obs] (or the reverse)."""
    full = _imu(0, 400)
    r = KeyframeRates(margin_s=0.15)
    r.add_imu(full)
    r.add_keyframe(2, 300 * MS, full.gyro[60], td_obs_s=0.003)
    assert r.td_obs(2) == 0.003 and r.td_obs(7) == 0.0
    np.testing.assert_allclose(r.rate(2, 0.010), mean_gyro(full, 300 * MS, 307 * MS), atol=1e-12)
    np.testing.assert_allclose(r.rate(2, -0.002), mean_gyro(full, 295 * MS, 300 * MS), atol=1e-12)
    np.testing.assert_allclose(r.rate(2, 0.003), full.gyro[60], atol=1e-12)


@pytest.mark.parametrize("rem_ms", [6.0, -4.0, -20.0, 0.0])
def test_keyframe_rate_spans_a_rolling_shutters_readout(rem_ms):
    """With a rolling shutter (``readout_s``) the rows are exposed from t_k + rem to t_k +
    rem + readout: the rate is the mean over the interval from t_k to all of them."""
    full = _imu(0, 400)
    r = KeyframeRates(margin_s=0.15)
    r.add_imu(full)
    r.add_keyframe(1, 300 * MS, full.gyro[60], td_obs_s=0.002)
    td = rem_ms * 1e-3 + 0.002
    lo, hi = 300 * MS + min(0, int(rem_ms * MS)), 300 * MS + max(0, int((rem_ms + 14.4) * MS))
    np.testing.assert_allclose(r.rate(1, td, 0.0144), mean_gyro(full, lo, hi), atol=1e-12)
    np.testing.assert_allclose(r.rate(1, td, 0.0), mean_gyro(full, *sorted((300 * MS, 300 * MS + int(rem_ms * MS)))),
                               atol=1e-12)


def test_body_motion_is_the_rate_over_the_offset_and_the_body_velocity():
    """``vio.backend.motion.body_motion`` (the KLT factors' predicted velocities and the
    photometric factors' exposure twists): the bias-corrected mean gyro over [t_k, t_k +
    td - td_obs] at the TD variable's value (with a rolling shutter to its last row's
    time), the velocity in the body frame, zeros at a keyframe flagged still."""
    import gtsam
    from types import SimpleNamespace
    from vio.backend.motion import body_motion
    rates = KeyframeRates(margin_s=0.1)
    imu = _imu(0, 200)
    rates.add_keyframe(3, 50 * MS, imu.gyro[10], td_obs_s=0.002)
    rates.add_imu(imu)
    est = SimpleNamespace(rates=rates, still_kf={4}, cam=SimpleNamespace(readout_s=0.0))
    T = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.3, -0.2, 1.1), np.array([1.0, 2.0, 3.0]))
    v_w, bias = np.array([0.5, -1.0, 0.2]), gtsam.imuBias.ConstantBias(np.zeros(3), np.array([0.01, -0.02, 0.03]))
    w, v = body_motion(est, 3, T, v_w, bias, 0.009)
    np.testing.assert_allclose(w, mean_gyro(imu, 50 * MS, 57 * MS) - [0.01, -0.02, 0.03], atol=1e-12)
    np.testing.assert_allclose(v, T.rotation().matrix().T @ v_w, atol=1e-12)
    w, v = body_motion(est, 4, T, v_w, bias, 0.009)
    assert not w.any() and not v.any()
    est.cam = SimpleNamespace(readout_s=3e-5 * 480)                    # a 14.4-ms readout
    w, _ = body_motion(est, 3, T, v_w, bias, 0.009)
    np.testing.assert_allclose(w, mean_gyro(imu, 50 * MS, int(71.4 * MS)) - [0.01, -0.02, 0.03], atol=1e-12)
