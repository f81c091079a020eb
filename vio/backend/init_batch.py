"""The dynamic initialization's batch over its window, and the camera-IMU offset it prefers.

``add_landmarks`` puts the window's landmark factors (inlier observations, inverse depths
anchored in their first keyframe) into a graph; ``vio.backend.dynamic_init`` solves them
with the IMU factors in one Levenberg-Marquardt batch.

``batch_td`` refines the td remainder on that batch's cost. The visual pair rotations
(``vio.backend.td_init``) put the remainder within ~2.5-10 ms; the window's whole
visual-inertial batch pins it to ~1 ms, because a wrong offset cuts the IMU at the wrong
times and no state makes the IMU and the tracks agree. Generated MH_03 tracks from 65 s
into the flight, true td 25 ms with the sync layer at 0: the pair rotations (0.9 degrees
RMS off) give 20.3 ms; the batch cost at 20.3 / 22.8 / 25.3 / 27.8 / 30.3 ms is
277.1 / 266.7 / 263.4 / 266.8 / 276.6, minimum 25.2 ms (sigma 1.0 ms).

The cost at a shift ``s`` of the keyframe times: the batch solution re-solved (warm
started) with the IMU re-cut at ``t_k + s`` between the window's inner keyframes (the
first and last keyframes keep their landmark factors but no IMU factor, so that every
shift of up to one keyframe interval needs only IMU the buffer holds and all shifts are
compared on the same factors).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors.landmark import landmark_factor, make_track
from factors.robust import RobustKernel
from vio.backend.config import BackendConfig
from vio.backend.td_init import refine_minimum
from vio.imu import integrate
from vio.io.types import CameraCalib, ImuData

X, V, B, L = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B,
              gtsam.symbol_shorthand.L)
E = gtsam.symbol_shorthand.E(0)


@dataclass(frozen=True)
class WindowBatch:
    """A window's batch: the alignment ``vi`` (``vio.backend.vi_align.ViSolution``), its
    observations ``obs`` (``WindowObs``) and ``tracks`` (``window_tracks``), the batch
    solution ``est``, the keyframe times ``t_ns`` (K,) in the IMU clock it was solved at,
    and ``td_s``: the td remainder (s) those times are shifted by from the packets'."""

    vi: object
    obs: object
    tracks: dict
    est: gtsam.Values
    t_ns: tuple
    td_s: float = 0.0


def add_priors(g: gtsam.NonlinearFactorGraph, cam: CameraCalib, cfg: BackendConfig, T0: gtsam.Pose3,
               bias_key: int) -> None:
    """The batch's gauge and calibration priors: ``X(0)`` at ``T0`` (roll and pitch 0.1
    rad, yaw and position 1e-3), the IMU bias at ``bias_key`` about zero
    (``prior_accel_bias_sigma``, the dynamic ``gyro_bias_sigma``), the extrinsic held."""
    ic = cfg.init
    g.add(gtsam.PriorFactorPose3(X(0), T0, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([0.1, 0.1, 1e-3, 1e-3, 1e-3, 1e-3]))))
    g.add(gtsam.PriorFactorConstantBias(bias_key, gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(
        np.r_[np.full(3, ic.prior_accel_bias_sigma), np.full(3, ic.dynamic.gyro_bias_sigma)])))
    g.add(gtsam.PriorFactorPose3(E, cam.T_b_c, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))


def add_landmarks(g: gtsam.NonlinearFactorGraph, vals: gtsam.Values | None, cam: CameraCalib,
                  cfg: BackendConfig, vi, obs, tracks: dict) -> None:
    """One landmark factor per track with at least two inlier observations (``vi.mask``)
    and an inverse depth ``vi.rho`` within the vision bounds; its inverse depth inserted
    into ``vals`` (unless None). ``vi``: ``vio.backend.vi_align.ViSolution``; ``obs``:
    ``WindowObs``; ``tracks``: ``window_tracks``; keys ``X(k)``, ``L(id)``, ``E(0)``."""
    sigma = cfg.vision.pixel_sigma / cam.intrinsics[0]
    lo, hi = 1.0 / cfg.vision.max_depth_m, 1.0 / cfg.vision.min_depth_m
    for li, lid in enumerate(obs.ids):
        sel = (obs.lm == li) & vi.mask
        if sel.sum() < 2 or not lo < vi.rho[li] < hi:
            continue
        a, uva = tracks[lid][0]
        tr = make_track(X(a), uva, [X(int(j)) for j in obs.j[sel]], obs.uv[sel])
        g.add(landmark_factor(tr, L(lid), E, sigma, cfg.vision.model, RobustKernel("huber")))
        if vals is not None:
            vals.insert(L(lid), np.array([vi.rho[li]]))


def td_cost(cam: CameraCalib, cfg: BackendConfig, params, imu: ImuData, batch: WindowBatch,
            shift_s: float) -> float:
    """The window batch's cost (GTSAM error at its optimum) with the inner keyframes'
    IMU cut ``shift_s`` later than ``batch.t_ns`` (module docstring), re-solved from
    ``batch.est`` (its values of keys this graph lacks stay as they are). inf when the IMU
    does not cover the shifted times or LM fails."""
    K, d = len(batch.t_ns), int(round(shift_s * 1e9))
    if K < 5:
        return float("inf")
    t = [int(batch.t_ns[k]) + d for k in range(1, K - 1)]
    if t[0] < imu.t_ns[0] or t[-1] > imu.t_ns[-1]:
        return float("inf")
    g = gtsam.NonlinearFactorGraph()
    add_priors(g, cam, cfg, batch.est.atPose3(X(0)), B(1))
    for k in range(2, K - 1):
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
        integrate(pim, imu.segment(t[k - 2], t[k - 1]))
        g.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
    add_landmarks(g, None, cam, cfg, batch.vi, batch.obs, batch.tracks)
    try:
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(30)
        sol = gtsam.LevenbergMarquardtOptimizer(g, batch.est, lm).optimize()
    except RuntimeError:
        return float("inf")
    return float(g.error(sol))


def batch_td(cam: CameraCalib, cfg: BackendConfig, params, imu: ImuData, batch: WindowBatch,
             td0: float, center: float) -> tuple[float, float, float]:
    """The td that minimises :func:`td_cost`, walking ``TdSearchConfig.batch_step_s`` from
    ``center`` up to ``batch_range_s`` (``td_init.refine_minimum``); the batch was solved
    at ``td0``. Returns ``(td, sigma, drop)``: sigma (s) from the cost's curvature (the
    cost is a negative log-likelihood; inf when the minimum is not bracketed) and the cost
    drop against ``center``."""
    tc = cfg.init.dynamic.td
    td, a, drop = refine_minimum(lambda x: td_cost(cam, cfg, params, imu, batch, x - td0),
                                 center, tc.batch_step_s, tc.batch_range_s, bracket=True)
    return td, (1.0 / np.sqrt(2.0 * a) if a > 0 else float("inf")), drop
