"""vio.sim.fuse: the generator's IMU-consistent ground truth.

On a simulated sequence (IMU consistent with its trajectory by construction) a ground
truth spoiled by jitter is pulled back to the true motion; on real EuRoC data the
smoothed trajectory stays within millimetres of the ground truth while its rotation
agrees with the gyro far better.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from conftest import shared
from vio.io.calib import read_imu_yaml
from vio.io.euroc import find_mav0, read_groundtruth, read_imu_csv
from vio.sim import simulate
from vio.sim.config import SimConfig
from vio.sim.fuse import fuse_groundtruth
from vio.sync import packets
from vio.trajectory import interpolate_poses


def _load(root):
    m = find_mav0(root)
    return (read_groundtruth(m / "state_groundtruth_estimate0"), read_imu_csv(m / "imu0" / "data.csv"),
            read_imu_yaml(m / "imu0" / "sensor.yaml"))


def _rot_err(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(a).between(gtsam.Rot3(b))))
                     for a, b in zip(Ra, Rb)])


def _gyro_residual(nodes, R, bg, imu) -> float:
    """RMS (rad) of the rotation between consecutive nodes minus the integrated gyro."""
    out = []
    pk = list(packets(imu, nodes))
    for i in range(1, len(nodes)):
        s = pk[i].imu
        w = 0.5 * (s.gyro[1:] + s.gyro[:-1]) - bg[i - 1]
        Ri = gtsam.Rot3()
        for k, d in enumerate(np.diff(s.t_ns) * 1e-9):
            Ri = Ri.compose(gtsam.Rot3.Expmap(w[k] * d))
        out.append(np.linalg.norm(gtsam.Rot3.Logmap(Ri.between(gtsam.Rot3(R[i - 1]).between(gtsam.Rot3(R[i]))))))
    return float(np.sqrt(np.mean(np.square(out))))


def test_jittered_ground_truth_is_pulled_back_to_the_true_motion(tmp_path):
    simulate(tmp_path, SimConfig(seconds=4.0, seed=2, render_images=False))
    gt, imu, calib = _load(tmp_path)
    rng = np.random.default_rng(0)
    jit = np.array([gtsam.Rot3.Expmap(rng.normal(0, 0.003, 3)).matrix() for _ in range(len(gt))])
    q_bad = np.array([gtsam.Rot3(gtsam.Rot3.Quaternion(*q).matrix() @ J).toQuaternion().coeffs()[[3, 0, 1, 2]]
                      for q, J in zip(gt.q_wxyz, jit)])
    p_bad = gt.p_w + rng.normal(0, 0.002, gt.p_w.shape)
    tk = gt.t_ns[20] + np.arange(70) * 50_000_000
    nodes = np.unique(np.r_[tk, tk + 5_000_000])
    p_true, R_true = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, nodes)
    p_in, R_in = interpolate_poses(gt.t_ns, p_bad, q_bad, nodes)
    f = fuse_groundtruth(nodes, gt.t_ns, p_bad, q_bad, imu, calib)
    e_in, e_out = _rot_err(R_true, R_in), _rot_err(R_true, f.R_w_b)
    assert np.sqrt(np.mean(e_out ** 2)) < 0.4 * np.sqrt(np.mean(e_in ** 2))
    pin = np.sqrt(np.mean(np.sum((p_in - p_true) ** 2, 1)))
    pout = np.sqrt(np.mean(np.sum((f.p_w - p_true) ** 2, 1)))
    assert pout < 0.5 * pin
    assert f.shift_rot_rms_rad == pytest.approx(np.sqrt(np.mean(_rot_err(R_in, f.R_w_b) ** 2)))
    rows = f.euroc_values()
    assert rows.shape == (len(nodes), 16)
    np.testing.assert_allclose(np.abs(np.sum(rows[:, 3:7] * np.array(
        [gtsam.Rot3(R).toQuaternion().coeffs()[[3, 0, 1, 2]] for R in f.R_w_b]), 1)), 1.0, atol=1e-9)
    with pytest.raises(ValueError, match="not a node"):
        f.at(nodes[:1] + 1)


def test_real_ground_truth_moves_little_and_agrees_with_the_gyro():
    gt, imu, calib = _load(shared("euroc_imu_gt", "V2_01_easy"))
    tk = gt.t_ns[0] + 1_000_000_000 + np.arange(200) * 50_000_000
    nodes = np.unique(np.r_[tk, tk + 5_000_000])
    f = fuse_groundtruth(nodes, gt.t_ns, gt.p_w, gt.q_wxyz, imu, calib)
    assert f.shift_pos_rms_m < 0.004 and np.degrees(f.shift_rot_rms_rad) < 0.3
    _, R0 = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, nodes)
    before, after = _gyro_residual(nodes, R0, f.bg, imu), _gyro_residual(nodes, f.R_w_b, f.bg, imu)
    assert after < 0.7 * before, (before, after)


def test_datasheet_imu_model_makes_both_residual_sets_consistent():
    """With the sensor's datasheet densities the whitened residuals of IMU factors and
    ground-truth priors are both of order one; the estimator's x5-inflated model made
    the smoother follow the ground truth (IMU chi^2/dof ~0.03), including the ground
    truth's own high-frequency errors that no camera would see."""
    from vio.imu import ImuNoiseConfig
    gt, imu, calib = _load(shared("euroc_imu_gt", "MH_05_difficult"))
    tk = gt.t_ns[0] + 14_000_000_000 + np.arange(300) * 50_000_000
    nodes = np.unique(np.r_[tk, tk + 5_000_000])
    f = fuse_groundtruth(nodes, gt.t_ns, gt.p_w, gt.q_wxyz, imu, calib)
    assert 0.05 < f.imu_chi2_dof < 3.0 and 0.05 < f.gt_chi2_dof < 3.0, (f.imu_chi2_dof, f.gt_chi2_dof)
    inflated = fuse_groundtruth(nodes, gt.t_ns, gt.p_w, gt.q_wxyz, imu, calib, noise=ImuNoiseConfig(5.0, 5.0))
    assert inflated.imu_chi2_dof < 0.2 * f.imu_chi2_dof
    assert inflated.shift_pos_rms_m < f.shift_pos_rms_m     # it stays glued to the ground truth


def test_nodes_without_a_prior_follow_the_imu_and_leave_the_others_unchanged():
    """The generator fuses at frame stamps and exposure times but puts ground-truth priors
    on the exposures only (``TrackGenConfig.gt_priors``): the extra nodes must not pull
    the solution, so the exposure nodes agree with a fusion at the exposures alone."""
    gt, imu, calib = _load(shared("euroc_imu_gt", "V2_01_easy"))
    tk = gt.t_ns[0] + 1_000_000_000 + np.arange(60) * 50_000_000
    expo = tk + 25_000_000
    nodes = np.unique(np.r_[tk, expo])
    with_stamps = fuse_groundtruth(nodes, gt.t_ns, gt.p_w, gt.q_wxyz, imu, calib,
                                   prior_mask=np.isin(nodes, expo))
    alone = fuse_groundtruth(expo, gt.t_ns, gt.p_w, gt.q_wxyz, imu, calib)
    p, R = with_stamps.at(expo)
    assert np.abs(p - alone.p_w).max() < 2e-4
    assert _rot_err(R, alone.R_w_b).max() < 2e-4
    both = fuse_groundtruth(nodes, gt.t_ns, gt.p_w, gt.q_wxyz, imu, calib)   # priors everywhere
    assert np.abs(both.at(expo)[0] - alone.p_w).max() > 2 * np.abs(p - alone.p_w).max()
