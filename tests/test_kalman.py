"""Planar Kalman filter / RTS smoother (seed eq. 3.4, Algorithm 2) on simulated and real tracks."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from vio.errors import DataError
from vio.nav.cli import smooth_file
from vio.nav.kalman import (KalmanConfig, PlanarKalmanFilter, TumTrack, filter_track,
                            planar_from_poses, process_model, read_tum, smooth_track, wrap_angle,
                            write_tum)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DT = 0.05


def simulate(cfg: KalmanConfig, n: int, seed: int, omega0: float | None = None):
    """Truth drawn from the filter's own model (so NIS must be chi-square), wrapped theta measurements."""
    rng = np.random.default_rng(seed)
    A, R = process_model(DT, cfg)
    s = np.array([1.0, 0, -2.0, 0, 3.0, 0]) + np.array([0, 1, 0, 1, 0, 1]) * rng.normal(size=6) * cfg.init_rate_sigma
    if omega0 is not None:
        s[5] = omega0
    truth = np.empty((n, 6))
    L = np.linalg.cholesky(R + 1e-18 * np.eye(6))
    for k in range(n):
        truth[k] = s
        s = A @ s + L @ rng.normal(size=6)
    sig = np.array([cfg.sigma_x, cfg.sigma_y, cfg.sigma_theta])
    z = truth[:, [0, 2, 4]] + rng.normal(size=(n, 3)) * sig
    z[:, 2] = wrap_angle(z[:, 2])
    return np.arange(n) * DT, truth, z


def pos_rmse(xy: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((xy - truth[:, [0, 2]]) ** 2, axis=1))))


def test_process_noise_is_seed_eq_3_4():
    cfg = KalmanConfig(k1=0.3, k2=0.7, k3=1.9)
    T = 0.1
    A, R = process_model(T, cfg)
    for i, k in enumerate((0.3, 0.7, 1.9)):
        blk = R[2 * i:2 * i + 2, 2 * i:2 * i + 2]
        np.testing.assert_allclose(blk, [[T ** 4 / 4 * k ** 2, T ** 3 / 2 * k ** 2],
                                         [T ** 3 / 2 * k ** 2, T ** 2 * k ** 2]], rtol=1e-12)
        np.testing.assert_allclose(A[2 * i:2 * i + 2, 2 * i:2 * i + 2], [[1, T], [0, 1]])
    off = R.copy()
    for i in range(3):
        off[2 * i:2 * i + 2, 2 * i:2 * i + 2] = 0
    assert np.all(off == 0)


def test_smoothing_beats_raw_and_filter_and_nis_is_consistent():
    cfg = KalmanConfig()
    n = 1500
    t, truth, z = simulate(cfg, n, seed=3)
    filt, smooth = filter_track(t, z, cfg), smooth_track(t, z, cfg)
    raw_e, filt_e, sm_e = pos_rmse(z[:, :2], truth), pos_rmse(filt.planar[:, :2], truth), \
        pos_rmse(smooth.planar[:, :2], truth)
    assert sm_e < 0.5 * raw_e, (sm_e, raw_e)
    assert sm_e < 0.8 * filt_e < 0.8 * raw_e, (sm_e, filt_e, raw_e)
    th_raw = np.sqrt(np.mean(wrap_angle(z[:, 2] - truth[:, 4]) ** 2))
    th_sm = np.sqrt(np.mean(wrap_angle(smooth.theta - truth[:, 4]) ** 2))
    assert th_sm < 0.6 * th_raw, (th_sm, th_raw)
    # NIS: sum over n-1 independent innovations is chi2(3(n-1)); 99% band on the mean.
    nis = filt.nis[1:]
    lo, hi = chi2.ppf([0.005, 0.995], 3 * len(nis)) / len(nis)
    assert lo < nis.mean() < hi, (lo, nis.mean(), hi)
    assert np.isnan(filt.nis[0]) and np.all(filt.innovations[0] == 0)
    np.testing.assert_array_equal(smooth.nis, filt.nis)
    # smoothed covariances are no larger than filtered ones (RTS)
    assert np.all(smooth.covariances[:, [0, 2, 4], [0, 2, 4]] <= filt.covariances[:, [0, 2, 4], [0, 2, 4]] + 1e-15)
    assert smooth.smoothed and not filt.smoothed


def test_nis_detects_a_mistuned_filter():
    """The consistency check can fail: measurements noisier than configured give a high mean NIS."""
    true_cfg = KalmanConfig(sigma_x=0.15, sigma_y=0.15, sigma_theta=0.06)
    t, _, z = simulate(true_cfg, 800, seed=5)
    nis = filter_track(t, z, KalmanConfig()).nis[1:]
    assert nis.mean() > chi2.ppf(0.995, 3 * len(nis)) / len(nis)


def test_theta_wraps_through_pi():
    cfg = KalmanConfig(k3=0.5)
    t, truth, z = simulate(cfg, 600, seed=11, omega0=3.0)  # ~14 turns: crosses +-pi many times
    assert np.sum(np.abs(np.diff(z[:, 2])) > np.pi) >= 10
    for tr in (filter_track(t, z, cfg), smooth_track(t, z, cfg)):
        err = wrap_angle(tr.theta - truth[:, 4])
        assert np.max(np.abs(err)) < 5 * cfg.sigma_theta, np.max(np.abs(err))
        assert np.all(tr.theta > -np.pi) and np.all(tr.theta <= np.pi)
        assert np.nanmax(tr.nis) < chi2.ppf(1 - 1e-6, 3)  # no spike at the wrap
        np.testing.assert_allclose(tr.rates[:, 2].mean(), truth[:, 5].mean(), atol=0.05)


def test_online_filter_matches_batch_and_gate_rejects_outlier():
    cfg = KalmanConfig(gate_nis=chi2.ppf(0.9999, 3))
    t, _, z = simulate(cfg, 200, seed=2)
    z[100, 0] += 3.0  # a 3 m VIO jump
    kf = PlanarKalmanFilter(cfg)
    steps = [kf.step(tk, zk) for tk, zk in zip(t, z)]
    batch = filter_track(t, z, cfg)
    np.testing.assert_allclose([s[1] for s in steps[1:]], batch.nis[1:], rtol=1e-12)
    assert kf.mu[0] == pytest.approx(batch.x[-1], abs=1e-12)
    assert np.flatnonzero(batch.rejected).tolist() == [100]
    assert abs(smooth_track(t, z, cfg).x[100] - z[100, 0]) > 2.5


def test_bad_timestamps_are_clear_errors():
    with pytest.raises(ValueError, match="strictly increase"):
        smooth_track(np.array([0.0, 0.1, 0.1]), np.zeros((3, 3)), KalmanConfig())
    with pytest.raises(ValueError, match="shape"):
        smooth_track(np.zeros(3), np.zeros((3, 5)), KalmanConfig())


def _tilted_track(n: int, seed: int) -> TumTrack:
    """EuRoC-like body (x axis near up), tilted and yawing, z varying."""
    rng = np.random.default_rng(seed)
    R_bx_up = gtsam.Rot3.Ypr(0.0, -1.2, 0.0)  # body x pitched towards the world z axis
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        R = gtsam.Rot3.Ypr(0.4 * k * DT + 3.0, 0.05 * np.sin(k / 9), 0.1 * np.cos(k / 7)).compose(R_bx_up)
        T[k, :3, :3] = R.matrix()
        T[k, :3, 3] = [np.cos(k * DT), np.sin(k * DT), 1.0 + 0.1 * rng.normal()]
    return TumTrack(t_ns=(1_403_715_274_302_140_000 + np.arange(n) * 50_000_000).astype(np.int64), T_w_b=T)


def test_apply_planar_keeps_height_and_tilt(tmp_path):
    cfg = KalmanConfig()
    raw = _tilted_track(120, seed=0)
    write_tum(tmp_path / "raw.txt", raw)
    back = read_tum(tmp_path / "raw.txt")
    np.testing.assert_array_equal(back.t_ns, raw.t_ns)
    np.testing.assert_allclose(back.T_w_b, raw.T_w_b, atol=1e-8)
    sm = smooth_file(tmp_path / "raw.txt", tmp_path / "smooth.txt", cfg)
    out = read_tum(tmp_path / "smooth.txt")
    np.testing.assert_allclose(out.T_w_b[:, 2, 3], raw.T_w_b[:, 2, 3], atol=1e-8)  # z kept
    np.testing.assert_allclose(out.T_w_b[:, :2, 3], sm.planar[:, :2], atol=1e-8)
    # tilt: the world up axis seen from the body is unchanged
    up_raw = np.einsum("nij,i->nj", raw.T_w_b[:, :3, :3], [0, 0, 1.0])
    up_out = np.einsum("nij,i->nj", out.T_w_b[:, :3, :3], [0, 0, 1.0])
    np.testing.assert_allclose(up_out, up_raw, atol=1e-7)
    np.testing.assert_allclose(wrap_angle(planar_from_poses(out.T_w_b, cfg)[:, 2] - sm.theta), 0, atol=1e-7)
    # Pose3 input gives the same measurements as 4x4 matrices; auto heading avoids the up-pointing x
    poses = [gtsam.Pose3(T) for T in raw.T_w_b]
    np.testing.assert_allclose(planar_from_poses(poses, cfg), planar_from_poses(raw.T_w_b, cfg))
    yaw_rate = np.diff(np.unwrap(planar_from_poses(raw.T_w_b, cfg)[:, 2])) / DT
    assert np.median(yaw_rate) == pytest.approx(0.4, abs=0.05)


def test_read_tum_errors_name_file_and_line(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"bad\.txt:3: expected 8 fields"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"bad\.txt:2: timestamp"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(DataError, match="zero quaternion"):
        read_tum(p)


def test_real_euroc_groundtruth_with_noise():
    path = DATA / "euroc_V1_01_static_stereo/mav0/state_groundtruth_estimate0/original_euroc_gt_tum.txt"
    if not path.exists():
        pytest.skip(f"EuRoC ground truth not found at {path}")
    gt = read_tum(path)
    sub = TumTrack(gt.t_ns[2000:12000:10], gt.T_w_b[2000:12000:10])  # 50 s flight at 20 Hz
    cfg = KalmanConfig(k1=2.0, k2=2.0, k3=2.0, sigma_x=0.05, sigma_y=0.05, sigma_theta=0.02)
    truth = planar_from_poses(sub.T_w_b, cfg)
    rng = np.random.default_rng(0)
    z = truth + rng.normal(size=truth.shape) * [0.05, 0.05, 0.02]
    sm = smooth_track(sub.t_s, z, cfg)
    raw_e = np.sqrt(np.mean(np.sum((z[:, :2] - truth[:, :2]) ** 2, 1)))
    sm_e = np.sqrt(np.mean(np.sum((sm.planar[:, :2] - truth[:, :2]) ** 2, 1)))
    assert sm_e < 0.7 * raw_e, (sm_e, raw_e)
    assert np.sqrt(np.mean(wrap_angle(sm.theta - truth[:, 2]) ** 2)) < 0.7 * 0.02
