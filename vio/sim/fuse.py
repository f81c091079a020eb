"""Ground truth made consistent with the real IMU, for the feature-track generator.

The generator renders its tracks from the real trajectory of a EuRoC sequence and
ships the real IMU with them. EuRoC's ground truth is itself an estimate (motion
capture or laser tracker, fused and resampled): measured on the eight ``euroc_imu_gt``
sequences, its body rate disagrees with the gyro by a time shift of up to about 1 ms
(0.0-0.4 ms from 50-ms rotation differences, up to 1.0 ms from smoothed 200-Hz rates)
and by more than the gyro noise, and that disagreement bleeds into everything an estimator
infers from vision against IMU. A real camera does not see that disagreement: it sees
the true motion, which the IMU measures. So the generator renders from the best
estimate of the true motion given both sensors: a batch smoother over nodes at the
render and evaluation times with

* a prior on every node's ``T_w_b`` from the interpolated ground truth (``pos_sigma_m``,
  ``rot_sigma_rad``: the ground truth's own accuracy),
* GTSAM's ``CombinedImuFactor`` between consecutive nodes on the real IMU samples, with
  the sensor's datasheet densities (:func:`vio.imu.combined_params` at scale 1 by default;
  the estimator inflates them x5 for robustness, which is no measurement model),

solved by Levenberg-Marquardt. The result (poses, velocities, biases at the nodes) is
the generated dataset's ground truth. Both residual sets should then be consistent with
their noise models: the whitened chi^2 per degree of freedom of the IMU factors and of the
ground-truth priors is returned (measured on the eight ``euroc_imu_gt`` excerpts: IMU
0.3-0.6, ground truth 0.4-2.0). Borrowing the estimator's x5 model instead gave 0.03-0.14 and
0.02-0.5: the smoother then followed the ground truth's own high-frequency errors, which the
IMU never measured, and an estimator given perfect tracks rendered from it stopped 0.16-0.41
ms short of the true td with 0.14-0.19% ATE on the Machine Hall excerpts (with the datasheet
model: within 0.1 ms and 0.09-0.13%). Frames: ``T_w_b`` body (IMU) in the world, world
z up (gravity along -z); times int64 ns in the IMU clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.imu import ImuNoiseConfig, combined_params, integrate
from vio.io.types import ImuCalib, ImuData
from vio.sync import packets
from vio.trajectory import interpolate_poses

X = gtsam.symbol_shorthand.X
V = gtsam.symbol_shorthand.V
B = gtsam.symbol_shorthand.B


@dataclass(frozen=True)
class FusedTrajectory:
    """Body states at ``t_ns`` (K,): ``p_w`` (K, 3) m, ``q_wxyz`` (K, 4) unit quaternions
    of ``R_w_b`` (the values written to file, and rendered from), ``v_w`` (K, 3) m/s,
    ``bg`` / ``ba`` (K, 3) gyro (rad/s) and accelerometer (m/s^2) biases; ``shift_*``:
    RMS change of position (m) and rotation (rad) from the input ground truth;
    ``imu_chi2_dof`` / ``gt_chi2_dof``: mean whitened chi^2 per degree of freedom of the
    IMU factors and of the ground-truth pose priors at the solution (about 1 when both
    noise models describe the data)."""

    t_ns: np.ndarray
    p_w: np.ndarray
    q_wxyz: np.ndarray
    v_w: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    shift_pos_rms_m: float
    shift_rot_rms_rad: float
    imu_chi2_dof: float = float("nan")
    gt_chi2_dof: float = float("nan")

    def at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(p_w (M, 3), R_w_b (M, 3, 3)) at node times ``t_ns`` (each must be a node)."""
        i = np.searchsorted(self.t_ns, t_ns)
        if np.any(i >= len(self.t_ns)) or np.any(self.t_ns[np.minimum(i, len(self.t_ns) - 1)] != t_ns):
            raise ValueError("FusedTrajectory.at: a requested time is not a node")
        return self.p_w[i], _matrices(self.q_wxyz[i])

    @property
    def R_w_b(self) -> np.ndarray:
        """(K, 3, 3) rotations of ``q_wxyz``."""
        return _matrices(self.q_wxyz)

    def euroc_values(self) -> np.ndarray:
        """(K, 16) value columns of an EuRoC ``state_groundtruth_estimate0/data.csv``
        row after the int64 stamp ``t_ns``: p, q_wxyz, v, bg, ba."""
        return np.column_stack([self.p_w, self.q_wxyz, self.v_w, self.bg, self.ba])


def _matrices(q_wxyz: np.ndarray) -> np.ndarray:
    return np.array([gtsam.Rot3.Quaternion(*q).matrix() for q in q_wxyz]).reshape(-1, 3, 3)


def fuse_groundtruth(node_t: np.ndarray, gt_t: np.ndarray, gt_p: np.ndarray, gt_q: np.ndarray,
                     imu: ImuData, calib: ImuCalib, pos_sigma_m: float = 0.002,
                     rot_sigma_rad: float = 0.005, noise: ImuNoiseConfig = ImuNoiseConfig(1.0, 1.0),
                     prior_mask: np.ndarray | None = None) -> FusedTrajectory:
    """Smooth the ground truth (``gt_t`` (N,) ns, ``gt_p`` (N, 3), ``gt_q`` (N, 4) wxyz)
    against the IMU at the increasing node times ``node_t`` (K,) ns, which must lie in
    both spans; ``prior_mask`` (K,) bool: the nodes holding a ground-truth pose prior
    (default all; the others follow from the IMU between them). See the module docstring."""
    node_t = np.asarray(node_t, np.int64)
    p0, R0 = interpolate_poses(gt_t, gt_p, gt_q, node_t)
    poses = [gtsam.Pose3(gtsam.Rot3(R), p) for R, p in zip(R0, p0)]
    v0 = np.gradient(p0, node_t * 1e-9, axis=0) if len(node_t) > 1 else np.zeros((1, 3))
    params = combined_params(calib, noise)
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, rot_sigma_rad), np.full(3, pos_sigma_m)])
    g, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    zero = gtsam.imuBias.ConstantBias()
    mask = np.ones(len(poses), bool) if prior_mask is None else np.asarray(prior_mask, bool)
    n_pose = int(mask.sum())
    for i, T in enumerate(poses):
        if mask[i]:
            g.add(gtsam.PriorFactorPose3(X(i), T, prior))
        vals.insert(X(i), T)
        vals.insert(V(i), v0[i])
        vals.insert(B(i), zero)
    g.add(gtsam.PriorFactorConstantBias(B(0), zero, gtsam.noiseModel.Diagonal.Sigmas(
        np.r_[np.full(3, 0.5), np.full(3, 0.1)])))
    pkts = list(packets(imu, node_t))
    if len(pkts) != len(node_t) or np.any([q.t_ns for q in pkts] != node_t):
        raise ValueError("fuse_groundtruth: node times must be increasing and inside the IMU span")
    for i, pkt in enumerate(pkts[1:], start=1):
        pim = gtsam.PreintegratedCombinedMeasurements(params, zero)
        integrate(pim, pkt.imu)
        g.add(gtsam.CombinedImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i), pim))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(50)
    lm.setRelativeErrorTol(1e-6)
    res = gtsam.LevenbergMarquardtOptimizer(g, vals, lm).optimize()
    T = [res.atPose3(X(i)) for i in range(len(node_t))]
    p = np.array([x.translation() for x in T])
    q = np.array([x.rotation().toQuaternion().coeffs()[[3, 0, 1, 2]] for x in T])   # xyzw -> wxyz
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    b = [res.atConstantBias(B(i)) for i in range(len(node_t))]
    drot = np.array([np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(a).between(x.rotation())))
                     for a, x in zip(R0, T)])
    chi2 = np.array([2.0 * g.at(i).error(res) / g.at(i).dim() for i in range(g.size())])
    imu_rows = chi2[n_pose + 1:]            # after the pose priors and the bias prior
    return FusedTrajectory(node_t, p, q, np.array([res.atVector(V(i)) for i in range(len(node_t))]),
                           np.array([x.gyroscope() for x in b]), np.array([x.accelerometer() for x in b]),
                           float(np.sqrt(np.mean(np.sum((p - p0) ** 2, axis=1)))),
                           float(np.sqrt(np.mean(drot ** 2))),
                           float(imu_rows.mean()) if imu_rows.size else float("nan"),
                           float(chi2[:n_pose].mean()))
