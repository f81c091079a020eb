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
newest observation, so it is marginalized with its last observer. Frames: ``p_w`` world
(m), observations normalized cam0 coordinates, keyframe poses ``T_w_b``; used in monocular
modes with the pinhole model and a held extrinsic (the factor holds ``T_b_c``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from factors.world_point import world_point_factor
from vio.backend import graph
from vio.backend.landmarks import Obs

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

WEAK_POINT = gtsam.noiseModel.Isotropic.Sigma(3, 100.0)
_KERNELS = {"none": 0, "huber": 1, "cauchy": 2}


@dataclass
class PointTrack:
    """A world-point landmark: its key, in-window observations by keyframe, the keyframes
    and smoother index of its main factor (None before the update records it)."""

    lid: int
    key: int
    obs: dict[int, Obs] = field(default_factory=dict)
    frames: list[int] = field(default_factory=list)
    index: int | None = None


class PointTracks:
    """The world-point landmarks of one ``Estimator`` (module docstring)."""

    def __init__(self, est: "Estimator") -> None:
        self.est = est
        self.tracks: dict[int, PointTrack] = {}
        self._pending: list[tuple[PointTrack, int]] = []   # (track, position in g)
        self._next_key = 0
        self._table = None     # the owner's motion table of the current update (callable)

    def begin_update(self, table) -> None:
        """The motion table (``vio.backend.motion.motion_table``) for this update's velocities."""
        self._table = table

    def usable(self) -> bool:
        """Whether tracks become world points (mono, pinhole, extrinsic held)."""
        cfg = self.est.cfg
        return (cfg.vision.reanchor == "point" and self.est.T_c0_c1 is None
                and cfg.vision.model == "pinhole" and not cfg.calib.estimate_extrinsic)

    def reset(self) -> None:
        self.tracks = {}
        self._pending = []

    def n_live(self, k: int) -> int:
        return sum(1 for p in self.tracks.values() if k in p.obs)

    def observe(self, lid: int, k: int, obs: Obs) -> bool:
        """Record keyframe ``k``'s observation of ``lid`` if it is a world point."""
        pt = self.tracks.get(lid)
        if pt is None:
            return False
        pt.obs[k] = obs
        return True

    def convert(self, lid: int, p_w: np.ndarray, obs: dict[int, Obs], t: float,
                g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict) -> None:
        """A newly inserted track becomes a world point at ``p_w`` (m, world), with a weak
        prior there (``point_prior_sigma_m``): a low-parallax track leaves the depth
        direction nearly unobservable, which an inverse depth tolerates and a point does
        not, and a point behind every camera during an iteration has zero Jacobians
        (measured without it: IndeterminateLinearSystem at a point, 3 solver recoveries
        in the 18 generated benchmark runs)."""
        self._next_key += 1
        pt = PointTrack(lid, graph.P(self._next_key), dict(obs))
        v.insert(pt.key, np.asarray(p_w, float))
        sigma = self.est.cfg.vision.point_prior_sigma_m
        g.add(gtsam.PriorFactorVector(pt.key, np.asarray(p_w, float), gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
        self._main(pt, sorted(pt.obs), g, p_w)
        stamps[pt.key] = t
        self.tracks[lid] = pt

    def _velocities(self, obs: list[Obs], frames: list[int], p_w: np.ndarray) -> np.ndarray:
        """(n, 2) image velocities (normalized units/s) multiplying td: with
        ``td_velocity = "predicted"`` (the default) those of ``p_w`` seen by a camera moving
        as the state says (``vio.backend.motion.motion_table``: ``dp_c/dt = -w x p_c - v``),
        so pixel noise does not pull td towards zero; zero where the prediction is
        further than ``td_velocity_gate`` from the measurement or the point is not in
        front; the measured ones otherwise. Capped at ``td_velocity_max``."""
        vc = self.est.cfg.vision
        meas = graph._td_velocity(np.array([o.velocity for o in obs]), vc.td_velocity_max)
        if vc.td_velocity != "predicted" or self._table is None:
            return meas
        pos, R, t, w, v = self._table()
        j = np.array([pos[f] for f in frames])
        pc = np.einsum("nab,na->nb", R[j], p_w - t[j])          # R_w_c^T (p_w - t_w_c)
        dp = -np.cross(w[j], pc) - v[j]
        z = pc[:, 2:3]
        front = z[:, 0] >= vc.min_depth_m
        zs = np.where(front[:, None], z, 1.0)
        pred = (dp[:, :2] * zs - pc[:, :2] * dp[:, 2:3]) / zs ** 2
        ok = front & (np.linalg.norm(pred - meas, axis=1) <= vc.td_velocity_gate)
        return graph._td_velocity(np.where(ok[:, None], pred, 0.0), vc.td_velocity_max)

    def _factor(self, pt: PointTrack, frames: list[int], p_w: np.ndarray | None = None) -> gtsam.NonlinearFactor:
        """The world-point factor of ``pt``'s observations in ``frames``: each moved by
        ``(td + offset) vel`` (:meth:`_velocities` at ``p_w``, default the estimate; offset:
        the rolling-shutter row delay minus the td its keyframe time holds)."""
        est, vc = self.est, self.est.cfg.vision
        obs = [pt.obs[f] for f in frames]
        vel = self._velocities(obs, frames, np.asarray(est.values.atVector(pt.key) if p_w is None else p_w, float))
        off = graph._row_offsets(obs, est.cam.line_time_s)
        kernel = (_KERNELS[vc.kernel], float(vc.kernel_k))
        return world_point_factor(pt.key, [graph.X(f) for f in frames], graph.TD if vc.use_td else None,
                                  est.values.atPose3(graph.EXTRINSIC), np.array([o.uv for o in obs]), vel, off,
                                  est.sigma, kernel)

    def _main(self, pt: PointTrack, frames: list[int], g: gtsam.NonlinearFactorGraph,
              p_w: np.ndarray | None = None) -> None:
        self._pending.append((pt, int(g.size())))
        g.add(self._factor(pt, frames, p_w))
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
        for lid in list(self.tracks):
            pt = self.tracks[lid]
            gone = [f for f in pt.frames if f in leave]
            live = k in pt.obs
            if not gone and not live:
                continue
            if pt.index is not None:
                removals.append(pt.index)
            if gone:
                g.add(self._factor(pt, gone))
            for f in [f for f in pt.obs if f in leave]:
                del pt.obs[f]
            if not pt.obs:
                del self.tracks[lid]
                continue
            self._main(pt, sorted(pt.obs), g)
            if live:
                stamps[pt.key] = t

    def record_factor_indices(self, indices: list[int]) -> None:
        for pt, pos in self._pending:
            pt.index = int(indices[pos])
        self._pending = []

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild: old -> new factor slots."""
        for pt in self.tracks.values():
            pt.index = remap.get(pt.index)

    def outlier_removals(self, values: gtsam.Values, g: gtsam.NonlinearFactorGraph, stamps: dict,
                         removals: list[int]) -> list[int]:
        """Ids of points whose reprojection error in their main factor exceeds
        ``outlier_px`` (observations moved by the current td) or that leave the depth
        range: the factor is removed and a weak prior keeps the key determined until the
        smoother marginalizes it."""
        vc = self.est.cfg.vision
        fx = self.est.cam.intrinsics[0]
        td = float(values.atVector(graph.TD)[0]) if vc.use_td and values.exists(graph.TD) else 0.0
        pos, R, t = graph.camera_table(values, sorted(self.est.kf_t))
        bad = []
        for lid, pt in self.tracks.items():
            if pt.index is None or not values.exists(pt.key) or any(f not in pos for f in pt.frames):
                continue
            p = np.asarray(values.atVector(pt.key), float)
            obs = [pt.obs[f] for f in pt.frames]
            vel = graph._td_velocity(np.array([o.velocity for o in obs]), vc.td_velocity_max)
            off = graph._row_offsets(obs, self.est.cam.line_time_s)
            j = np.array([pos[f] for f in pt.frames])
            q = np.einsum("nab,na->nb", R[j], p - t[j])
            if not np.all((q[:, 2] >= vc.min_depth_m) & (q[:, 2] <= vc.max_depth_m)):
                worst = np.inf
            else:
                uv = np.array([o.uv for o in obs]) - (td + off)[:, None] * vel
                worst = float(np.max(np.linalg.norm(q[:, :2] / q[:, 2:3] - uv, axis=1))) * fx
            if worst > vc.outlier_px:
                removals.append(pt.index)
                g.add(gtsam.PriorFactorVector(pt.key, p, WEAK_POINT))
                stamps[pt.key] = 0.0
                bad.append(lid)
        for lid in bad:
            del self.tracks[lid]
        return bad

    def points_w(self, values: gtsam.Values) -> tuple[list[int], list[np.ndarray]]:
        ids, pts = [], []
        for lid, pt in self.tracks.items():
            if values.exists(pt.key):
                ids.append(lid)
                pts.append(np.asarray(values.atVector(pt.key), float))
        return ids, pts
