"""TrackFrame of each new keyframe against the previous one, for the photometric
``FactorSource`` (a mixin of ``vio.direct.source.PhotometricSource``; seed Algorithm 3,
step 2 of that module's docstring): its pose becomes X(k)'s initial guess where it
converged and agrees with the IMU prediction, its affine the guess of A(k); a failed or
IMU-contradicting alignment runs again without the IMU prior (``vio.direct.imu_check``).
Every run is kept in ``tracks`` (``TrackRecord``, the failure signal).

Where the run from the IMU prediction fails and the keyframe has feature observations of
the window's landmarks (hybrid mode), it runs again from their RANSAC PnP pose and the
lower RMSE wins (DSO's CoarseTracker tries several motion guesses the same way). After a
1-s camera gap on real MH_01 (frames 240-259 dropped) the IMU prediction is 67 mm off and
TrackFrame from it settles 63 mm off (RMSE 50); from the ground-truth pose it settles 10 mm
off (RMSE 31). Where that fails too over an interval longer than
``BridgeConfig.imu_check_ref_s``, six more runs start ``track_gate_m`` off the prediction
along each camera axis (:meth:`TrackFrameStep._around`): after a 2-s gap on real MH_01
(frames 150-189 dropped) hybrid's prediction was 80 mm off, TrackFrame from it ended at
RMSE 46.5, from one of the six at 21.0 (ATE 37.1 -> 4.4 mm). Over such an interval the IMU gate (``PointsConfig.track_gate_m``) and the
test for a contradicted IMU widen with the prediction's own error
(``vio.backend.bridge.long_interval``)."""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from factors.photometric_shutter import Shutter
from vio.backend.bridge import contradicts, locate, long_interval, within_hold
from vio.backend.graph import A, B, X
from vio.direct.coarse_ref import keyframe_reference
from vio.direct.imu_check import free_alignment, pose_offset, window_guess
from vio.direct.keyframe import KeyframeData
from vio.direct.records import TrackRecord
from vio.direct.trackframe import MotionPrior, body_pose, track_frame

log = logging.getLogger(__name__)

AROUND_MARGIN = 0.75
"""RMSE ratio a start off the IMU prediction must beat (:meth:`TrackFrameStep._around`)."""


class TrackFrameStep:
    """The host class provides ``est`` (the estimator), ``rig``, ``cfg`` (``DirectConfig``),
    ``kfs`` (keyframe -> ``KeyframeData``), ``tracks``, ``contradicted_k``,
    ``_latest_in_graph``, ``live_points``, ``_twist``, ``_cam_twist`` and ``features`` (the
    newest keyframe's ``FeatureFrame`` or None)."""

    def _track(self, k: int, kd: KeyframeData, pred: gtsam.NavState, v: gtsam.Values) -> np.ndarray:
        """TrackFrame of keyframe k against the previous keyframe; the guess of A(k)."""
        prev = self._latest_in_graph(k)
        if prev is None:
            return np.zeros(2)
        vals, T_b_c, pc = self.est.values, self.rig.T_b_c, self.cfg.points
        ab_p = np.asarray(vals.atVector(A(prev.k)), float)
        if not self.cfg.track.enabled:
            return ab_p
        T_w_cp = vals.atPose3(X(prev.k)).compose(T_b_c)
        T_pred = v.atPose3(X(k))
        T_init = T_w_cp.between(T_pred.compose(T_b_c))
        dt_ns = kd.t_ns - prev.t_ns
        held = within_hold(self.est, kd.t_ns)      # the IMU is suspect: neither its guess nor its prior
        if held:
            T_init = window_guess(self.kfs, vals, prev, T_w_cp, T_b_c, kd.t_ns) or T_init
        prior = None if held else MotionPrior.from_imu(T_init, self.est.pim, dt_ns * 1e-9, self.cfg.track)
        t0 = time.perf_counter()
        ref = self._reference(prev, ab_p, T_w_cp)
        sh = self._track_shutter(k, prev, pred, v)
        try:
            res = track_frame(ref, kd.pyramid(self.cfg.track.levels), T_init, ab_p, self.cfg.track, prior, sh)
        except (ArithmeticError, np.linalg.LinAlgError) as exc:   # a numerical failure is a failure
            res = None
            log.warning("TrackFrame failed at keyframe %d (%s: %s); IMU prediction kept", k,
                        type(exc).__name__, exc)
        if res is None or not res.ok:
            res = self._from_features(k, kd, T_w_cp, T_init, ab_p, ref, prior, sh, res)
        if (res is None or not res.ok) and dt_ns * 1e-9 > self.est.cfg.bridge.imu_check_ref_s:
            res = self._around(k, kd, T_init, ab_p, ref, prior, sh, res)
        ms = (time.perf_counter() - t0) * 1e3
        # held, the run above was already the prior-free one from the visual guess
        if (res is None or not res.ok) and self.cfg.track.retry_visual and not held:
            ab = self._retry(k, kd, prev, ab_p, T_w_cp, v, ref, sh)
            if ab is not None:
                self._release(kd)
                return ab
        if res is None:
            self._release(kd)
            self.tracks.append(TrackRecord(k, kd.t_ns, float("inf"), False, False, float("nan"), float("nan"), ms))
            return ab_p
        T_tr = body_pose(T_w_cp, res.T_kf_new, T_b_c)
        dist, ang = pose_offset(T_pred, T_tr)
        gate_m = pc.track_gate_m * long_interval(self.est.cfg.bridge, dt_ns * 1e-9)
        used = bool(res.ok and pc.use_track_guess and dist <= gate_m and ang <= pc.track_gate_rad)
        if res.ok and self.cfg.track.retry_visual and self._contradicts(k, dist, ang, dt_ns, held):
            used = True      # converged against the IMU prior, and still away from the prediction
            free = None if held else free_alignment(self.cfg, self.kfs, vals, prev, kd, T_w_cp, T_b_c, ab_p,
                                                    ref, sh)
            if free is not None and free[0].rmse <= res.rmse:   # the prior is the contradicted IMU (imu_check)
                res, T_tr = free
                dist, ang = pose_offset(T_pred, T_tr)
                if not contradicts(self.est.cfg.bridge, dist, ang, dt_ns * 1e-9):
                    self.contradicted_k = None   # without the prior, vision agrees with the IMU
        self._release(kd)
        if used:
            v.update(X(k), T_tr)
        ms = (time.perf_counter() - t0) * 1e3      # with the prior-free run, where there was one
        self.tracks.append(TrackRecord(k, kd.t_ns, res.rmse, res.ok, used, dist, ang, ms))
        if not res.ok:
            log.warning("TrackFrame failed at keyframe %d: rmse %.1f (IMU prediction kept)", k, res.rmse)
        return np.array([res.a, res.b]) if res.ok else ab_p

    def _attempt(self, ref, kd: KeyframeData, guess: gtsam.Pose3, ab_p: np.ndarray, prior,
                 shutter: Shutter | None):
        """TrackFrame of ``kd`` from one more start ``guess`` (``T_kf_new``); None where it
        fails numerically (a second guess that cannot be computed is no guess)."""
        try:
            return track_frame(ref, kd.pyramid(self.cfg.track.levels), guess, ab_p, self.cfg.track, prior, shutter)
        except (ArithmeticError, np.linalg.LinAlgError):
            return None

    def _from_features(self, k: int, kd: KeyframeData, T_w_cp: gtsam.Pose3, T_init: gtsam.Pose3,
                       ab_p: np.ndarray, ref, prior, shutter: Shutter | None, res):
        """TrackFrame of keyframe k from the RANSAC PnP pose of its feature observations of
        the window's landmarks (module docstring), returned where it ends with a lower RMSE
        than ``res`` (the run from the IMU prediction ``T_init``, None: it raised); else ``res``."""
        fr, est = self.features, self.est
        if fr is None or fr.t_ns != kd.t_ns or len(fr.ids) == 0:
            return res
        ids, pts = est.check_points()
        bc = est.cfg.bridge
        if len(ids) < bc.pnp_min_inliers:
            return res
        T_b_c = self.rig.T_b_c
        T_pred = T_w_cp.compose(T_init).compose(T_b_c.inverse())
        T, _ = locate(ids, pts, fr, T_pred, T_b_c, est.cfg.vision.outlier_px / est.cam.intrinsics[0],
                      bc.pnp_min_inliers)
        if T is None:
            return res
        alt = self._attempt(ref, kd, T_w_cp.between(T.compose(T_b_c)), ab_p, prior, shutter)
        if alt is None or (res is not None and not alt.rmse < res.rmse):
            return res
        dist, ang = pose_offset(T_pred, T)
        log.info("keyframe %d: TrackFrame from the features' PnP pose (%.3f m / %.2f deg from the IMU "
                 "prediction): rmse %.1f against %s from the prediction", k, dist, np.degrees(ang), alt.rmse,
                 "a failure" if res is None else f"{res.rmse:.1f}")
        return alt

    def _around(self, k: int, kd: KeyframeData, T_init: gtsam.Pose3, ab_p: np.ndarray, ref, prior,
                shutter: Shutter | None, res):
        """After a failed TrackFrame over a long interval (a camera gap, the IMU prediction
        ``T_init`` several cm off): six more runs from ``T_init`` moved by
        ``PointsConfig.track_gate_m`` along each camera axis; the lowest RMSE is kept where
        it is below ``AROUND_MARGIN`` times ``res``'s (DSO's CoarseTracker tries several
        motion guesses the same way). A start off the prediction must explain the images
        clearly better: after a 1-s gap from real MH_01 frame 280 one reached RMSE 32.4
        against the prediction's 40.5 at 60 mm from the truth (the ground truth's pose: 36.5),
        and hybrid's ATE went 9.6 -> 13.1 mm."""
        best, d = res, self.cfg.points.track_gate_m
        limit = np.inf if res is None else AROUND_MARGIN * res.rmse
        for step in np.vstack([np.eye(3), -np.eye(3)]) * d:
            alt = self._attempt(ref, kd, gtsam.Pose3(T_init.rotation(), T_init.translation() + step), ab_p,
                                prior, shutter)
            if alt is not None and alt.rmse < limit and (best is res or alt.rmse < best.rmse):
                best = alt
        if best is not res:
            log.info("keyframe %d: TrackFrame from a start %.0f mm off the IMU prediction: rmse %.1f against %s",
                     k, d * 1e3, best.rmse, "a failure" if res is None else f"{res.rmse:.1f}")
        return best

    def _retry(self, k: int, kd: KeyframeData, prev: KeyframeData, ab_p: np.ndarray, T_w_cp: gtsam.Pose3,
               v: gtsam.Values, ref, shutter: Shutter | None = None) -> np.ndarray | None:
        """After a failed TrackFrame: once more without the IMU prior from the visual guess
        (``vio.direct.imu_check``). Where it converges as ``bridge.contradicts`` says (3 cm from
        the IMU prediction, within 1 degree), the IMU is contradicted: its pose becomes
        X(k)'s guess and the affine guess of A(k) is returned; else None."""
        t0 = time.perf_counter()
        free = free_alignment(self.cfg, self.kfs, self.est.values, prev, kd, T_w_cp, self.rig.T_b_c, ab_p, ref,
                              shutter) \
            if self.est.cfg.bridge.imu_check else None
        if free is None:
            return None
        res, T_tr = free
        dist, ang = pose_offset(v.atPose3(X(k)), T_tr)
        if not self._contradicts(k, dist, ang, kd.t_ns - prev.t_ns, False):
            return None
        v.update(X(k), T_tr)
        self.tracks.append(TrackRecord(k, kd.t_ns, res.rmse, True, True, dist, ang, (time.perf_counter() - t0) * 1e3))
        return np.array([res.a, res.b])

    def _track_shutter(self, k: int, prev: KeyframeData, pred: gtsam.NavState, v: gtsam.Values) -> Shutter | None:
        """TrackFrame's rolling shutter of keyframe k against ``prev``: cam0's line time, the
        camera twists of ``prev`` (kept at its insertion) and of k (from the prediction);
        None for a global shutter."""
        lt = float(self.rig.cam0.line_time_s)
        if lt <= 0.0:
            return None
        tw_k = self._twist(k, v.atPose3(X(k)), pred.velocity(), v.atConstantBias(B(k)))
        return Shutter(lt, self._cam_twist(prev.k), self.rig.T_b_c.inverse().AdjointMap() @ tw_k,
                       self.rig.rows0, self.rig.rows0)

    def _reference(self, prev: KeyframeData, ab: np.ndarray, T_w_cp: gtsam.Pose3):
        """TrackFrame's reference of ``prev`` (camera ``T_w_cp``, affine ``ab``): its own
        points and the window's (``vio.direct.coarse_ref``, ``TrackConfig.window_cell_px``)."""
        if self.cfg.track.window_cell_px <= 0:
            return prev.reference(ab, self.cfg)
        lt = float(self.rig.cam0.line_time_s)
        rows = self.rig.rows0
        shutter_of = (lambda h: Shutter(lt, self._cam_twist(h), self._cam_twist(prev.k), rows, rows)) \
            if lt > 0.0 else None
        return keyframe_reference(prev, ab, T_w_cp, self.live_points(), self.est.values, self.rig.T_b_c,
                                  self.cfg.track, shutter_of)

    def _release(self, kd: KeyframeData) -> None:
        """Drop keyframe ``kd``'s coarse pyramid levels after its TrackFrame; with the
        window's points it is the next reference image (``_reference`` drops them then)."""
        if self.cfg.track.window_cell_px <= 0:
            kd.release_pyramid()      # its own reference (built by the keyframe worker) is kept

    def _contradicts(self, k: int, dist: float, ang: float, dt_ns: int, held: bool) -> bool:
        """:func:`vio.backend.bridge.contradicts` for keyframe k's converged TrackFrame,
        ``dist`` m / ``ang`` rad from the IMU prediction over ``dt_ns``, ``held``: within the
        IMU hold; recorded for :meth:`imu_contradicted`."""
        if not contradicts(self.est.cfg.bridge, dist, ang, dt_ns * 1e-9, held):
            return False
        self.contradicted_k = k
        log.info("keyframe %d: TrackFrame converged %.3f m / %.2f deg from the IMU prediction over %.2f s",
                 k, dist, np.degrees(ang), dt_ns * 1e-9)
        return True

    def imu_contradicted(self, k: int) -> bool:
        """Whether keyframe k's TrackFrame contradicted the IMU prediction (:meth:`_retry`)."""
        return self.contradicted_k == k
