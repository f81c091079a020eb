"""The backend facade: a fixed-lag iSAM2 smoother over keyframe states, IMU and
landmark factors.

The smoother's ``Values`` is the only copy of the estimator state; ``Track``
objects hold measurements and graph bookkeeping. Landmarks are inverse depths
anchored in their first keyframe of the window. A live landmark whose anchor is
about to be marginalized is re-anchored (new key in the next observing keyframe,
observations of the leaving keyframe dropped); a landmark that is no longer
observed is marginalized together with its anchor so its information stays in
the smoother's marginal prior.
"""

from __future__ import annotations

import logging
from typing import Any

import gtsam
import numpy as np

from vio.backend import bridge, graph, padding, recovery, smoother
from vio.backend.config import BackendConfig, InitConfig
from vio.backend.health import HealthMonitor
from vio.backend.init import InitialState
from vio.backend.estimator_outputs import EstimatorOutputs
from vio.backend.keyframe_api import FactorSource, KeyframeResult
from vio.backend.gauge import GaugeAnchor
from vio.backend.outlier_carry import OutlierCarry
from vio.backend.realign import GapRealign
from vio.backend.regauge import ScaleRefiner
from vio.backend.td_reanchor import maybe_reanchor_td
from vio.backend.bundles import EliminatedLandmarks
from vio.backend.tracks import LandmarkManager
from vio.imu import KeyframeRates, bridge_params, combined_params, integrate, integrate_still
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib, ImuData

log = logging.getLogger(__name__)
X, V, B = graph.X, graph.V, graph.B


class Estimator(EstimatorOutputs):
    """Fixed-lag VIO backend. Call ``initialize``, then per frame ``add_imu`` and, for
    keyframes, ``add_keyframe``; ``predict`` gives the IMU-propagated current state."""

    def __init__(self, imu_calib: ImuCalib, cam: CameraCalib, cfg: BackendConfig,
                 td0_s: float = 0.0, cam1: CameraCalib | None = None) -> None:
        self.cfg = cfg
        self.cam = cam
        # stereo rig (fixed): cam1 relative to cam0, and C = T_b_c1 T_b_c0^-1
        self.T_c0_c1 = cam.T_b_c.between(cam1.T_b_c) if cam1 is not None else None
        self.C_stereo = cam1.T_b_c.compose(cam.T_b_c.inverse()) if cam1 is not None else None
        self.params = combined_params(imu_calib, cfg.imu)
        self.bridge_params = bridge_params(imu_calib, cfg.imu, cfg.bridge.accel_density,
                                           cfg.bridge.gyro_density)
        self._bridge_t: int | None = None   # bridging an IMU gap: synthetic readings up to here
        w = cfg.imu.scale_walk
        self.bias_walk = np.r_[np.full(3, w * imu_calib.accel_random_walk), np.full(3, w * imu_calib.gyro_random_walk)]
        self.health = HealthMonitor(
            cfg.health, np.r_[np.full(3, cfg.init.prior_accel_bias_sigma), np.full(3, cfg.init.prior_gyro_bias_sigma)],
            self.bias_walk)
        self.bridged = 0          # keyframe intervals bridged across IMU gaps
        self.realigned = 0        # gravity re-alignments after a gap (vio.backend.realign)
        self.divergences = 0      # soft restarts after a divergence
        self.imu_contradictions = 0   # keyframe intervals whose IMU vision contradicted (bridged)
        self.frame_contradictions = 0  # frames between keyframes output at their PnP pose instead
        self._frame_points: tuple = (None, None)   # (the values they were computed at, frame_points())
        self.contradicted_k: int | None = None   # the last keyframe such an interval ended at
        self.contradicted_t: int | None = None   # and its time (ns; BridgeConfig.imu_check_hold_s)
        self.check_fired_t: int | None = None    # the landmark check's last firing (ns)
        self.restart_state: InitialState | None = None   # the last soft restart's state (vio.reinit)
        self.td_reanchors = 0     # restarts at a fed-back td (CalibConfig.td_reanchor_s)
        self.reiterations = 0     # updates iterated again (SolverConfig.reiterate_chi2)
        self._td_anchor = 0.0     # the td its keyframe time held at the last (re)start (s)
        self.t_start: int | None = None
        self.sigma = cfg.vision.pixel_sigma / cam.intrinsics[0]
        self.td0 = 0.0  # residual td prior mean (the sync layer applies td0_s)
        self.td_applied_s = td0_s
        self.lm = (EliminatedLandmarks if cfg.vision.eliminate_depth else LandmarkManager)(self)
        self.values = gtsam.Values()
        self.k = -1
        self.kf_t: dict[int, int] = {}
        self.still_kf: set[int] = set()   # keyframes the pipeline flagged still (no td term)
        self.bridged_kf: set[int] = set()  # window keyframes reached by an IMU-gap bridge
        self.rates = KeyframeRates()
        self.recoveries = 0
        self.smoother: gtsam.IncrementalFixedLagSmoother | None = None
        self.smoother_factorization = cfg.solver.factorization   # QR after a re-solve (vio.backend.smoother)
        self.qr_since: int | None = None
        self.qr_key: int | None = None  # the variable of that refusal (vio.backend.smoother)
        self.qr_resolves = 0
        self.point_holds = 0   # Cholesky refusals repaired by holding a world point (vio.backend.smoother)
        self.n_pad = 0      # padding keys in the smoother (vio.backend.padding)
        self.pim: gtsam.PreintegratedCombinedMeasurements | None = None
        self.sources: list[FactorSource] = []
        self.refiner = ScaleRefiner(cfg.refine, np.asarray(self.params.n_gravity, float))
        self.realign = GapRealign(cfg.realign, np.asarray(self.params.n_gravity, float))
        self.gauge = GaugeAnchor(cfg.gauge)   # position and yaw held in the window (vio.backend.gauge)
        self.carry = OutlierCarry()           # SolverConfig.outlier_update "next_frame"
        self._after: tuple | None = None      # SolverConfig.bookkeeping "next_frame"

    # ------------------------------------------------------------------ setup
    def _new_smoother(self, factorization: str | None = None) -> gtsam.IncrementalFixedLagSmoother:
        extra = {ch: d for src in self.sources for ch, d in src.key_dims.items()}
        own = {ch: th for src in self.sources for ch, th in src.key_thresholds.items()}
        return smoother.make(self.cfg.solver, extra, factorization, own)

    @property
    def home_factorization(self) -> str:
        return self.cfg.solver.factorization

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild (``vio.backend.smoother``): old -> new factor slots."""
        self.lm.remap_factor_indices(remap)
        self.gauge.remap_factor_indices(remap)
        self.carry.remap(remap)
        for src in self.sources:
            src.remap_factor_indices(remap)

    def initialize(self, state: InitialState, T_b_c: gtsam.Pose3 | None = None,
                   td_s: float | None = None) -> None:
        """Start the window at ``state`` (keyframe 0); td: ``td_s``, else the state's
        (an initializer's finding), else the residual prior mean."""
        td = td_s if td_s is not None else (state.td_s if state.td_s is not None else self.td0)
        self._restart(0, state, self.cam.T_b_c if T_b_c is None else T_b_c, td, None)
        if state.method == "static":    # a still start: its images carry no timing information
            self.still_kf.add(0)

    def first_keyframe(self, frame) -> None:
        """Keyframe 0's time and raw gyro reading (``KeyframeRates``) from its packet
        ``frame`` (``vio.sync.FramePacket``), with the td its time holds (:meth:`td_obs`:
        non-zero for a window replayed at its found td, ``vio.init_retime``, or a
        re-initialization after td feedback); td re-anchoring counts from there."""
        self.rates.add_keyframe(0, frame.t_ns, frame.imu.gyro[-1], self.td_obs(frame))
        self._td_anchor = self.rates.td_obs(0)

    def _restart(self, k: int, state: InitialState, T_b_c: gtsam.Pose3, td: float,
                 pose_sigmas: np.ndarray | None, init: InitConfig | None = None,
                 priors: gtsam.NonlinearFactorGraph | None = None) -> None:
        """A fresh smoother holding keyframe ``k`` at ``state`` with priors, extrinsic and td
        (``init``: the prior sigmas, default ``cfg.init``; ``priors``: the state's priors
        instead)."""
        self.smoother = self._new_smoother()
        self.smoother_factorization, self.qr_since = self.cfg.solver.factorization, None
        self.n_pad = 0
        self.carry.clear()
        self._after = None
        self.t_start = state.t_ns if self.t_start is None else self.t_start
        self._bridge_t = None
        self.health.reset(state.t_ns, state.bias)
        self.refiner.reset()
        self.realign.reset()
        self.k = k
        self.kf_t = {k: state.t_ns}
        self.still_kf = set()
        self.bridged_kf = set()
        self.rates.reset_to(k)
        self.gauge.reset(k)
        self._td_anchor = self.rates.td_obs(k)
        g = priors if priors is not None else graph.state_priors(
            k, state, self.cfg.init if init is None else init, pose_sigmas)
        g.push_back(graph.calib_priors(T_b_c, td, self.cfg.calib))
        v = gtsam.Values()
        v.insert(X(k), state.T_w_b)
        v.insert(V(k), state.v_w)
        v.insert(B(k), state.bias)
        v.insert(graph.EXTRINSIC, T_b_c)
        v.insert(graph.TD, np.array([td]))
        t = state.t_ns * 1e-9
        smoother.update(self.smoother, g, v, {X(k): t, V(k): t, B(k): t, graph.EXTRINSIC: t, graph.TD: t})
        self.values = self.smoother.calculateEstimate()
        self.pim = gtsam.PreintegratedCombinedMeasurements(self.params, state.bias)

    @property
    def initialized(self) -> bool:
        return self.smoother is not None

    # --------------------------------------------------------------- per frame
    def add_imu(self, seg: ImuData, ahead: ImuData | None = None, gap: bool = False) -> None:
        """Preintegrate a packet's IMU segment (since the previous frame); ``ahead``:
        samples past the frame, kept for the td term only (``vio.sync`` lookahead).
        ``gap``: the segment touches an IMU gap (``FramePacket.imu_gaps``): nothing is
        preintegrated across it; the whole interval since the last keyframe becomes a
        bridge (``BridgeConfig``: constant velocity and attitude with growing sigmas, bias
        random walk) until the next keyframe, after which IMU factors resume."""
        self.finish_keyframe()
        self.rates.add_imu(seg)
        if ahead is not None:
            self.rates.add_imu(ahead)
        if gap and self._bridge_t is None:
            self.pim = gtsam.PreintegratedCombinedMeasurements(self.bridge_params, self.latest()[2])
            self._bridge_t = self.kf_t[self.k]
        if self._bridge_t is None:
            integrate(self.pim, seg)
            return
        T, _, b = self.latest()
        t1 = int(seg.t_ns[-1])
        integrate_still(self.pim, T.rotation(), b, self.cfg.imu.gravity, (t1 - self._bridge_t) * 1e-9,
                        self.cfg.bridge.step_s)
        self._bridge_t = max(self._bridge_t, t1)

    def prefetch(self, t_ns: int) -> None:
        """Between keyframes, after the frame at ``t_ns`` has its output: the world points'
        farewell factors of the keyframes already past the lag, which the next keyframe
        (later than ``t_ns``) drops whatever its time; its update then finds them built
        (``PointTracks.prefetch``; the same factors, so the same result)."""
        if self.smoother is None or not self.lm.points.tracks:
            return
        leave = set(self._leaving(t_ns * 1e-9))
        if leave:
            self.lm.points.prefetch(leave)

    def _leaving(self, t_s: float) -> list[int]:
        """The window's keyframes a keyframe at ``t_s`` (s) drops: at least ``lag_s`` old."""
        return [k for k, tk in self.kf_t.items() if t_s - tk * 1e-9 >= self.cfg.solver.lag_s - 1e-9]

    def latest(self) -> tuple[gtsam.Pose3, np.ndarray, gtsam.imuBias.ConstantBias]:
        """Estimate of the newest keyframe."""
        return (self.values.atPose3(X(self.k)), self.values.atVector(V(self.k)),
                self.values.atConstantBias(B(self.k)))

    def predict(self) -> gtsam.NavState:
        """Current state: the newest keyframe propagated with the IMU since."""
        self.finish_keyframe()
        T, v, b = self.latest()
        return self.pim.predict(gtsam.NavState(T, v), b)

    def frame_state(self, features: FeatureFrame | None, gyro: np.ndarray | None, frame: Any = None) -> gtsam.NavState:
        """A frame between keyframes (``features``, raw ``gyro``, the packet as for
        :meth:`add_keyframe`): :meth:`predict`, unless vision contradicts it
        (:func:`vio.backend.bridge.frame_state`)."""
        pred = self.predict()
        shift = bridge.exposure_shift(self, pred, self.latest()[2], gyro, frame, features)
        return bridge.frame_state(self, features, pred, shift)

    def add_keyframe(self, t_ns: int, features: FeatureFrame, still: bool = False,
                     gyro: np.ndarray | None = None, frame: Any = None) -> KeyframeResult:
        """Insert a keyframe at ``t_ns`` with the IMU integrated since the last one.
        ``gyro``: the raw gyro reading (rad/s, body) at ``t_ns``, for predicted
        feature velocities (see ``vio.imu.KeyframeRates``);
        ``frame``: the pipeline's packet, passed to ``sources``."""
        self.flush_outliers()
        smoother.maybe_back_to_cholesky(self)    # before any factor slot is read
        k0, k1 = self.k, self.k + 1
        div0 = self.divergences
        pred = self.predict()
        _, v0, b0 = self.latest()
        shift = bridge.exposure_shift(self, pred, b0, gyro, frame, features)
        T_pnp = bridge.imu_contradicted(self, features, pred, shift) if self._bridge_t is None else None
        hold = T_pnp is not None or bridge.imu_held(self, t_ns)
        if hold:                   # the velocity the motion prior carries on
            pred = gtsam.NavState(pred.pose() if T_pnp is None else T_pnp, v0)
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        fs, held = bridge.motion_factors(self, k0, k1, t_ns, hold)
        f_imu = fs[0]
        for f in fs:
            g.add(f)
        if still:
            g.add(graph.zero_velocity(k1, self.cfg.init.zupt_sigma))
            self.still_kf.add(k1)
        if held:
            self.bridged_kf.add(k1)
        if self.bridged_kf and self.cfg.bridge.pnp_gate:   # bridged states in the window: vision holds them
            pred, features = bridge.gate_bridged(self, features, pred, keep_pose=not held)
        v.insert(X(k1), pred.pose())
        v.insert(V(k1), pred.velocity())
        v.insert(B(k1), b0)
        t = t_ns * 1e-9
        stamps = {X(k1): t, V(k1): t, B(k1): t, graph.EXTRINSIC: t, graph.TD: t}
        self.k = k1
        self.kf_t[k1] = t_ns
        td_obs = self.td_obs(frame)
        if gyro is not None:
            self.rates.add_keyframe(k1, t_ns, gyro, td_obs)
        self.lm.observe(k1, features)
        leaving = self._leaving(t)
        removals = self.lm.prepare_update(k1, pred, leaving, g, v, stamps)
        removals += self.gauge.prepare_update(
            sorted(self.kf_t), leaving, lambda k: v.atPose3(X(k)) if v.exists(X(k)) else self.values.atPose3(X(k)),
            X, g)
        for src in self.sources:
            src.observe(k1, frame)
            removals += src.prepare_update(k1, pred, leaving, g, v, stamps)
        if any(src.imu_contradicted(k1) for src in self.sources):
            if not held:
                f_imu, held = bridge.replace_imu_factor(self, g, k0, k1, t_ns)[0], True
                self.bridged_kf.add(k1)
                v.update(V(k1), v0)
            elif hold:
                self.contradicted_t = t_ns        # the hold goes on from here
        recovered = False
        try:
            self._update(g, v, stamps, removals)
        except RuntimeError as exc:
            recovery.recover(self, exc, k0, k1, pred, b0, t_ns)
            recovered = True
        self._after = (k0, k1, t_ns, leaving, recovered, div0, held, features, f_imu)
        n_removed = 0 if self.cfg.solver.bookkeeping == "next_frame" else self.finish_keyframe()
        T, vel, bias = self.latest()
        return KeyframeResult(k1, t_ns, T, vel, bias, self.lm.n_active(), n_removed, recovered)

    def finish_keyframe(self) -> int:
        """The last keyframe's bookkeeping (:meth:`_after_update`), then a fresh
        preintegration at its bias, if it is still to run (``SolverConfig.bookkeeping``:
        ``add_imu``, ``predict`` and ``flush_outliers`` call this first). Returns the
        landmarks its outlier check rejected."""
        if self._after is None:
            return 0
        after, self._after = self._after, None
        n_removed = self._after_update(*after)
        self.pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.latest()[2])
        return n_removed

    def _after_update(self, k0: int, k1: int, t_ns: int, leaving: list[int], recovered: bool,
                      div0: int, held: bool, features: FeatureFrame, f_imu) -> int:
        """A keyframe's bookkeeping after its update: the leaving keyframes forgotten, more
        iterations after an overshooting update, the outlier check, the health check, the
        scale refinement, the gravity re-alignment and td re-anchoring (each skipped once a
        recovery or restart replaced the window).
        Returns the number of landmarks the outlier check rejected."""
        for k in leaving:
            self.kf_t.pop(k, None)
            self.still_kf.discard(k)
            self.bridged_kf.discard(k)
            self.rates.drop(k)
        if not (recovered or held or self.bridged_kf):   # an overshooting Gauss-Newton step
            recovered = recovery.reiterate(self, t_ns, f_imu)   # (SolverConfig.reiterate_chi2)
        n_removed = 0 if recovered else self._remove_outliers()
        if not recovered and self.k == k1:
            recovery.check_health(self, t_ns, n_removed, f_imu)
        if not recovered and self.k == k1 and self.divergences == div0:
            self.refiner.keyframe(self, k0, k1, t_ns, self.pim, held, features)
            self.realign.step(self, t_ns)
        if not recovered and self.k == k1:
            maybe_reanchor_td(self)
        return n_removed

    def _update(self, g, v, stamps, removals) -> None:
        padding.pad(self, g, v, stamps)
        try:
            smoother.update(self.smoother, g, v, stamps, removals)
            indices = list(self.smoother.getISAM2Result().getNewFactorsIndices())
        except RuntimeError as exc:   # re-raised unless a Cholesky refusal QR can take
            indices = smoother.qr_resolve(self, g, exc)
        self.lm.record_factor_indices(indices)
        self.gauge.record_factor_indices(indices)
        for src in self.sources:
            src.record_factor_indices(indices)
        for _ in range(self.cfg.solver.extra_iterations):
            smoother.update(self.smoother)
        self.values = self.smoother.calculateEstimate()

    def _remove_outliers(self) -> int:
        """Reject this keyframe's outlier landmarks; their update runs now or is held
        for the next frame (``SolverConfig.outlier_update``). Returns how many."""
        n = self.carry.hold(*self.lm.outlier_removals(self.values))
        if self.cfg.solver.outlier_update == "now":
            self.flush_outliers()
        return n

    def flush_outliers(self) -> None:
        """Run the outlier update the last keyframe held (``vio.backend.outlier_carry``)."""
        self.finish_keyframe()
        held = self.carry.take(self.smoother) if self.smoother is not None else None
        try:
            if held is not None:
                self.lm.arm(held[0])
                self._update(held[0], gtsam.Values(), held[1], held[2])
        except RuntimeError as exc:
            recovery.recover_latest(self, exc, self.kf_t[self.k])
