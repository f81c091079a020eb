"""Landmark life cycle inside the fixed-lag window.

Per keyframe: new observations are appended; a track enters the graph once its
depth can be triangulated (or it has waited long enough); its factor is rebuilt
whenever it gains an observation; live tracks are re-anchored before their
anchor is marginalized, handing what they measured in the leaving keyframes to the
new key (farewell and depth-transfer factors, marginalized with those keyframes);
dead tracks are marginalized with their anchor; tracks with large reprojection
errors or non-positive depth are dropped and restart from their next observation.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from factors.stack import Member
from vio.backend import graph, health
from vio.backend.landmarks import Obs, Track, anchor_points, bearing_depth, stereo_depth
from vio.backend.point_tracks import PointTracks
from vio.backend.kernels import compile_kernels
from vio.backend.track_arrays import compile_kernel
from vio.backend.track_build import TrackFactorBuilder
from vio.io.types import FeatureFrame

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

WEAK = gtsam.noiseModel.Isotropic.Sigma(1, 10.0)


class LandmarkManager(TrackFactorBuilder):
    """Owns the ``Track`` table of an ``Estimator`` (factor construction:
    :class:`vio.backend.track_build.TrackFactorBuilder`)."""

    def __init__(self, est: "Estimator") -> None:
        self.est = est
        self.tracks: dict[int, Track] = {}
        self.rejected: set[int] = set()
        self.strikes: dict[int, int] = {}
        self._next_key = 0
        self._pending: list[tuple[Track, int]] = []
        self._motion_cache: dict = {}
        self._pose_cache: dict[int, gtsam.Pose3] = {}
        self._calib_cache: tuple | None = None   # (T_b_c, td) of the current update
        self._rig = None                         # factors.stereo.StereoRig of est.C_stereo
        self._rig_c1 = None                      # td_velocity.rig_c1 of est.T_c0_c1 (stereo)
        self.points = PointTracks(est)           # triangulated tracks as world points (VisionConfig.reanchor)
        compile_kernels()                  # not at the first keyframe: a stall there
        compile_kernel()

    # ------------------------------------------------------------ bookkeeping
    def observe(self, k: int, fr: FeatureFrame) -> None:
        """Append keyframe ``k``'s observations, with the td its time holds (``Obs.td_obs``,
        from ``KeyframeRates.td_obs``)."""
        td_obs = self.est.rates.td_obs(k)
        right = fr.right_uv if fr.right_uv is not None else np.full((len(fr.ids), 2), np.nan)
        rvel = fr.right_velocity if fr.right_velocity is not None else np.zeros((len(fr.ids), 2))
        rrow = fr.right_row if fr.right_row is not None else np.full(len(fr.ids), np.nan)
        for lid, uv, vel, row, ruv, rv, rr in zip(fr.ids, fr.uv, fr.velocity, fr.row, right, rvel, rrow):
            lid = int(lid)
            if lid in self.rejected:
                continue
            has_r = bool(np.all(np.isfinite(ruv)))
            o = Obs(np.asarray(uv, float), np.asarray(vel, float), float(row),
                    np.asarray(ruv, float) if has_r else None, np.asarray(rv, float) if has_r else None,
                    float(td_obs), float(rr) if has_r else float("nan"))
            if not self.points.observe(lid, k, o):
                self.tracks.setdefault(lid, Track(lid)).obs[k] = o

    def n_active(self) -> int:
        return sum(1 for t in self.tracks.values() if t.key is not None) + len(self.points.tracks)

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
        self.points.reset()

    def _new_key(self) -> int:
        self._next_key += 1
        return graph.L(self._next_key)

    def record_factor_indices(self, indices) -> None:
        idx = list(indices)
        for tr, pos in self._pending:
            tr.factor_indices.append(int(idx[pos]))
        self._pending = []
        self.points.record_factor_indices(idx)

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild (``vio.backend.smoother``): old -> new factor slots."""
        for tr in {id(t): t for t in self._indexed()}.values():
            tr.factor_indices = [remap[i] for i in tr.factor_indices if i in remap]
        self.points.remap_factor_indices(remap)

    def _indexed(self):
        """Every track that may hold factor slots."""
        return self.tracks.values()

    # ----------------------------------------------------------- graph update
    def prepare_update(self, k: int, pred: gtsam.NavState, leaving: list[int],
                       g: gtsam.NonlinearFactorGraph, v: gtsam.Values,
                       stamps: dict) -> list[int]:
        """Add this keyframe's landmark factors to ``g``/``v``/``stamps``; return the
        smoother indices of factors to remove."""
        removals: list[int] = []
        self._motion_cache: dict = {}
        self._pose_cache: dict[int, gtsam.Pose3] = {}
        self._calib_cache: tuple | None = None
        farewells: list[Member | tuple] = []
        self._deferred: list[tuple[Track, list[int], float, int]] = []
        t = self.est.kf_t[k] * 1e-9
        leave = set(leaving)
        self.points.begin_update(lambda: self._motion_table(k, pred))
        self.points.prepare_update(k, t, leave, g, stamps, removals)
        to_point = self.points.usable()
        # the cap counts live landmarks only (dead ones wait for marginalization)
        n_active = (sum(1 for tr in self.tracks.values() if tr.key is not None and k in tr.obs)
                    + self.points.n_live(k))
        # longest tracks first, so the landmark cap keeps the best-constrained ones
        for lid in sorted(self.tracks, key=lambda i: -len(self.tracks[i].obs)):
            tr = self.tracks[lid]
            live = k in tr.obs
            if tr.anchor is not None and tr.anchor in leave:
                if not live:      # dead: marginalized with its anchor this update
                    del self.tracks[lid]
                    continue
                self._hand_over(tr, k, pred, leave, g, v, stamps, removals, farewells)
            for f in [f for f in tr.obs if f in leave]:
                del tr.obs[f]
            if not tr.obs:
                del self.tracks[lid]
                continue
            if not live:
                if tr.key is not None:
                    stamps[tr.key] = self.est.kf_t[tr.anchor] * 1e-9
                continue
            if tr.key is None and n_active < self.est.cfg.vision.max_landmarks:
                self._try_insert(tr, k, pred, v)
                n_active += tr.key is not None
                if to_point and tr.key is not None:    # a world point from now on
                    self._to_point(tr, k, pred, t, g, v, stamps)
                    del self.tracks[lid]
                    continue
            if tr.key is not None and (len(tr.obs) >= 2 or tr.stereo_frames()):
                removals.extend(tr.factor_indices)
                tr.factor_indices = []
                lam = v.atVector(tr.key)[0] if v.exists(tr.key) else self.est.values.atVector(tr.key)[0]
                self._add_factor(tr, g, k, pred, float(lam))
                stamps[tr.key] = t
        self._build_deferred(g, farewells, k, pred)
        return removals

    def _hand_over(self, tr: Track, k: int, pred: gtsam.NavState, leave: set[int],
                   g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict,
                   removals: list[int], farewells: list[Member]) -> None:
        """Re-anchor a live track whose anchor leaves: a new key in its oldest remaining
        keyframe, depth transferred from the current point. With
        ``VisionConfig.marginalize_reanchored`` the leaving observations become targets of a
        farewell residual of the new key and a depth-transfer residual ties the old key to
        the new one (both appended to ``farewells``, stacked into one factor by the caller);
        the smoother marginalizes them with the leaving keyframes, so what the track
        measured there stays in its prior instead of being dropped."""
        vals = self.est.values
        p_w = self._point_w(tr)
        lam_o = float(vals.atVector(tr.key)[0]) if tr.key is not None and vals.exists(tr.key) else 0.0
        old_key, old_anchor, old_shift = tr.key, tr.anchor, tr.td_shift.get(tr.anchor)
        leaving = {f: tr.obs.pop(f) for f in sorted(tr.obs) if f in leave}
        self._retire_key(tr, g, stamps, removals)
        if p_w is None or not tr.obs:
            return
        self._reanchor(tr, p_w, k, pred, v)
        if tr.key is None:
            return
        stamps[tr.key] = self.est.kf_t[k] * 1e-9
        if self.est.cfg.vision.marginalize_reanchored:
            lam = float(v.atVector(tr.key)[0])
            anchor = dataclasses.replace(tr.obs[tr.anchor], right_uv=None, right_velocity=None)
            farewell = Track(tr.lid, {tr.anchor: anchor, **leaving}, tr.key, tr.anchor)
            farewells.append((farewell, [tr.anchor, *leaving], lam))
            if old_key is not None and lam_o > 0:
                farewells.append(graph.build_depth_transfer(old_key, tr.key, old_anchor, tr.anchor,
                                                            leaving[old_anchor].uv, lam_o, old_shift, self.est.cfg))

    def _to_point(self, tr: Track, k: int, pred: gtsam.NavState, t: float, g: gtsam.NonlinearFactorGraph,
                  v: gtsam.Values, stamps: dict) -> None:
        """A just-inserted track handed to ``self.points`` at the point its inverse depth
        says (``VisionConfig.reanchor = "point"``); the inverse-depth value is dropped."""
        T_w_c = self._pose(tr.anchor, k, pred).compose(self.est.values.atPose3(graph.EXTRINSIC))
        p_w = tr.anchor_point(T_w_c, float(v.atVector(tr.key)[0]), graph.td_value(self.est.values))
        v.erase(tr.key)
        self.points.convert(tr.lid, p_w, tr.obs, t, g, v, stamps, tr.weak)

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
        lam = self._lam(tr)
        if lam is None or lam <= 0:
            return None
        return tr.anchor_point(vals.atPose3(graph.X(tr.anchor)).compose(vals.atPose3(graph.EXTRINSIC)), lam,
                               graph.td_value(vals))

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
            self._set_depth(tr, 1.0 / z, v)

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
                    tr.key, tr.anchor, tr.weak = self._new_key(), f, False
                    for g in [g for g in frames if g < f]:
                        del tr.obs[g]          # the anchor is the first kept observation
                    self._set_depth(tr, 1.0 / z, v)
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
        tr.weak = not (ok and angle >= vc.min_parallax_deg)   # waited out: the depth is a guess
        self._set_depth(tr, 1.0 / depth, v)

    def _set_depth(self, tr: Track, lam: float, v: gtsam.Values) -> None:
        """A new key's initial inverse depth (1/m): a variable in ``v``."""
        v.insert(tr.key, np.array([lam]))

    def _lam(self, tr: Track) -> float | None:
        """The track's current inverse depth (None without one)."""
        vals = self.est.values
        return float(vals.atVector(tr.key)[0]) if tr.key is not None and vals.exists(tr.key) else None

    # --------------------------------------------------------------- outliers
    def outlier_removals(self, values: gtsam.Values
                         ) -> tuple[gtsam.NonlinearFactorGraph, dict, list[int], int]:
        """Factors of tracks whose worst reprojection error exceeds ``outlier_px``
        (``health.outlier_limit_px``) or whose depth left the valid range. Such a track is
        dropped with all its observations; the front end's next observation of the id starts
        it afresh (as VINS-Mono does); only an id dropped ``max_rejections`` times is ignored
        for good. Rejecting at once starved the estimator on long tracks: a track that entered
        at the default depth while still and failed at take-off stayed tracked but ignored,
        and MH_04 ran with 2-18 landmarks for 30 s (ATE 0.95 m; with restarts 0.18 m).
        World points (``PointTracks.outlier_removals``) may lose only an isolated outlier
        observation instead (``VisionConfig.outlier_obs``): those count in ``n`` (their
        factors are replaced in the same update) but do not strike the id."""
        vc = self.est.cfg.vision
        fx = self.est.cam.intrinsics[0]
        g, stamps, removals, n = gtsam.NonlinearFactorGraph(), {}, [], 0
        table = graph.camera_table(values, sorted(self.est.kf_t))
        checked, bad = [], []
        for tr in self.tracks.values():
            if tr.key is None or not tr.factor_indices:
                continue
            lam = float(values.atVector(tr.key)[0])
            # the depth bounds exclude lam <= 0 (reprojection_errors: all infinite)
            ok = lam > 0 and 1.0 / vc.max_depth_m <= lam <= 1.0 / vc.min_depth_m
            (checked if ok else bad).append(tr)
        worst = graph.worst_reprojection_errors(checked, values, table) * fx
        limit = health.outlier_limit_px(self.est)
        bad_ids = {tr.lid for tr in bad} | {tr.lid for tr, e in zip(checked, worst) if e > limit}
        for lid in list(self.tracks):
            tr = self.tracks[lid]
            if lid in bad_ids:
                self._retire_key(tr, g, stamps, removals)
                del self.tracks[lid]
                self._strike(lid)
                n += 1
        dropped, trimmed = self.points.outlier_removals(values, g, stamps, removals)
        for lid in dropped:
            self._strike(lid)
        n += len(dropped) + len(trimmed)
        return g, stamps, removals, n

    def arm(self, g: gtsam.NonlinearFactorGraph) -> None:
        """``g``, an outlier check's graph, goes into the next update (``PointTracks.arm``)."""
        self.points.arm(g)

    def _strike(self, lid: int) -> None:
        """Count a rejection of ``lid``; at ``max_rejections`` it is ignored for good."""
        self.strikes[lid] = self.strikes.get(lid, 0) + 1
        if self.strikes[lid] >= self.est.cfg.vision.max_rejections:
            self.rejected.add(lid)
            del self.strikes[lid]

    def weak_ids(self) -> np.ndarray:
        """Ids of the landmarks that entered without parallax (``Track.weak``,
        ``PointTrack.weak``): their depths are guesses."""
        return np.array([lid for lid, tr in self.tracks.items() if tr.weak]
                        + [lid for lid, pt in self.points.tracks.items() if pt.weak], dtype=np.int64)

    def points_w(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        """Ids (N,) and world points (N, 3) of the tracks in the graph."""
        cams = graph.anchor_cameras(values, {tr.anchor for tr in self.tracks.values() if tr.key is not None})
        sel = [tr for tr in self.tracks.values()
               if tr.key is not None and tr.anchor in cams and values.exists(tr.key)]
        lams = np.array([values.atVector(tr.key)[0] for tr in sel], float)
        keep = lams > 0
        sel = [tr for tr, k in zip(sel, keep) if k]
        pids, ppts = self.points.points_w(values)
        return (np.array([tr.lid for tr in sel] + pids, dtype=np.int64),
                np.vstack([anchor_points(sel, lams[keep], cams, graph.td_value(values)),
                           np.array(ppts).reshape(-1, 3)]))

