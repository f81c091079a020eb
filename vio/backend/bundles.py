"""Landmarks with their inverse depths eliminated inside the factors
(``VisionConfig.eliminate_depth``): one factor per anchor keyframe.

The life cycle is that of :class:`vio.backend.tracks.LandmarkManager` (insertion,
re-anchoring before the anchor leaves, outlier restarts); what differs is where a
landmark's inverse depth lives and which factor carries it:

* the inverse depth is ``Track.lam`` (1/m, anchor camera), not a graph variable; the
  factor refines it at each linearization (``factors.landmark_schur``) and it is read back
  from the factor's ``Bundle`` (:meth:`EliminatedLandmarks._sync`) for re-anchoring, the
  outlier check, the td velocity prediction and the map output;
* all landmarks anchored in keyframe a with observations beyond their anchor ray (two
  keyframes, or a cam1 match) share one factor over ``[T_b_c, X(a), X(f)..., td]``,
  rebuilt whenever one of them changes (a new observation, a new landmark, a rejection);
  the iSAM2 graph holds only keyframe states and calibration, and each keyframe costs one
  callback per anchor keyframe instead of one per landmark;
* when a leaves the window, its factor is replaced by a final one holding its dead
  landmarks (all their observations) and, with ``VisionConfig.farewell_poses``, for each
  live landmark re-anchored to its oldest remaining keyframe a', the observations in the
  leaving keyframes against the ray of a' (the farewell factor of
  ``VisionConfig.marginalize_reanchored``, its depth eliminated too); the smoother
  marginalizes it with the leaving keyframes. With the depth eliminated, the farewell
  passes on what the leaving observations say about the poses, not about the depth; with
  ``VisionConfig.reanchor_depth_prior`` the re-anchored landmark also gets a depth prior:
  the farewell's depth and its information with the leaving poses held at the estimate
  (an approximation of the variable mode's marginal: it ignores the leaving poses'
  uncertainty, so it is not carried over to the next re-anchoring, where accumulating it
  cost the real V1_01 tracks 0.025 -> 0.064 m).

Inverse depths are refined (``factors.landmark_schur.refine``, 3 Gauss-Newton steps) at
the estimate after every update, before the outlier check; the factors linearize around
them (``VisionConfig.depth_iters`` = 0 more steps inside): refining inside, at iSAM2's
linearization point (the IMU prediction for the new keyframe), cost real MH_05 mono
0.20 -> 0.58 m.

Each member track's ``factor_indices`` holds its factor's smoother index (the same one for
every member), so the scale refinement's index remapping (``vio.backend.regauge``) applies.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from factors import landmark_schur
from factors.bearing_model import tangent_basis
from vio.backend import graph
from vio.backend.health import outlier_limit_px
from vio.backend.landmarks import Track, anchor_points
from vio.backend.tracks import LandmarkManager

_EYE4, _EYE6 = np.eye(4), np.eye(6)
_WARM = False


class EliminatedLandmarks(LandmarkManager):
    """A ``LandmarkManager`` whose landmark factors are per-anchor-keyframe bundles."""

    def __init__(self, est) -> None:
        super().__init__(est)
        self.groups: dict[int, tuple[list[Track], landmark_schur.Bundle, list[int]]] = {}
        self._pending_groups: list[tuple[int, int]] = []
        _warm_up()

    # ------------------------------------------------------------ bookkeeping
    def reset(self) -> None:
        super().reset()
        for tr in self.tracks.values():
            tr.lam_prior = None
        self.groups = {}
        self._pending_groups = []

    def _set_depth(self, tr: Track, lam: float, v: gtsam.Values) -> None:
        tr.lam, tr.lam_prior = float(lam), None

    def _lam(self, tr: Track) -> float | None:
        return tr.lam if tr.key is not None else None

    def _sync(self) -> None:
        """Copy each factor's refined inverse depths into its member tracks."""
        for members, bundle, _ in self.groups.values():
            for tr, lam, on in zip(members, bundle.lam, bundle.active):
                if on:
                    tr.lam = float(lam)

    def _refine_at(self, values: gtsam.Values) -> None:
        """Refine every factor's inverse depths at the estimate ``values`` (the factors
        refine them at their linearization point, which the update has since moved), then
        copy them into the tracks."""
        T_b_c = values.atPose3(graph.EXTRINSIC).matrix()
        td = float(values.atVector(graph.TD)[0])
        for members, bundle, keys in self.groups.values():
            bodies = np.array([values.atPose3(x).matrix() for x in keys[1:1 + bundle.n_bodies]])
            landmark_schur.refine(bundle, bodies, T_b_c, td if bundle.use_td else 0.0, 3)
        self._sync()

    def scale_depths(self, f: float) -> None:
        """Multiply every inverse depth (tracks, factors, depth priors) by ``f``: the
        state moved by a similarity of scale 1/f (``vio.backend.regauge``)."""
        for tr in self.tracks.values():
            tr.lam *= f
            if tr.lam_prior is not None:
                tr.lam_prior = (tr.lam_prior[0] * f, tr.lam_prior[1] / (f * f))
        for _, bundle, _ in self.groups.values():
            bundle.lam *= f
            bundle.p_lam *= f
            bundle.p_info /= f * f

    def _index(self, a: int) -> list[int]:
        members = self.groups[a][0] if a in self.groups else []
        return sorted({i for tr in members for i in tr.factor_indices})

    def _indexed(self):
        return [*self.tracks.values(), *(tr for members, _, _ in self.groups.values() for tr in members)]

    def record_factor_indices(self, indices) -> None:
        idx = list(indices)
        for a, pos in self._pending_groups:
            if a in self.groups:
                members, bundle, _ = self.groups[a]
                for tr, on in zip(members, bundle.active):
                    tr.factor_indices = [int(idx[pos])] if on else []
        self._pending_groups = []
        self._pending = []

    @staticmethod
    def _has_rows(tr: Track) -> bool:
        return tr.key is not None and (len(tr.obs) >= 2 or bool(tr.stereo_frames()))

    # ----------------------------------------------------------- graph update
    def prepare_update(self, k: int, pred: gtsam.NavState, leaving: list[int],
                       g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict) -> list[int]:
        """As ``LandmarkManager.prepare_update`` (no landmark variables: ``v`` and
        ``stamps`` get none); returns the smoother indices of the factors replaced."""
        self._motion_cache, self._pose_cache, self._calib_cache = {}, {}, None
        self._sync()
        leave = set(leaving)
        old = {a: self._index(a) for a in self.groups}
        final: dict[int, list[tuple[Track, list[int]]]] = {}
        dirty: set[int] = set()
        self._live_of: dict[int, Track] = {}
        for a in sorted(self.groups):
            if a in leave:      # dead members go into the final factor with all they saw
                final[a] = [(tr, tr.frames()) for tr in self.groups[a][0]
                            if k not in tr.obs and tr.lid in self.tracks and tr.anchor == a]
        n_active = sum(1 for tr in self.tracks.values() if tr.key is not None and k in tr.obs)
        for lid in sorted(self.tracks, key=lambda i: -len(self.tracks[i].obs)):
            tr = self.tracks[lid]
            live = k in tr.obs
            if tr.anchor is not None and tr.anchor in leave:
                if not live:
                    del self.tracks[lid]
                    continue
                self._hand_over_eliminated(tr, k, pred, leave, v, final)
            for f in [f for f in tr.obs if f in leave]:
                del tr.obs[f]
            if not tr.obs:
                del self.tracks[lid]
                continue
            if not live:
                continue
            if tr.key is None and n_active < self.est.cfg.vision.max_landmarks:
                self._try_insert(tr, k, pred, v)
                n_active += tr.key is not None
            if self._has_rows(tr):
                dirty.add(tr.anchor)
        removals: list[int] = []
        finals = []
        for a in sorted(final):
            removals += old.get(a, [])
            self.groups.pop(a, None)
            entries = [(tr, fr) for tr, fr in final[a] if len(fr) >= 2 or any(
                tr.obs[f].right_uv is not None for f in fr)]
            if entries:
                finals.append(entries)
        rebuilds = [(a, self._group_members(a)) for a in sorted(dirty - leave)]
        # every factor's new rows in one pass: per factor, the pass's fixed cost was
        # ~0.7 ms of ~13 factors a real MH_01 stereo keyframe rebuilds
        self._refresh([e for entries in finals for e in entries]
                      + [(tr, tr.frames()) for _, members in rebuilds for tr in members], k, pred)
        for entries in finals:
            self._final_factor(entries, k, pred, g)
        for a, members in rebuilds:
            removals += old.get(a, [])
            self._rebuild(a, members, k, pred, g)
        return sorted(set(removals))

    def _final_factor(self, entries: list, k: int, pred: gtsam.NavState,
                      g: gtsam.NonlinearFactorGraph) -> None:
        """The leaving anchor's final factor (dead tracks and farewells) and, with
        ``VisionConfig.reanchor_depth_prior``, each re-anchored track's depth prior: its
        farewell's depth information at the estimate (the leaving poses held)."""
        vc = self.est.cfg.vision
        fw = [i for i, (tr, _) in enumerate(entries) if tr.lid in self._live_of]
        keep = entries if vc.farewell_poses else [e for i, e in enumerate(entries) if i not in fw]
        if keep:
            g.add(self._bundle_factor(keep, k, pred)[0])
        if not (vc.reanchor_depth_prior and fw):
            return
        sub = [entries[i] for i in fw]
        _, bundle, keys = self._bundle_factor(sub, k, pred)
        frames = sorted({f for _, fr in sub for f in fr})
        bodies = np.array([self._pose(f, k, pred).matrix() for f in frames])
        T_b_c, td = self._calib_cache
        landmark_schur.refine(bundle, bodies, T_b_c.matrix(), td if bundle.use_td else 0.0, 3)
        for j, (tr, _) in enumerate(sub):
            live = self._live_of[tr.lid]
            lam, h = float(bundle.lam[j]), float(bundle.hll[j])
            if h > 0 and np.isfinite(lam):
                live.lam_prior = (lam, 1.0 / (1.0 / h + (vc.reanchor_prior_sigma * lam) ** 2))

    def _group_members(self, a: int) -> list[Track]:
        """Group a's current members: its tracks with rows, by landmark id."""
        return sorted((tr for tr in self.tracks.values() if tr.anchor == a and self._has_rows(tr)),
                      key=lambda tr: tr.lid)

    def _rebuild(self, a: int, members: list[Track], k: int, pred: gtsam.NavState,
                 g: gtsam.NonlinearFactorGraph) -> None:
        """Replace group a's factor by one over ``members`` (none: dropped)."""
        for tr in (self.groups[a][0] if a in self.groups else []):
            tr.factor_indices = []
        self.groups.pop(a, None)
        if not members:
            return
        factor, bundle, keys = self._bundle_factor([(tr, tr.frames()) for tr in members], k, pred)
        self.groups[a] = (members, bundle, keys)
        self._pending_groups.append((a, int(g.size())))
        g.add(factor)

    def _hand_over_eliminated(self, tr: Track, k: int, pred: gtsam.NavState, leave: set[int],
                              v: gtsam.Values, final: dict) -> None:
        """Re-anchor a live track whose anchor leaves (its oldest remaining keyframe, depth
        transferred from the current point); its leaving observations become a farewell
        entry of the old anchor's final factor (module docstring)."""
        p_w = self._point_w(tr)
        old_anchor, lam_old, prior_old = tr.anchor, tr.lam, tr.lam_prior
        gone = {f: tr.obs.pop(f) for f in sorted(tr.obs) if f in leave}
        tr.key = tr.anchor = tr.lam_prior = None
        tr.factor_indices = []
        if p_w is None or not tr.obs:
            return
        self._reanchor(tr, p_w, k, pred, v)
        if tr.key is None or not self.est.cfg.vision.marginalize_reanchored:
            return
        anchor = dataclasses.replace(tr.obs[tr.anchor], right_uv=None, right_velocity=None)
        prior = None
        if prior_old is not None and lam_old > 0 and self.est.cfg.vision.reanchor_prior_sigma > 0:
            prior = (tr.lam * prior_old[0] / lam_old, prior_old[1] * (lam_old / tr.lam) ** 2)
        farewell = Track(tr.lid, {tr.anchor: anchor, **gone}, tr.key, tr.anchor, lam=tr.lam, lam_prior=prior)
        self._live_of[tr.lid] = tr
        final.setdefault(old_anchor, []).append((farewell, [tr.anchor, *gone]))

    # -------------------------------------------------------------- factors
    def _bundle_factor(self, entries: list[tuple[Track, list[int]]], k: int, pred: gtsam.NavState
                       ) -> tuple[gtsam.NonlinearFactor, landmark_schur.Bundle, list[int]]:
        """One factor over ``entries`` (track, its frames with the anchor first)."""
        est, vc = self.est, self.est.cfg.vision
        robust, td_key = graph._vision_options(est.cfg)
        if self._rig is None and est.C_stereo is not None:
            self._rig = graph.stereo_rig(est.C_stereo)
        C, ad_inv = (self._rig.C, self._rig.ad_inv) if self._rig is not None else (_EYE4, _EYE6)
        frames = sorted({f for _, fr in entries for f in fr})
        pos = {f: i for i, f in enumerate(frames)}
        lms = self._landmarks(entries, pos)
        bundle = landmark_schur.pack(len(frames), lms, C, ad_inv, vc.model, est.sigma, robust,
                                     td_key is not None, (1.0 / vc.max_depth_m, 1.0 / vc.min_depth_m),
                                     vc.depth_iters)
        if self._calib_cache is None:
            vals = est.values
            self._calib_cache = (vals.atPose3(graph.EXTRINSIC), float(vals.atVector(graph.TD)[0]))
        T_b_c, td = self._calib_cache
        if vc.anchor_noise:
            bodies = np.array([self._pose(f, k, pred).matrix() for f in frames])
            landmark_schur.set_whitening(bundle, bodies, T_b_c.matrix(), td if td_key is not None else 0.0)
        keys = [graph.EXTRINSIC] + [graph.X(f) for f in frames] + ([int(td_key)] if td_key is not None else [])
        return landmark_schur.bundle_factor(keys, bundle), bundle, keys

    def _refresh(self, entries: list[tuple[Track, list[int]]], k: int, pred: gtsam.NavState) -> None:
        """Set ``Track.entry`` (frames, arrays) of each track in ``entries`` observed at k or
        with other frames than its entry's, all rows in one pass (``vio.backend.track_arrays``)."""
        fresh = [(tr, fr, tr.lam) for tr, fr in entries
                 if not (tr.entry is not None and tr.entry[0] == tuple(fr) and k not in tr.obs)]
        for (tr, fr, _), r in zip(fresh, self._rows(fresh, k, pred)):
            tr.entry = (tuple(fr), dict(target=r.target, right=r.right, uv=r.uv, vel=r.vel, off=r.offset,
                                        basis=r.basis, a_uv=r.a_uv, a_vel=r.a_vel, a_off=r.a_off))

    def _landmarks(self, entries: list[tuple[Track, list[int]]], pos: dict) -> list[dict]:
        """``landmark_schur.pack``'s entries of ``entries`` (track, frames with the anchor
        first) from their ``Track.entry`` arrays, which :meth:`prepare_update` refreshed
        (:meth:`_refresh`) before building any factor. A track no longer observed keeps the
        arrays of its last factor (td velocities and shifts included, as the variable mode
        keeps a dead landmark's factor)."""
        return [{**tr.entry[1], "lam": tr.lam, "p_lam": tr.lam_prior[0] if tr.lam_prior else 0.0,
                 "p_info": tr.lam_prior[1] if tr.lam_prior else 0.0, "bodies": [pos[f] for f in fr]}
                for tr, fr in entries]

    # --------------------------------------------------------------- outliers
    def outlier_removals(self, values: gtsam.Values
                         ) -> tuple[gtsam.NonlinearFactorGraph, dict, list[int], int]:
        """As ``LandmarkManager.outlier_removals`` with the factors' inverse depths; each
        affected factor is re-added with its rejected landmarks switched off."""
        self._refine_at(values)
        vc = self.est.cfg.vision
        fx = self.est.cam.intrinsics[0]
        g, removals, n = gtsam.NonlinearFactorGraph(), [], 0
        members = [tr for ms, _, _ in self.groups.values() for tr in ms
                   if tr.key is not None and tr.factor_indices and tr.lid in self.tracks]
        ok = [1.0 / vc.max_depth_m <= tr.lam <= 1.0 / vc.min_depth_m for tr in members]
        checked = [tr for tr, o in zip(members, ok) if o]
        table = graph.camera_table(values, sorted(self.est.kf_t))
        worst = graph.worst_reprojection_errors(checked, values, table, np.array([tr.lam for tr in checked])) * fx
        limit = outlier_limit_px(self.est)
        bad = {tr.lid for tr, o in zip(members, ok) if not o} | {
            tr.lid for tr, e in zip(checked, worst) if e > limit}
        for a in sorted(self.groups):
            ms, bundle, keys = self.groups[a]
            hit = [i for i, tr in enumerate(ms) if tr.lid in bad and bundle.active[i]]
            if not hit:
                continue
            removals += self._index(a)
            bundle.active[hit] = False
            if bundle.active.any():
                self._pending_groups.append((a, int(g.size())))
                g.add(landmark_schur.bundle_factor(keys, bundle))
            else:
                for tr in ms:
                    tr.factor_indices = []
                del self.groups[a]
        for lid in sorted(bad):
            tr = self.tracks.pop(lid, None)
            if tr is None:
                continue
            tr.key = tr.anchor = None
            tr.factor_indices = []
            self.strikes[lid] = self.strikes.get(lid, 0) + 1
            if self.strikes[lid] >= vc.max_rejections:
                self.rejected.add(lid)
                del self.strikes[lid]
            n += 1
        return g, {}, sorted(set(removals)), n

    def points_w(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        """Ids (N,) and world points (N, 3) of the landmarks in the factors."""
        self._sync()
        cams = graph.anchor_cameras(values, {tr.anchor for tr in self.tracks.values() if tr.key is not None})
        sel = [tr for tr in self.tracks.values() if tr.key is not None and tr.lam > 0 and tr.anchor in cams]
        return (np.array([tr.lid for tr in sel], dtype=np.int64),
                anchor_points(sel, np.array([tr.lam for tr in sel]), cams, graph.td_value(values)))


def _warm_up() -> None:
    """Compile (or load) the bundle kernels once per process, off the first keyframe."""
    global _WARM
    if _WARM:
        return
    _WARM = True
    uv = np.array([[0.01, 0.02]])
    lm = dict(bodies=[0, 1], target=np.array([1]), right=np.array([False]), uv=uv, vel=np.zeros((1, 2)),
              off=np.zeros(1), basis=tangent_basis(uv), a_uv=np.zeros(2), a_vel=np.zeros(2), a_off=0.0, lam=0.5)
    T = np.array([np.eye(4), np.eye(4)])
    T[1, 0, 3] = 0.1
    for use_td in (False, True):
        b = landmark_schur.pack(2, [lm], _EYE4, _EYE6, "pinhole", 0.01, None, use_td, (0.01, 10.0))
        landmark_schur.set_whitening(b, T, np.eye(4), 0.0)
        H, gv, E = landmark_schur.linearize(b, T, np.eye(4), 0.0)
        landmark_schur.square_root(H + np.eye(len(H)), gv, E)
