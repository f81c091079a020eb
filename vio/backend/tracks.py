"""Landmark life cycle inside the fixed-lag window.

Per keyframe: new observations are appended; a track enters the graph once its
depth can be triangulated (or it has waited long enough); its factor is rebuilt
whenever it gains an observation; live tracks are re-anchored before their
anchor is marginalized; dead tracks are marginalized with their anchor; tracks
with large reprojection errors or non-positive depth are removed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.landmarks import Obs, Track, bearing_depth, stereo_depth
from vio.io.types import FeatureFrame

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

WEAK = gtsam.noiseModel.Isotropic.Sigma(1, 10.0)


class LandmarkManager:
    """Owns the ``Track`` table of an ``Estimator``."""

    def __init__(self, est: "Estimator") -> None:
        self.est = est
        self.tracks: dict[int, Track] = {}
        self.rejected: set[int] = set()
        self._next_key = 0
        self._pending: list[tuple[Track, int]] = []
        self._motion_cache: dict = {}

    # ------------------------------------------------------------ bookkeeping
    def observe(self, k: int, fr: FeatureFrame) -> None:
        right = fr.right_uv if fr.right_uv is not None else np.full((len(fr.ids), 2), np.nan)
        rvel = fr.right_velocity if fr.right_velocity is not None else np.zeros((len(fr.ids), 2))
        for lid, uv, vel, row, ruv, rv in zip(fr.ids, fr.uv, fr.velocity, fr.row, right, rvel):
            lid = int(lid)
            if lid in self.rejected:
                continue
            tr = self.tracks.setdefault(lid, Track(lid))
            has_r = bool(np.all(np.isfinite(ruv)))
            tr.obs[k] = Obs(np.asarray(uv, float), np.asarray(vel, float), float(row),
                            np.asarray(ruv, float) if has_r else None,
                            np.asarray(rv, float) if has_r else None)

    def n_active(self) -> int:
        return sum(1 for t in self.tracks.values() if t.key is not None)

    def reset(self) -> None:
        """After a solver restart: forget keys and factors, keep the newest observations."""
        k = self.est.k
        for tr in self.tracks.values():
            tr.key = tr.anchor = None
            tr.factor_indices = []
            tr.obs = {f: o for f, o in tr.obs.items() if f == k}
            tr.waited = 0
        self.tracks = {i: t for i, t in self.tracks.items() if t.obs}
        self._pending = []

    def _new_key(self) -> int:
        self._next_key += 1
        return graph.L(self._next_key)

    def record_factor_indices(self, indices) -> None:
        idx = list(indices)
        for tr, pos in self._pending:
            tr.factor_indices.append(int(idx[pos]))
        self._pending = []

    # ----------------------------------------------------------- graph update
    def prepare_update(self, k: int, pred: gtsam.NavState, leaving: list[int],
                       g: gtsam.NonlinearFactorGraph, v: gtsam.Values,
                       stamps: dict) -> list[int]:
        """Add this keyframe's landmark factors to ``g``/``v``/``stamps``; return the
        smoother indices of factors to remove."""
        removals: list[int] = []
        self._motion_cache: dict = {}
        t = self.est.kf_t[k] * 1e-9
        leave = set(leaving)
        # the cap counts live landmarks only (dead ones wait for marginalization)
        n_active = sum(1 for tr in self.tracks.values() if tr.key is not None and k in tr.obs)
        # longest tracks first, so the landmark cap keeps the best-constrained ones
        for lid in sorted(self.tracks, key=lambda i: -len(self.tracks[i].obs)):
            tr = self.tracks[lid]
            live = k in tr.obs
            p_w = None
            if tr.anchor is not None and tr.anchor in leave:
                if not live:      # dead: marginalized with its anchor this update
                    del self.tracks[lid]
                    continue
                p_w = self._point_w(tr)
                self._retire_key(tr, g, stamps, removals)
            for f in [f for f in tr.obs if f in leave]:
                del tr.obs[f]
            if not tr.obs:
                del self.tracks[lid]
                continue
            if p_w is not None:
                self._reanchor(tr, p_w, k, pred, v)
            if not live:
                if tr.key is not None:
                    stamps[tr.key] = self.est.kf_t[tr.anchor] * 1e-9
                continue
            if tr.key is None and n_active < self.est.cfg.vision.max_landmarks:
                self._try_insert(tr, k, pred, v)
                n_active += tr.key is not None
            if tr.key is not None and (len(tr.obs) >= 2 or tr.stereo_frames()):
                removals.extend(tr.factor_indices)
                tr.factor_indices = []
                lam = v.atVector(tr.key)[0] if v.exists(tr.key) else self.est.values.atVector(tr.key)[0]
                self._add_factor(tr, g, k, pred, float(lam))
                stamps[tr.key] = t
        return removals

    def _retire_key(self, tr: Track, g: gtsam.NonlinearFactorGraph, stamps: dict,
                    removals: list[int]) -> None:
        """Detach a track's factor; its old key keeps a weak prior and is marginalized."""
        removals.extend(tr.factor_indices)
        if tr.key is not None:
            val = self.est.values.atVector(tr.key) if self.est.values.exists(tr.key) else np.ones(1)
            g.add(gtsam.PriorFactorVector(tr.key, val, WEAK))
            stamps[tr.key] = 0.0
        tr.key = tr.anchor = None
        tr.factor_indices = []

    def _point_w(self, tr: Track) -> np.ndarray | None:
        vals = self.est.values
        if tr.key is None or not vals.exists(tr.key):
            return None
        lam = float(vals.atVector(tr.key)[0])
        if lam <= 0:
            return None
        a = tr.obs[tr.anchor]
        T = vals.atPose3(graph.X(tr.anchor)).compose(vals.atPose3(graph.EXTRINSIC))
        return T.transformFrom(np.array([a.uv[0], a.uv[1], 1.0]) / lam)

    def _reanchor(self, tr: Track, p_w: np.ndarray, k: int, pred: gtsam.NavState,
                  v: gtsam.Values) -> None:
        """New key anchored in the oldest remaining frame, depth transferred from p_w."""
        a = tr.frames()[0]
        T_w_c = self._pose(a, k, pred).compose(self.est.values.atPose3(graph.EXTRINSIC))
        z = T_w_c.transformTo(p_w)[2]
        vc = self.est.cfg.vision
        if vc.min_depth_m <= z <= vc.max_depth_m:
            tr.key = self._new_key()
            tr.anchor = a
            v.insert(tr.key, np.array([1.0 / z]))

    def _add_factor(self, tr: Track, g: gtsam.NonlinearFactorGraph, k: int, pred: gtsam.NavState,
                    lam: float) -> None:
        frames = tr.frames()
        cam = self.est.cam
        src = tr
        if self.est.cfg.vision.td_velocity == "predicted" and lam > 0:
            src = self._with_predicted_velocity(tr, frames, k, pred, lam)
        if len(frames) >= 2:
            self._pending.append((tr, int(g.size())))
            g.add(graph.build_landmark_factor(src, frames, self.est.cfg, self.est.sigma,
                                              cam.line_time_s))
        if self.est.C_stereo is not None and src.stereo_frames():
            self._pending.append((tr, int(g.size())))
            g.add(graph.build_stereo_factor(src, self.est.C_stereo, self.est.cfg, self.est.sigma,
                                            cam.line_time_s))

    def _with_predicted_velocity(self, tr: Track, frames: list[int], k: int,
                                 pred: gtsam.NavState, lam: float) -> Track:
        """A copy of ``tr`` whose observation velocities are predicted from the state
        (keyframe velocity, bias-corrected gyro, landmark depth) instead of measured:
        independent of the pixel noise of the observations the factor compares, so the
        td estimate is not biased towards zero by noise (see ``VisionConfig.td_velocity``).
        A prediction further than ``td_velocity_gate`` from the measurement (a landmark
        with a wrong depth) is not used."""
        a = tr.obs[frames[0]]
        T_w_ca, _, _ = self._frame_motion(frames[0], k, pred)
        p_w = T_w_ca.transformFrom(np.array([a.uv[0], a.uv[1], 1.0]) / lam)
        obs = {}
        vc = self.est.cfg.vision
        for f in frames:
            T_w_c, w_c, v_c = self._frame_motion(f, k, pred)
            z = T_w_c.transformTo(p_w)[2]
            o = tr.obs[f]
            vel = o.velocity
            if z > vc.min_depth_m:
                p = graph.image_velocity(o.uv, z, w_c, v_c)
                # keep the measurement where the prediction is implausible (bad depth)
                if np.linalg.norm(p - o.velocity) < vc.td_velocity_gate:
                    vel = p
            if not np.linalg.norm(vel) <= vc.td_velocity_max:
                vel = np.zeros(2)  # a spike would dominate td (huge leverage): drop its td term
            obs[f] = Obs(o.uv, vel, o.row, o.right_uv, o.right_velocity)
        return Track(tr.lid, obs, tr.key, tr.anchor)

    def _frame_motion(self, f: int, k: int, pred: gtsam.NavState
                      ) -> tuple[gtsam.Pose3, np.ndarray, np.ndarray]:
        """``T_w_c`` of keyframe f and its camera angular / linear velocity in the camera
        frame (bias-corrected gyro, estimated velocity); cached per update."""
        key = (f, k)
        hit = self._motion_cache.get(key)
        if hit is not None:
            return hit
        vals, est = self.est.values, self.est
        T_b_c = vals.atPose3(graph.EXTRINSIC)
        R_c_b = T_b_c.rotation().matrix().T
        T_w_b = self._pose(f, k, pred)
        v_w = pred.velocity() if f == k else vals.atVector(graph.V(f))
        b = vals.atConstantBias(graph.B(k - 1 if f == k else f))
        w_b = est.kf_gyro.get(f, np.zeros(3)) - b.gyroscope()
        v_b = T_w_b.rotation().unrotate(v_w) + np.cross(w_b, T_b_c.translation())
        out = (T_w_b.compose(T_b_c), R_c_b @ w_b, R_c_b @ v_b)
        self._motion_cache[key] = out
        return out

    def _pose(self, f: int, k: int, pred: gtsam.NavState) -> gtsam.Pose3:
        return pred.pose() if f == k else self.est.values.atPose3(graph.X(f))

    def _try_insert(self, tr: Track, k: int, pred: gtsam.NavState, v: gtsam.Values) -> None:
        """Give the track a key and an initial inverse depth once it is triangulable."""
        frames = tr.frames()
        vc = self.est.cfg.vision
        if self.est.T_c0_c1 is not None:
            for f in frames:
                o = tr.obs[f]
                if o.right_uv is None:
                    continue
                z = stereo_depth(o.uv, o.right_uv, self.est.T_c0_c1)
                if np.isfinite(z) and vc.min_depth_m <= z <= min(vc.max_depth_m, vc.max_stereo_depth_m):
                    tr.key, tr.anchor = self._new_key(), f
                    for g in [g for g in frames if g < f]:
                        del tr.obs[g]          # the anchor is the first kept observation
                    v.insert(tr.key, np.array([1.0 / z]))
                    return
        if len(frames) < 2:
            return
        T_b_c = self.est.values.atPose3(graph.EXTRINSIC)
        cams = [self._pose(f, k, pred).compose(T_b_c) for f in frames]
        depth, angle = bearing_depth(tr.obs[frames[0]].uv, cams[0],
                                     [(tr.obs[f].uv, c) for f, c in zip(frames[1:], cams[1:])])
        ok = np.isfinite(depth) and vc.min_depth_m <= depth <= vc.max_depth_m
        if not (ok and angle >= vc.min_parallax_deg):
            tr.waited += 1
            if tr.waited < vc.max_wait_keyframes:
                return
            if not ok:
                depth = vc.default_depth_m
        tr.key = self._new_key()
        tr.anchor = frames[0]
        v.insert(tr.key, np.array([1.0 / depth]))

    # --------------------------------------------------------------- outliers
    def outlier_removals(self, values: gtsam.Values
                         ) -> tuple[gtsam.NonlinearFactorGraph, dict, list[int], int]:
        """Factors of tracks whose worst reprojection error exceeds ``outlier_px`` or whose
        depth left the valid range; those tracks are rejected for good."""
        vc = self.est.cfg.vision
        fx = self.est.cam.intrinsics[0]
        g, stamps, removals, n = gtsam.NonlinearFactorGraph(), {}, [], 0
        for lid in list(self.tracks):
            tr = self.tracks[lid]
            if tr.key is None or not tr.factor_indices:
                continue
            lam = float(values.atVector(tr.key)[0])
            bad_depth = not (1.0 / vc.max_depth_m <= lam <= 1.0 / vc.min_depth_m)
            err = graph.reprojection_errors(tr, tr.frames(), values) * fx
            if bad_depth or (err.size and err.max() > vc.outlier_px):
                self._retire_key(tr, g, stamps, removals)
                del self.tracks[lid]
                self.rejected.add(lid)
                n += 1
        return g, stamps, removals, n

    def points_w(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        """Ids (N,) and world points (N, 3) of the tracks in the graph."""
        pts, ids = [], []
        T_b_c = values.atPose3(graph.EXTRINSIC)
        for tr in self.tracks.values():
            if tr.key is None or not values.exists(tr.key) or not values.exists(graph.X(tr.anchor)):
                continue
            lam = float(values.atVector(tr.key)[0])
            if lam <= 0:
                continue
            a = tr.obs[tr.anchor]
            T = values.atPose3(graph.X(tr.anchor)).compose(T_b_c)
            pts.append(T.transformFrom(np.array([a.uv[0], a.uv[1], 1.0]) / lam))
            ids.append(tr.lid)
        return np.array(ids, dtype=np.int64), np.array(pts).reshape(-1, 3)
