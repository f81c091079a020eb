"""World-point landmarks: the monocular tracks' representation with ``VisionConfig.reanchor = "point"``.

A track enters the graph once its depth can be triangulated (``vio.backend.tracks``);
here it then becomes a world point ``p_w`` (a 3-vector key) observed through one
``factors.world_point`` factor over its observations in the window, td included (seed
004's shift with state-predicted image velocities). The anchored inverse depth of the
VINS-Mono factor takes the first observation as the point's exact ray (its noise only
whitened to first order) and must be re-anchored when that keyframe leaves. Measured on
generated tracks from real IMU (mid-flight excerpts), the anchored trajectory came out
0.5-2% short, while a GTSAM-native pipeline keeping ``Point3`` landmarks (same lag,
keyframes, IMU and noise) and these world points had the right scale (figures in
``VisionConfig``; world points only after re-anchoring changed nothing).

Life cycle per keyframe: a live point's factor is rebuilt with the new observation;
when keyframes leave the window, the observations they hold move into a farewell factor
that the smoother marginalizes with them, so the main factor never holds a marginalized
key and nothing measured is dropped or re-expressed; the point's timestamp follows its
newest observation, so it is marginalized with its last observer. After each update the
outlier check (``vio.backend.point_outliers``) drops a point whose errors disagree, or
only the observation of an isolated gross error, retiring the point. Frames: ``p_w`` world
(m), observations normalized cam0 coordinates, keyframe poses ``T_w_b``; used in monocular
modes with the pinhole model; the extrinsic ``T_b_c`` is a key of every factor when
calibrated online (``CalibConfig.estimate_extrinsic``), else a constant of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from factors.world_point import world_point_factor
from vio.backend import graph
from vio.backend.health import outlier_limit_px
from vio.backend.landmarks import Obs
from vio.backend.motion import motion_table
from vio.backend.point_outliers import point_row_errors, rejections
from vio.backend.td_velocity import points_velocities
from vio.backend.track_arrays import gather, run_starts

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

WEAK_POINT = gtsam.noiseModel.Isotropic.Sigma(3, 100.0)
_KERNELS = {"none": 0, "huber": 1, "cauchy": 2}


@dataclass
class PointTrack:
    """A world-point landmark: its key, in-window observations by keyframe, the keyframes
    and smoother index of its main factor (None before the update records it); ``rows``:
    (frames, ``Obs.packed`` rows, row offsets) of its last factor built, for the outlier
    check (``track_arrays.gather``'s arrays without the gather); ``retired``: the outlier
    check took one of its observations out, and it takes no new ones (the id is free again
    once the point has left the window); ``weak``: converted from a track that entered
    without parallax (``Track.weak``)."""

    lid: int
    key: int
    obs: dict[int, Obs] = field(default_factory=dict)
    frames: list[int] = field(default_factory=list)
    index: int | None = None
    rows: tuple[tuple[int, ...], np.ndarray, np.ndarray] | None = None
    retired: bool = False
    weak: bool = False


class PointTracks:
    """The world-point landmarks of one ``Estimator`` (module docstring)."""

    def __init__(self, est: "Estimator") -> None:
        self.est = est
        self.tracks: dict[int, PointTrack] = {}   # by landmark id
        self._pending: list[tuple[PointTrack, int]] = []   # (track, position in g)
        self._next_key = 0
        self._table = None     # the owner's motion table of the current update (callable)
        self._early: dict = {}            # (key, leaving frames) -> farewell factor (prefetch)
        self._early_values = None         # the estimate they were built at
        self._held = None                 # (outlier graph, its rebuilt main factors' slots in it)

    def begin_update(self, table) -> None:
        """The motion table (``vio.backend.motion.motion_table``) for this update's velocities."""
        self._table = table

    def usable(self) -> bool:
        """Whether tracks become world points (mono, pinhole)."""
        cfg = self.est.cfg
        return cfg.vision.reanchor == "point" and self.est.T_c0_c1 is None and cfg.vision.model == "pinhole"

    def reset(self) -> None:
        self.tracks = {}
        self._pending = []
        self._held = None
        self._early, self._early_values = {}, None

    def prefetch(self, leave: set[int]) -> None:
        """Build the farewell factors of the keyframes ``leave`` ahead of the update that drops
        them (``Estimator.prefetch``, between keyframes). They are the factors
        :meth:`prepare_update` would build: what goes into them (the leaving observations,
        the estimate, the motion of those keyframes) does not change between updates, and
        they are used only while the estimate they were built at is the current one."""
        est = self.est
        if self._early_values is not est.values:
            self._early, self._early_values = {}, est.values
        jobs = []
        for pt in self.tracks.values():
            gone = tuple(f for f in pt.frames if f in leave)
            if gone and (pt.key, gone) not in self._early:
                jobs.append((pt, list(gone), [pt.obs[f] for f in gone], None))
        if not jobs:
            return
        # the window's rows only: keyframe k + 1 does not exist yet, so no prediction is read
        table = motion_table(est, est.k + 1, None, lambda f: est.values.atPose3(graph.X(f)))
        held, self._table = self._table, (lambda: table)
        try:
            for (pt, gone, _, _), factor in zip(jobs, self._factors(jobs)):
                self._early[(pt.key, tuple(gone))] = factor
        finally:
            self._table = held

    def n_live(self, k: int) -> int:
        return sum(1 for p in self.tracks.values() if k in p.obs)

    def observe(self, lid: int, k: int, obs: Obs) -> bool:
        """Record keyframe ``k``'s observation of ``lid`` if it is a world point (a retired
        point's is ignored); False if ``lid`` is not one."""
        pt = self.tracks.get(lid)
        if pt is None:
            return False
        if pt.retired:
            return True
        pt.obs[k] = obs
        return True

    def convert(self, lid: int, p_w: np.ndarray, obs: dict[int, Obs], t: float,
                g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict, weak: bool = False) -> None:
        """A newly inserted track becomes a world point at ``p_w`` (m, world), with a weak
        prior there (``point_prior_sigma_m``): a low-parallax track leaves the depth
        direction nearly unobservable, which an inverse depth tolerates and a point does
        not, and a point behind every camera during an iteration has zero Jacobians
        (measured without it: IndeterminateLinearSystem at a point, 3 solver recoveries
        in the 18 generated benchmark runs)."""
        self._next_key += 1
        pt = PointTrack(lid, graph.P(self._next_key), dict(obs), weak=weak)
        v.insert(pt.key, np.asarray(p_w, float))
        sigma = self.est.cfg.vision.point_prior_sigma_m
        g.add(gtsam.PriorFactorVector(pt.key, np.asarray(p_w, float), gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
        jobs: list = []
        self._main(pt, sorted(pt.obs), g, jobs, p_w)
        self._fill(g, jobs)
        stamps[pt.key] = t
        self.tracks[lid] = pt

    def _factors(self, jobs: list[tuple[PointTrack, list[int], list[Obs], np.ndarray | None]]
                 ) -> list[gtsam.NonlinearFactor]:
        """The world-point factor of each ``(point, frames, obs, p_w)`` job: the
        observations ``obs`` made in ``frames``, each moved by ``(td + offset) vel``.
        ``vel``: the image velocities multiplying td (normalized units/s); with
        ``td_velocity = "predicted"`` (the default) those of ``p_w`` (None: the estimate)
        seen by a camera moving as the state says (``vio.backend.motion.motion_table``:
        ``dp_c/dt = -w x p_c - v``), so pixel noise does not pull td towards zero, zero
        where the prediction is further than ``td_velocity_gate`` from the measurement or
        the point is not in front; the measured ones otherwise; capped at
        ``td_velocity_max``. ``offset``: the rolling-shutter row delay minus the td its
        keyframe time holds. All jobs' observations in one array (``Obs.packed``), the
        velocities in one compiled pass (``vio.backend.td_velocity.points_velocities``)."""
        if not jobs:
            return []
        est, vc = self.est, self.est.cfg.vision
        P, start, off = gather([obs for _, _, obs, _ in jobs], est.cam.line_time_s)
        for (pt, fr, _, _), a, b in zip(jobs, start[:-1], start[1:]):
            pt.rows = (tuple(fr), P[a:b], off[a:b])
        vel = graph._td_velocity(P[:, 2:4], vc.td_velocity_max)
        uv = np.ascontiguousarray(P[:, 0:2])
        if vc.td_velocity == "predicted" and self._table is not None:
            pos, R, t, w, v = self._table()
            idx = np.array([pos[f] for _, fr, _, _ in jobs for f in fr], np.int64)
            p_w = np.array([est.values.atVector(pt.key) if p is None else p for pt, _, _, p in jobs],
                           float).reshape(-1, 3)
            meas, vel = vel, np.empty_like(vel)
            points_velocities(start, idx, R, t, w, v, p_w, meas, float(vc.min_depth_m), float(vc.td_velocity_gate),
                              float(vc.td_velocity_max), vel)
        kernel = (_KERNELS[vc.kernel], float(vc.kernel_k))
        # the extrinsic: a key of every factor when calibrated online, else the held value
        T_b_c = graph.EXTRINSIC if est.cfg.calib.estimate_extrinsic else est.values.atPose3(graph.EXTRINSIC)
        td_key = graph.TD if vc.use_td else None
        return [world_point_factor(pt.key, [graph.X(f) for f in fr], td_key, T_b_c, uv[a:b], vel[a:b], off[a:b],
                                   est.sigma, kernel)
                for (pt, fr, _, _), a, b in zip(jobs, start[:-1], start[1:])]

    def _reserve(self, jobs: list, pt: PointTrack, frames: list[int], g: gtsam.NonlinearFactorGraph,
                 p_w: np.ndarray | None = None) -> None:
        """Hold a slot of ``g`` for the factor of ``pt``'s observations in ``frames``;
        :meth:`_fill` builds the jobs' factors together and puts them there."""
        jobs.append(((pt, frames, [pt.obs[f] for f in frames], p_w), int(g.size())))
        g.add(graph.SLOT)

    def _fill(self, g: gtsam.NonlinearFactorGraph, jobs: list) -> None:
        for (_, slot), factor in zip(jobs, self._factors([job for job, _ in jobs])):
            g.replace(slot, factor)

    def _main(self, pt: PointTrack, frames: list[int], g: gtsam.NonlinearFactorGraph, jobs: list,
              p_w: np.ndarray | None = None) -> None:
        """Reserve ``pt``'s main factor (its smoother index is recorded)."""
        self._pending.append((pt, int(g.size())))
        self._reserve(jobs, pt, frames, g, p_w)
        pt.frames, pt.index = frames, None

    def prepare_update(self, k: int, t: float, leave: set[int], g: gtsam.NonlinearFactorGraph,
                       stamps: dict, removals: list[int]) -> None:
        """Keyframe ``k``: rebuild the main factor of every point that gained an
        observation or holds one in a leaving keyframe; those observations go to a
        farewell factor, marginalized with their keyframes. So only what leaves is
        linearized for good: leaving a dead point's factor for the smoother to absorb
        whole froze its in-window observations too (``bench_midflight`` MH_04@40 0.234 ->
        0.319%, MH_05@40 0.136 -> 0.214%, ~20% less CPU). Points with no observation left
        in the window are forgotten."""
        jobs: list = []    # the factors, built together into their slots of g
        early_ok = self._early_values is self.est.values   # prefetched farewells still valid
        for lid in list(self.tracks):
            pt = self.tracks[lid]
            gone = [f for f in pt.frames if f in leave]
            live = k in pt.obs
            if not gone and not live:
                continue
            if pt.index is not None:
                removals.append(pt.index)
            early = self._early.get((pt.key, tuple(gone))) if early_ok and gone else None
            if early is not None:
                g.add(early)
            elif gone:
                self._reserve(jobs, pt, gone, g)
            for f in [f for f in pt.obs if f in leave]:
                del pt.obs[f]
            if not pt.obs:
                del self.tracks[lid]
                continue
            self._main(pt, sorted(pt.obs), g, jobs)
            if live:
                stamps[pt.key] = t
        self._fill(g, jobs)
        self._early, self._early_values = {}, None

    def record_factor_indices(self, indices: list[int]) -> None:
        for pt, pos in self._pending:
            pt.index = int(indices[pos])
        self._pending = []

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild: old -> new factor slots."""
        for pt in self.tracks.values():
            pt.index = remap.get(pt.index)

    def outlier_removals(self, values: gtsam.Values, g: gtsam.NonlinearFactorGraph, stamps: dict,
                         removals: list[int]) -> tuple[list[int], list[int]]:
        """The outlier check (``vio.backend.point_outliers``) on every point's main factor:
        observations whose reprojection error exceeds ``outlier_px``
        (``health.outlier_limit_px``; moved by the current td). A point that only loses
        those observations gets its main factor rebuilt from the others in ``g`` (slots
        recorded when :meth:`arm` hands ``g`` to the update); a point rejected whole
        (``VisionConfig.outlier_obs`` off, too few consistent observations, a depth out of
        range) has its factor removed and a weak prior keeps the key determined until the
        smoother marginalizes it. Returns (ids dropped, ids trimmed)."""
        vc = self.est.cfg.vision
        fx = self.est.cam.intrinsics[0]
        td = float(values.atVector(graph.TD)[0]) if vc.use_td and values.exists(graph.TD) else 0.0
        pos, R, t = graph.camera_table(values, sorted(self.est.kf_t))
        cand = [(lid, pt) for lid, pt in self.tracks.items()
                if pt.index is not None and values.exists(pt.key) and all(f in pos for f in pt.frames)]
        if not cand:
            return [], []
        # every candidate's observations in one array, one compiled pass (~60 points of ~8
        # observations: 3.8 -> ~0.6 ms a keyframe on generated MH_03)
        ob, start, off = self._rows([pt for _, pt in cand])
        j = np.array([pos[f] for _, pt in cand for f in pt.frames], dtype=np.int64)
        P = np.array([values.atVector(pt.key) for _, pt in cand], dtype=float).reshape(-1, 3)
        vel = graph._td_velocity(ob[:, 2:4], vc.td_velocity_max)
        rows = np.empty(len(ob))
        point_row_errors(start, j, np.ascontiguousarray(ob[:, :2]), vel, off, P, R, t, td,
                         float(vc.min_depth_m), float(vc.max_depth_m), rows)
        dropped, trimmed = rejections(rows * fx, start, outlier_limit_px(self.est), vc.outlier_obs,
                                      vc.outlier_obs_agree)
        for i in dropped:
            lid, pt = cand[i]
            removals.append(pt.index)
            g.add(gtsam.PriorFactorVector(pt.key, P[i].copy(), WEAK_POINT))
            stamps[pt.key] = 0.0
            del self.tracks[lid]
        jobs: list = []
        n0 = len(self._pending)     # the rebuilt factors' slots wait for arm(g), not the next update
        for i, bad in trimmed.items():
            lid, pt = cand[i]
            removals.append(pt.index)
            for f, b in zip(pt.frames, bad):
                if b:
                    del pt.obs[f]
            self._main(pt, sorted(pt.obs), g, jobs)
            pt.retired = True
        self._fill(g, jobs)
        self._held = (g, self._pending[n0:])
        del self._pending[n0:]
        return [cand[i][0] for i in dropped], [cand[i][0] for i in trimmed]

    def arm(self, g: gtsam.NonlinearFactorGraph) -> None:
        """``g`` (an outlier check's graph) goes into the next update: the main factors it
        rebuilt get their slots from that update's indices. A graph the estimator dropped
        (a restart cleared the held update) is never armed, and its factors never recorded."""
        if self._held is not None and self._held[0] is g:
            self._pending += self._held[1]
        self._held = None

    def _rows(self, pts: list[PointTrack]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``gather``'s (rows, start, offsets) of the points' observations in ``pt.frames``:
        the rows their last factors were built from where those frames are the same (the
        main factors this keyframe's update took), gathered anew for the others."""
        blocks = [pt.rows if pt.rows is not None and pt.rows[0] == tuple(pt.frames) else None for pt in pts]
        miss = [i for i, b in enumerate(blocks) if b is None]
        if miss:
            P, start, off = gather([[pts[i].obs[f] for f in pts[i].frames] for i in miss], self.est.cam.line_time_s)
            for i, a, b in zip(miss, start[:-1], start[1:]):
                blocks[i] = (None, P[a:b], off[a:b])
        start = run_starts(np.array([len(b[1]) for b in blocks], np.int64))
        return np.concatenate([b[1] for b in blocks]), start, np.concatenate([b[2] for b in blocks])

    def points_w(self, values: gtsam.Values) -> tuple[list[int], list[np.ndarray]]:
        ids, pts = [], []
        for lid, pt in self.tracks.items():
            if values.exists(pt.key):
                ids.append(lid)
                pts.append(np.asarray(values.atVector(pt.key), float))
        return ids, pts
