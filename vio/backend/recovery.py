"""Window restarts of an ``Estimator`` (``vio.backend.estimator``): after a solver failure
(``recover``), after a divergence (``check_health``, ``vio.backend.health``) and, through
``fresh_window``, the td re-anchoring (``vio.backend.td_reanchor``). Each forgets the
landmarks and the factor sources' state and starts a new smoother at one keyframe;
the output keeps going from the restart state.
"""

from __future__ import annotations

import dataclasses
import logging

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.config import InitConfig
from vio.backend.init import InitialState

log = logging.getLogger(__name__)
X = graph.X


def fresh_window(est, k: int, state: InitialState, T_b_c: gtsam.Pose3, td: float,
                 pose_sigmas: np.ndarray | None, init: InitConfig | None = None,
                 priors: gtsam.NonlinearFactorGraph | None = None) -> None:
    """Forget ``est``'s landmarks and sources' state, then ``est._restart`` (same arguments)."""
    est.lm.reset()
    for src in est.sources:
        src.reset()
    est._restart(k, state, T_b_c, td, pose_sigmas, init, priors)


def recover(est, exc: Exception, k0: int, k1: int, pred: gtsam.NavState,
            b0: gtsam.imuBias.ConstantBias, t_ns: int) -> None:
    """Restart the window from the last good state after a solver failure."""
    est.recoveries += 1
    log.error("solver failure at keyframe %d (%s): re-initializing from the last good "
              "state (recovery #%d)", k1, str(exc).splitlines()[0][:120], est.recoveries)
    good = est.values
    T_b_c = good.atPose3(graph.EXTRINSIC)
    td = float(good.atVector(graph.TD)[0])
    T, v, b = pred.pose(), pred.velocity(), b0
    sane = (np.all(np.isfinite(T.matrix())) and np.all(np.isfinite(v)) and np.all(np.isfinite(b.vector()))
            and np.linalg.norm(v) < 50.0 and np.linalg.norm(T.translation()) < 1e5)
    if not sane:   # the prediction blew up: hold still at the last good pose
        T, v, b = good.atPose3(X(k0)), np.zeros(3), gtsam.imuBias.ConstantBias()
    state = InitialState(t_ns, T, v, b, "recovery")
    sig = np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05])
    try:
        fresh_window(est, k1, state, T_b_c, td, sig)
    except RuntimeError:   # last resort: loose priors, zero velocity, calibration reset
        log.error("recovery restart refused by the solver; restarting with loose priors")
        state = InitialState(t_ns, T, np.zeros(3), gtsam.imuBias.ConstantBias(), "recovery")
        est._restart(k1, state, est.cam.T_b_c, est.td0, np.full(6, 0.1))


def check_health(est, t_ns: int, n_removed: int, f_imu: gtsam.CombinedImuFactor) -> None:
    """Soft restart (``vio.backend.health``) when the newest state is divergent: the
    current position kept (no jump), attitude, velocity and bias from the last healthy
    keyframe propagated with the IMU."""
    T, v, b = est.latest()
    chi2 = 2.0 * f_imu.error(est.values) if est.values.exists(X(est.k - 1)) else 0.0
    T_b_c = est.values.atPose3(graph.EXTRINSIC)
    td = float(est.values.atVector(graph.TD)[0])
    reason = est.health.check(t_ns, T, v, b, est.pim, est.lm.n_active(), n_removed, chi2, (T_b_c, td))
    if reason is None:
        return
    est.divergences += 1
    log.warning("t=%d ns (%.3f s after the start): divergence at keyframe %d (%s): soft "
                "restart at the current position, attitude and velocity of the last healthy "
                "keyframe propagated by the IMU (restart #%d)", t_ns,
                (t_ns - (est.t_start or t_ns)) * 1e-9, est.k, reason, est.divergences)
    fb = est.health.fallback()
    if fb is None:
        nav, b0 = gtsam.NavState(T, np.zeros(3)), gtsam.imuBias.ConstantBias()
        T_b_c, td = est.cam.T_b_c, est.td0
    else:
        nav, b0, (T_b_c, td) = fb
    p = T.translation() if np.all(np.isfinite(T.translation())) else nav.position()
    state = InitialState(t_ns, gtsam.Pose3(nav.attitude(), p), nav.velocity(), b0, "restart")
    h = est.cfg.health
    init = dataclasses.replace(est.cfg.init, prior_rp_sigma=h.restart_rp_sigma,
                               prior_vel_sigma=h.restart_vel_sigma,
                               prior_accel_bias_sigma=h.restart_accel_bias_sigma,
                               prior_gyro_bias_sigma=h.restart_gyro_bias_sigma)
    fresh_window(est, est.k, state, T_b_c, td, None, init)
