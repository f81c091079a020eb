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

from vio.backend import graph, smoother
from vio.backend.config import InitConfig
from vio.backend.init import InitialState
from vio.errors import one_line

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
              "state (recovery #%d)", k1, one_line(exc), est.recoveries)
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


def recover_latest(est, exc: Exception, t_ns: int) -> None:
    """:func:`recover` at the newest keyframe from the smoother's latest state: a refused
    update after the keyframe's own (the held outlier update, a re-iteration)."""
    T, v, b = est.latest()
    recover(est, exc, est.k, est.k, gtsam.NavState(T, v), b, t_ns)


def check_health(est, t_ns: int, n_removed: int, f_imu: gtsam.CombinedImuFactor) -> None:
    """Soft restart (``vio.backend.health``) when the newest state is divergent: the
    current position kept (no jump), attitude, velocity and bias from the last healthy
    keyframe propagated with the IMU."""
    T, v, b = est.latest()
    chi2 = 2.0 * f_imu.error(est.values) if est.values.exists(X(est.k - 1)) else 0.0
    T_b_c = est.values.atPose3(graph.EXTRINSIC)
    td = float(est.values.atVector(graph.TD)[0])
    # a source's lost measurements (FactorSource.lost) are a divergence where they are the only
    # vision (direct mode): next to landmarks (hybrid) they are not. A right camera covered for
    # 2 s on real MH_01: hybrid 5.3 mm as is, 12.3 mm when its photometric loss restarted it
    n_lm = est.lm.n_active()
    lost = None if n_lm else next((r for r in (src.lost(est.k) for src in est.sources) if r is not None), None)
    reason = est.health.check(t_ns, T, v, b, est.pim, n_lm, n_removed, chi2, (T_b_c, td), lost)
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
    est.restart_state = state
    h = est.cfg.health
    init = dataclasses.replace(est.cfg.init, prior_rp_sigma=h.restart_rp_sigma,
                               prior_vel_sigma=h.restart_vel_sigma,
                               prior_accel_bias_sigma=h.restart_accel_bias_sigma,
                               prior_gyro_bias_sigma=h.restart_gyro_bias_sigma)
    fresh_window(est, est.k, state, T_b_c, td, None, init)


def reiterate(est, t_ns: int, f_imu: gtsam.NonlinearFactor) -> bool:
    """More iSAM2 iterations (``SolverConfig.reiterate_max``) after a keyframe's update whose
    newest IMU factor ``f_imu`` disagrees wildly with the result (whitened squared error
    above ``reiterate_chi2``, 15 dof: a clean window stays below ~10, the real sets below 7).
    iSAM2 takes one Gauss-Newton step per update; from a poor linearization point (new world
    points from short baselines) that step can overshoot, and the outlier check after it
    then empties the window. Generated V2_03 from 65 s (seed 13): one update moved all 61
    world points ~2 m towards the camera, IMU chi2 820; the check then rejected 61 of them,
    after 1 / 2 / 3 / 4 more iterations 50 / 26 / 13 / 3 (the states come back in one, the
    points more slowly: iSAM2 relinearizes a point once its step exceeds
    ``point_relinearize_threshold``). Not while bridged keyframes are in the window
    (``Estimator._after_update``): vision alone holds those, the window may be
    inconsistent, and more iterations moved the V1_01 take-off gaps both ways (3-s gap at
    4.0 s 0.093 -> 0.287 m, at 5.5 s 0.151 -> 0.124 m). A refused iteration rebuilds the
    smoother as a refused update does (QR, else a recovery restart: returns True)."""
    sc = est.cfg.solver
    if not sc.reiterate_chi2 > 0 or not est.values.exists(graph.X(est.k - 1)):
        return False
    chi0 = 2.0 * f_imu.error(est.values)
    if not chi0 > sc.reiterate_chi2:
        return False
    est.reiterations += 1
    for n in range(1, sc.reiterate_max + 1):
        try:
            smoother.update(est.smoother)
        except RuntimeError as exc:   # an update that raised leaves iSAM2 unusable: rebuilt
            log.warning("t=%d ns: re-iteration %d after keyframe %d refused (%s)", t_ns, n, est.k, one_line(exc))
            try:
                smoother.qr_resolve(est, gtsam.NonlinearFactorGraph(), exc)
                est.values = est.smoother.calculateEstimate()
            except RuntimeError as exc2:
                recover_latest(est, exc2, t_ns)
                return True
            return False
        est.values = est.smoother.calculateEstimate()
    log.warning("t=%d ns: keyframe %d's update left its IMU factor at chi2 %.0f: %d more "
                "iteration(s), chi2 %.1f", t_ns, est.k, chi0, sc.reiterate_max, 2.0 * f_imu.error(est.values))
    return False
