"""Photometric points as a ``FactorSource`` of the estimator (``Estimator.sources``).

Keys (next to the backend's X/V/B/E/D/L): ``A(k)`` = [a, b] of keyframe k's left image,
``S(k)`` = [a, b] of its right image relative to the left, ``R(n)`` = inverse depth
(1/m) of point n in its host keyframe's cam0 frame. The pose keys X(k) are T_w_b
(body); the factors use the calibrated, fixed T_b_c of cam0 and T_c1_c0.

Per keyframe k (``prepare_update``):

0. every point in the graph is checked at the current estimate (the result of the
   previous update): targets whose residual RMSE exceeds ``max_target_rmse`` or that
   left the image are dropped from its factor (occlusion, a depth discontinuity: the
   point stays, constrained by its other targets); a point with no target left or an
   inverse depth out of range is removed (weak prior, marginalized at once). Checking
   only the points rebuilt in the last update missed targets that went bad later and
   removed whole points for one bad target;
1. points whose host leaves the window are forgotten (their keys carry the host's
   timestamp, so the smoother marginalizes them with it);
2. TrackFrame (seed Algorithm 3) aligns keyframe k to the previous keyframe, starting
   at the IMU prediction; its pose becomes the initial guess of X(k) when it
   converged and agrees with the prediction (``PointsConfig.track_gate_*``), its
   affine the guess of A(k); its RMSE is logged and kept in ``tracks`` (failure signal);
3. every active point is checked in keyframe k at the initial guess (inside the image,
   residual RMSE below ``max_target_rmse``); accepted ones gain target k and their one
   factor (``factors.photometric_point.point_factor``: static stereo at the host plus all
   temporal targets) is rebuilt; rejected or full ones become inactive and keep their
   last factor until their host is marginalized;
4. A(k), S(k) get weak priors, and new points hosted in k (epipolar depths, static
   stereo term only) fill the active set up to ``max_active``, away from the
   projections of the active points.

Keyframe 0 (and the restart keyframe after a solver recovery) only gets ``observe``:
its keys and points are inserted at the next keyframe.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.adapter import FactorHealth
from factors.photometric import (HostPatch, PhotometricParams, make_host_patch, stereo_eval,
                                 temporal_eval)
from factors.photometric_point import StereoTerm, point_factor
from vio.direct.config import DirectConfig
from vio.direct.keyframe import KeyframeData, StereoRig, build_keyframe
from vio.direct.trackframe import track_frame

log = logging.getLogger(__name__)
X = gtsam.symbol_shorthand.X
A = gtsam.symbol_shorthand.A
S = gtsam.symbol_shorthand.S
R = gtsam.symbol_shorthand.R
_WEAK = gtsam.noiseModel.Isotropic.Sigma(1, 10.0)


@dataclass(eq=False)
class Point:
    """One photometric point: host keyframe, host pixel ``uv`` (undistorted px), its
    host patch, the target keyframes and the smoother indices of its factor."""

    pid: int
    key: int
    host: int
    uv: np.ndarray
    patch: HostPatch
    targets: list
    factor_indices: list
    active: bool = True
    dirty: bool = True


@dataclass(frozen=True)
class TrackRecord:
    """TrackFrame at keyframe ``k``: level-0 ``rmse`` (intensity units), ``ok``, whether
    its pose was ``used`` as the initial guess, its distance to the IMU prediction
    (m, rad) and the wall time (ms)."""

    k: int
    t_ns: int
    rmse: float
    ok: bool
    used: bool
    dist_m: float
    angle_rad: float
    ms: float


@dataclass(frozen=True)
class PointSnapshot:
    """Points seen in the newest keyframe: ``uv`` (N, 2) normalized cam0 coordinates,
    ``rmse`` (N,) residual RMSE (intensity units) at the current estimate (stereo term
    for points hosted there, else the temporal term), ``hosted`` (N,) bool,
    ``inv_depth`` (N,) inverse depth (1/m) in that keyframe's cam0 at the estimate."""

    k: int
    t_ns: int
    uv: np.ndarray
    rmse: np.ndarray
    hosted: np.ndarray
    inv_depth: np.ndarray | None = None


def _stack(patches: list[HostPatch]) -> HostPatch:
    return HostPatch(*(np.concatenate([getattr(p, f) for p in patches])
                       for f in ("uv", "bearing", "intensity", "grad_sq", "valid")))


class PhotometricSource:
    """The direct-mode factor source (module docstring); ``rig`` the stereo geometry."""

    key_dims = {"a": 2, "s": 2, "r": 1}

    def __init__(self, est, rig: StereoRig, cfg: DirectConfig) -> None:
        self.est, self.rig, self.cfg = est, rig, cfg
        pc = cfg.points
        self.params = PhotometricParams(pc.sigma_I, pc.grad_c, pc.huber_k)
        self.stereo_params = PhotometricParams(pc.sigma_I, pc.grad_c, pc.huber_k, pc.stereo_weight)
        self.kfs: dict[int, KeyframeData] = {}
        self.points: dict[int, Point] = {}
        self.tracks: list[TrackRecord] = []
        self.health = FactorHealth()
        self.n_points_total = 0
        self.n_factors_built = 0
        self._pending: list[tuple[Point, int]] = []
        self.n_outliers = 0
        self.last_stats: dict = {}
        a, b = pc.affine_sigma
        self._ab_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([a, b]))

    # ------------------------------------------------------------- protocol
    def observe(self, k: int, frame) -> None:
        """Build keyframe k's data from ``frame.images`` (left, right)."""
        imgs = getattr(frame, "images", ())
        if len(imgs) < 2:
            raise ValueError(f"direct mode: keyframe {k} packet has no stereo images")
        self.kfs[k] = build_keyframe(k, frame.t_ns, imgs[0], imgs[1], self.rig, self.cfg)

    def prepare_update(self, k: int, pred: gtsam.NavState, leaving: list[int],
                       g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict) -> list[int]:
        removals: list[int] = []
        self.last_stats = {"k": k, "extended": 0, "rejected": 0, "new": 0, "outliers": 0}
        self._forget(set(leaving))
        self._remove_outliers(g, stamps, removals)
        kd = self.kfs.get(k)
        if kd is None:
            return removals
        vals = self.est.values
        for f in sorted(self.kfs):     # keyframe 0 / restart keyframe: keys not yet inserted
            fd = self.kfs[f]
            if f < k and not fd.in_graph and vals.exists(X(f)):
                self._insert_keyframe(fd, vals.atPose3(X(f)), np.zeros(2), g, v, stamps, None)
        ab_k = self._track(k, kd, pred, v)
        T_k = v.atPose3(X(k))
        occupied = self._extend_points(k, T_k, ab_k, v)
        self._insert_keyframe(kd, T_k, ab_k, g, v, stamps, occupied)
        for p in self.points.values():    # (re)build the factors of new / extended points
            if p.dirty:
                removals.extend(p.factor_indices)
                p.factor_indices = []
                self._add_factor(p, g)
                p.dirty = False
        return removals

    def record_factor_indices(self, indices) -> None:
        idx = list(indices)
        for p, pos in self._pending:
            p.factor_indices.append(int(idx[pos]))
        self._pending = []

    def reset(self) -> None:
        """After a solver restart: forget points and keys; the restart keyframe's images
        are kept and its keys inserted at the next keyframe."""
        self.points = {}
        self._pending = []
        kd = self.kfs.get(self.est.k)
        self.kfs = {} if kd is None else {kd.k: kd}
        if kd is not None:
            kd.in_graph = False

    # ------------------------------------------------------------ internals
    def _target_rmse(self, pts: list[Point], h: int, j: int, v: gtsam.Values | None = None,
                     T_j: gtsam.Pose3 | None = None, ab_j: np.ndarray | None = None):
        """Residual RMSE (N,) (intensity units), inside fraction (N,) and the evaluation
        of host ``h``'s points ``pts`` in keyframe ``j``, at ``v`` (falling back on the
        estimate) or, when given, at ``T_j`` / ``ab_j`` for keyframe j."""
        rho = np.array([self._value(v, p.key)[0] for p in pts])
        ev = temporal_eval(self._value(v, X(h), True), self._value(v, X(j), True) if T_j is None else T_j,
                           rho, self._value(v, A(h)), self._value(v, A(j)) if ab_j is None else ab_j,
                           _stack([p.patch for p in pts]), self.kfs[j].left, self.rig.K0, self.rig.T_b_c)
        n_in = ev.valid.sum(1)
        return np.sqrt((ev.r ** 2).sum(1) / np.maximum(n_in, 1)), n_in / ev.valid.shape[1], ev

    def _remove_outliers(self, g, stamps, removals: list[int]) -> None:
        """Check every point in the graph at the current estimate (DSO practice: the
        residuals after the update). A target whose RMSE exceeds ``max_target_rmse`` or
        that left the image (occlusion, depth discontinuity, misfit) is dropped: the
        point's factor is rebuilt without it and the point stops gaining targets. A
        point with an inverse depth outside the depth range, or with no target left,
        loses its factor and its key is marginalized with a weak prior (like
        ``LandmarkManager._retire_key``)."""
        vals, pc = self.est.values, self.cfg.points
        pts = [p for p in self.points.values()
               if p.factor_indices and vals.exists(p.key) and vals.exists(X(p.host))]
        bad = set()
        for p in pts:
            rho = float(vals.atVector(p.key)[0])
            if not 1.0 / pc.max_depth_m <= rho <= 1.0 / pc.min_depth_m:
                bad.add(p.pid)
        groups: dict[tuple[int, int], list[Point]] = {}
        for p in pts:
            for j in p.targets:
                if p.pid not in bad and vals.exists(X(j)) and j in self.kfs:
                    groups.setdefault((p.host, j), []).append(p)
        dropped = 0
        for (h, j), grp in groups.items():
            rmse, inside, _ = self._target_rmse(grp, h, j)
            for p, o in zip(grp, (rmse > pc.max_target_rmse) | (inside < 0.5)):
                if o:
                    p.targets.remove(j)
                    p.active, p.dirty = False, True
                    dropped += 1
        bad.update(p.pid for p in pts if p.dirty and not p.targets)
        for pid in bad:
            p = self.points.pop(pid)
            removals.extend(p.factor_indices)
            p.factor_indices = []
            g.add(gtsam.PriorFactorVector(p.key, np.asarray(vals.atVector(p.key), float), _WEAK))
            stamps[p.key] = 0.0
        self.n_outliers += len(bad)
        self.last_stats.update(outliers=len(bad), dropped=dropped)

    def _forget(self, leave: set[int]) -> None:
        self.points = {i: p for i, p in self.points.items() if p.host not in leave}
        for f in leave:
            self.kfs.pop(f, None)

    def _value(self, v: gtsam.Values | None, key: int, pose: bool = False):
        src = v if v is not None and v.exists(key) else self.est.values
        return src.atPose3(key) if pose else np.asarray(src.atVector(key), float)

    def _latest_in_graph(self, k: int) -> KeyframeData | None:
        vals = self.est.values
        cands = [f for f, fd in self.kfs.items() if f < k and fd.in_graph and vals.exists(A(f))]
        return self.kfs[max(cands)] if cands else None

    def _track(self, k: int, kd: KeyframeData, pred: gtsam.NavState, v: gtsam.Values) -> np.ndarray:
        """TrackFrame of keyframe k against the previous keyframe; the guess of A(k)."""
        prev = self._latest_in_graph(k)
        if prev is None:
            return np.zeros(2)
        vals, T_b_c, pc = self.est.values, self.rig.T_b_c, self.cfg.points
        ab_p = np.asarray(vals.atVector(A(prev.k)), float)
        T_w_cp = vals.atPose3(X(prev.k)).compose(T_b_c)
        T_pred = v.atPose3(X(k))
        t0 = time.perf_counter()
        res = track_frame(prev.reference(ab_p, self.cfg), kd.image,
                          T_w_cp.between(T_pred.compose(T_b_c)), ab_p, self.cfg.track)
        ms = (time.perf_counter() - t0) * 1e3
        T_tr = T_w_cp.compose(res.T_kf_new).compose(T_b_c.inverse())
        d = T_pred.between(T_tr)
        dist, ang = float(np.linalg.norm(d.translation())), float(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation())))
        used = bool(res.ok and pc.use_track_guess and dist <= pc.track_gate_m and ang <= pc.track_gate_rad)
        if used:
            v.update(X(k), T_tr)
        self.tracks.append(TrackRecord(k, kd.t_ns, res.rmse, res.ok, used, dist, ang, ms))
        if not res.ok:
            log.warning("TrackFrame failed at keyframe %d: rmse %.1f (IMU prediction kept)", k, res.rmse)
        return np.array([res.a, res.b]) if res.ok else ab_p

    def _extend_points(self, k: int, T_k: gtsam.Pose3, ab_k: np.ndarray, v) -> np.ndarray:
        """Add target k to the active points that pass the checks; (M, 2) target pixels."""
        pc = self.cfg.points
        by_host: dict[int, list[Point]] = {}
        for p in self.points.values():
            if p.active:
                by_host.setdefault(p.host, []).append(p)
        hits = []
        for h, pts in by_host.items():
            rmse, inside, ev = self._target_rmse(pts, h, k, v, T_k, ab_k)
            ok = (inside >= pc.min_inside) & (rmse <= pc.max_target_rmse)
            self.last_stats["rejected"] += int((~ok).sum())
            self.last_stats["extended"] += int(ok.sum())
            for p, good, uv in zip(pts, ok, ev.uv[:, 4]):
                if not good:
                    p.active = False
                    continue
                p.targets.append(k)
                p.dirty = True
                p.active = len(p.targets) < pc.max_targets
                hits.append(uv)
        return np.array(hits).reshape(-1, 2)

    def _add_factor(self, p: Point, g: gtsam.NonlinearFactorGraph) -> None:
        h = self.kfs[p.host]
        keys = [X(p.host), p.key, A(p.host), S(p.host)]
        for j in p.targets:
            keys += [X(j), A(j)]
        stereo = StereoTerm(h.right, self.rig.K1, self.rig.T_c1_c0, self.stereo_params)
        self._pending.append((p, int(g.size())))
        g.add(point_factor(keys, p.patch, [self.kfs[j].left for j in p.targets], self.rig.K0,
                           self.rig.T_b_c, self.params, stereo, self.health))
        self.n_factors_built += 1

    def _insert_keyframe(self, kd: KeyframeData, T_w_b: gtsam.Pose3, ab: np.ndarray, g, v, stamps,
                         occupied: np.ndarray | None) -> None:
        """A(k), S(k) with their priors, then new points hosted in kd."""
        t = kd.t_ns * 1e-9
        v.insert(A(kd.k), np.asarray(ab, float))
        v.insert(S(kd.k), kd.ab_right.copy())
        g.add(gtsam.PriorFactorVector(A(kd.k), np.zeros(2), self._ab_noise))
        g.add(gtsam.PriorFactorVector(S(kd.k), kd.ab_right.copy(), self._ab_noise))
        stamps[A(kd.k)] = stamps[S(kd.k)] = t
        kd.in_graph = True
        free = self.cfg.points.max_active - sum(p.active for p in self.points.values())
        idx = self._new_point_indices(kd, occupied, free)
        self.last_stats["new"] += len(idx)
        patches = make_host_patch(kd.left, kd.uv[idx], self.rig.K0)
        for j, i in enumerate(idx):
            self.n_points_total += 1
            p = Point(self.n_points_total, R(self.n_points_total), kd.k, kd.uv[i].copy(),
                      patches.subset(np.array([j])), [], [])
            v.insert(p.key, np.array([kd.idepth[i]]))
            stamps[p.key] = t
            self.points[p.pid] = p

    def _new_point_indices(self, kd: KeyframeData, occupied: np.ndarray | None, free: int) -> np.ndarray:
        """Candidates at least ``min_spacing_px`` (grid cells) from the occupied pixels,
        evenly thinned to ``free``."""
        if free <= 0 or len(kd.uv) == 0:
            return np.zeros(0, int)
        cell = max(self.cfg.points.min_spacing_px, 1.0)
        keep = np.ones(len(kd.uv), bool)
        if occupied is not None and len(occupied):
            occ = {(int(a), int(b)) for a, b in np.floor(occupied / cell)}
            cells = np.floor(kd.uv / cell).astype(int)
            keep = np.array([(a, b) not in occ for a, b in cells])
        idx = np.flatnonzero(keep)
        if len(idx) > free:
            idx = idx[np.linspace(0, len(idx) - 1, free).round().astype(int)]
        return idx

    # ------------------------------------------------------------- outputs
    def n_active(self) -> int:
        return sum(p.active for p in self.points.values())

    def snapshot(self) -> PointSnapshot | None:
        """The points seen in the newest keyframe at the current estimate (for display)."""
        vals = self.est.values
        ks = [f for f, fd in self.kfs.items() if fd.in_graph and vals.exists(A(f))]
        if not ks:
            return None
        k = max(ks)
        kd = self.kfs[k]
        uv, rmse, hosted, inv_depth = [], [], [], []
        groups: dict[int, list[Point]] = {}
        for p in self.points.values():
            if not vals.exists(p.key):
                continue
            if p.host == k:
                rho_p = vals.atVector(p.key)
                ev = stereo_eval(rho_p, vals.atVector(S(k)), p.patch, kd.right,
                                 self.rig.K1, self.rig.T_c1_c0)
                uv.append(p.uv), hosted.append(True), inv_depth.append(float(rho_p[0]))
                rmse.append(np.sqrt(np.mean(ev.r[ev.valid] ** 2)) if ev.valid.any() else np.nan)
            elif k in p.targets:
                groups.setdefault(p.host, []).append(p)
        T_ck_w = vals.atPose3(X(k)).compose(self.rig.T_b_c).inverse()
        for h, pts in groups.items():
            rho = np.array([vals.atVector(p.key)[0] for p in pts])
            patch = _stack([p.patch for p in pts])
            ev = temporal_eval(vals.atPose3(X(h)), vals.atPose3(X(k)), rho, vals.atVector(A(h)),
                               vals.atVector(A(k)), patch, kd.left, self.rig.K0, self.rig.T_b_c)
            n = np.maximum(ev.valid.sum(1), 1)
            uv.extend(ev.uv[:, 4]), hosted.extend([False] * len(pts))
            rmse.extend(np.sqrt((ev.r ** 2).sum(1) / n))
            T_ck_ch = T_ck_w.compose(vals.atPose3(X(h)).compose(self.rig.T_b_c)).matrix()
            p_ck = (patch.bearing[:, 4] / rho[:, None]) @ T_ck_ch[:3, :3].T + T_ck_ch[:3, 3]
            inv_depth.extend(1.0 / p_ck[:, 2])
        uvn = self.rig.K0.unproject(np.array(uv).reshape(-1, 2))[:, :2]
        return PointSnapshot(k, kd.t_ns, uvn, np.array(rmse, float), np.array(hosted, bool),
                             np.array(inv_depth, float))
