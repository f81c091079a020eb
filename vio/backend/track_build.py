"""Landmark factor construction for :class:`vio.backend.tracks.LandmarkManager`.

A keyframe's landmark factors are reserved as slots of the update's graph while the life
cycle runs (:meth:`TrackFactorBuilder._add_factor`) and built together afterwards, all
residual rows in one compiled pass (``vio.backend.track_arrays``), with the motion table
and poses of the update cached once (:meth:`TrackFactorBuilder._build_deferred`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import gtsam

from factors.stack import Member, stacked_factor
from vio.backend import graph
from vio.backend.landmarks import Track
from vio.backend.motion import motion_table
from vio.backend.td_velocity import rig_c1
from vio.backend.track_arrays import TrackRows, track_rows
from vio.backend.track_factor import member_factor, track_member

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator


class TrackFactorBuilder:
    """The factor-building half of ``LandmarkManager``. The host sets ``est``, and per
    update ``_pending`` (track, position in the graph), ``_deferred`` (track, frames,
    inverse depth, slot), ``_motion_cache``, ``_pose_cache`` and ``_calib_cache``; ``_rig``
    and ``_rig_c1`` are filled here on first use."""

    est: "Estimator"
    _pending: list
    _deferred: list
    _motion_cache: dict
    _pose_cache: dict
    _calib_cache: tuple | None
    _rig: object
    _rig_c1: object

    def _build_deferred(self, g: gtsam.NonlinearFactorGraph, farewells: list, k: int,
                        pred: gtsam.NavState) -> None:
        """Build this update's landmark factors into their reserved slots of ``g`` and
        the farewells (``(track, frames, lam)`` entries among depth-transfer members),
        all rows in one pass (``vio.backend.track_arrays``)."""
        todo = [d[:3] for d in self._deferred] + [f for f in farewells if isinstance(f, tuple)]
        built = iter(self._members(todo, k, pred))
        for *_, slot in self._deferred:
            g.replace(slot, member_factor(next(built)))
        self._deferred = []
        if farewells:   # one callback for all of them (factors.stack): marginalized in this update
            g.add(stacked_factor([next(built) if isinstance(f, tuple) else f for f in farewells]))

    def _add_factor(self, tr: Track, g: gtsam.NonlinearFactorGraph, k: int, pred: gtsam.NavState,
                    lam: float) -> None:
        """Reserve the track's factor over all its observations a slot in ``g`` (its
        smoother index is recorded), built by :meth:`_build_deferred`."""
        self._pending.append((tr, int(g.size())))
        self._deferred.append((tr, tr.frames(), lam, int(g.size())))
        g.add(graph.SLOT)

    def _members(self, items: list[tuple[Track, list[int], float]], k: int,
                 pred: gtsam.NavState) -> list[Member]:
        """Landmark (or, with cam1 observations, stereo) residuals of each ``(track,
        frames, lam)`` over its frames (anchor first) at inverse depth lam
        (``track_factor.track_member``)."""
        est = self.est
        rows = self._rows(items, k, pred)
        if est.cfg.vision.anchor_noise and self._calib_cache is None:
            self._calib_cache = (est.values.atPose3(graph.EXTRINSIC), float(est.values.atVector(graph.TD)[0]))
        out = []
        for (tr, frames, lam), r in zip(items, rows):
            at = None
            if est.cfg.vision.anchor_noise:
                T_b_c, td = self._calib_cache
                at = graph.LinPoint(lam, T_b_c, {f: self._pose(f, k, pred) for f in frames}, td)
            out.append(track_member(tr, frames, r, self._rig, est.cfg, est.sigma, at))
        return out

    def _rows(self, items: list[tuple[Track, list[int], float]], k: int,
              pred: gtsam.NavState) -> list[TrackRows]:
        """``vio.backend.track_arrays.track_rows`` of ``(track, frames, lam)`` items with
        this update's motion table and the rig (cam1 rows with stereo)."""
        est, vc = self.est, self.est.cfg.vision
        if self._rig is None and est.C_stereo is not None:
            self._rig = graph.stereo_rig(est.C_stereo)
        predicted = vc.td_velocity == "predicted"
        if predicted and self._rig_c1 is None and est.T_c0_c1 is not None:
            self._rig_c1 = rig_c1(est.T_c0_c1)
        table = self._motion_table(k, pred) if predicted and any(lam > 0 for *_, lam in items) else None
        return track_rows(items, self._rig is not None, predicted, table, self._rig_c1, vc.min_depth_m,
                          vc.td_velocity_gate, vc.td_velocity_max, est.cam.line_time_s)

    def _motion_table(self, k: int, pred: gtsam.NavState) -> tuple:
        """``vio.backend.motion.motion_table`` of this update (cached per update)."""
        if not self._motion_cache:
            self._motion_cache["table"] = motion_table(self.est, k, pred, lambda f: self._pose(f, k, pred))
        return self._motion_cache["table"]

    def _pose(self, f: int, k: int, pred: gtsam.NavState) -> gtsam.Pose3:
        """``T_w_b`` of keyframe f: the prediction for the new keyframe k, else the
        estimate (cached for the current update; the estimate does not change within it)."""
        T = self._pose_cache.get(f)
        if T is None:
            T = pred.pose() if f == k else self.est.values.atPose3(graph.X(f))
            self._pose_cache[f] = T
        return T
