"""Photometric points as a ``FactorSource`` (``vio.backend.keyframe_api``) of the estimator
(``Estimator.sources``).

One factor per host keyframe (``factors.photometric_host``): the host's points, their
inverse depths eliminated inside the factor (refined at each linearization, Schur
complement), observed in the next ``max_targets`` keyframes. Keys next to the
backend's X/V/B: ``A(k)`` = [a, b] of keyframe k's left image (I ~ e^a I_0 + b). The
pose keys X(k) are T_w_b (body); the factors use the calibrated, fixed T_b_c of cam0
and T_c1_c0; the right image's affine relative to the left is estimated once per
keyframe from the stereo matches (``vio.direct.keyframe.right_affine``) and held.

Per keyframe k (``prepare_update``):

1. hosts whose keyframe leaves the window are forgotten (the smoother marginalizes
   their factor with X(host));
2. TrackFrame (seed Algorithm 3) aligns keyframe k to the previous keyframe (its points
   and the window's, ``vio.direct.coarse_ref``) from the IMU prediction; its pose becomes
   the initial guess of X(k) when it converged and agrees with the prediction
   (``PointsConfig.track_gate_*``, off by default), its affine the guess of A(k); its
   result is kept in ``tracks`` (failure signal);
3. every host with fewer than ``max_targets`` targets whose live points are at least
   ``min_visible`` inside keyframe k (at the initial guess) gains target k: its factor
   is rebuilt (remove + add); the others stop gaining targets;
4. A(k) gets a weak prior, and keyframe k becomes a host with its ``max_points``
   best-spread candidates (stereo epipolar depths, filled up with temporal ones where the
   stereo search placed fewer, ``vio.direct.temporal``; made at the first reader after
   k's update, its factor appears with its first target).

With ``PointsConfig.exposure_td`` (and td estimated) each host factor also carries td's
key and sees its frames at their exposure times, moved along the body twists kept at
their insertion (``factors.photometric_host.HostTiming``). With a rolling shutter
(cam0's ``line_time_s``, for both cameras) each image row is taken at its own time along
the same twists (``factors.photometric_host.HostShutter``).

Outliers (a (point, target) pair off the image or above ``outlier_rms``, a point whose
stereo match fails or whose depth leaves the range) are switched off inside the
factor at linearization (``factors.photometric_kernel``). Keyframe 0 (and the restart
keyframe after a solver recovery) only gets ``observe``: its keys are inserted at the
next keyframe.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.adapter import FactorHealth
from factors.photometric import PhotometricParams, make_host_patch
from factors.photometric_host import (HostParams, HostPoints, HostShutter, HostTiming, StereoHost,
                                      host_factor)
from vio.backend.graph import TD, A, B, V, X
from vio.backend.motion import body_motion
from vio.direct.config import DirectConfig
from vio.direct.coarse_ref import host_in_camera
from vio.direct.keyframe import KeyframeData, StereoRig, build_keyframe
from vio.direct.records import PointSnapshot, TrackRecord, snapshot
from vio.direct.source_track import TrackFrameStep
from vio.direct.temporal import host_candidates
from vio.io.euroc import read_image

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Host:
    """One host keyframe ``k``: its points (``pts``: patches, inverse depths, masks),
    host pixels ``uv`` (N, 2, undistorted px), targets (keyframe indices) and the
    smoother index of its factor (None before the first target)."""

    k: int
    uv: np.ndarray
    pts: HostPoints
    targets: list
    factor_index: int | None = None
    open: bool = True


class PhotometricSource(TrackFrameStep):
    """The direct-mode factor source (module docstring); ``rig`` the stereo geometry."""

    key_dims = {"a": 2}

    def __init__(self, est, rig: StereoRig, cfg: DirectConfig) -> None:
        self.est, self.rig, self.cfg = est, rig, cfg
        self.features = None          # the newest keyframe's FeatureFrame (``observe``)
        pc = cfg.points
        self.key_thresholds = {"a": tuple(pc.affine_relinearize)}
        self.params = HostParams(PhotometricParams(pc.sigma_I, pc.grad_c, pc.huber_k),
                                 pc.stereo_weight, pc.outlier_rms, pc.refine_iters,
                                 1.0 / pc.max_depth_m, 1.0 / pc.min_depth_m, pc.damping)
        self.kfs: dict[int, KeyframeData] = {}
        self.twists: dict[int, np.ndarray] = {}   # body twist [omega_b, v_b] at insertion
        self.hosts: dict[int, Host] = {}
        self.tracks: list[TrackRecord] = []
        self.contradicted_k: int | None = None   # the last keyframe TrackFrame found the IMU wrong at
        self.health = FactorHealth()
        self.n_factors_built = 0
        self._pending: list[tuple[Host, int]] = []
        self._unhosted: list[KeyframeData] = []   # in the graph, Host not yet made (_host_pending)
        self.last_stats: dict = {}
        self._coverage: list[int] = []   # pairs in use at the last keyframes (``lost``)
        self._levels: list[float] = []   # the window's median pair RMS at the last keyframes
        a, b = pc.affine_sigma
        self._ab_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([a, b]))

    # ------------------------------------------------------------- protocol
    def observe(self, k: int, frame) -> None:
        """Build keyframe k's data from ``frame.images`` (left, right), read from
        ``frame.image_files`` when the packet carries none (the right one in the
        keyframe worker, ``vio.direct.keyframe.build_keyframe``)."""
        files = tuple(getattr(frame, "image_files", ())[:2])
        imgs = getattr(frame, "images", ()) or files
        if len(imgs) == 1 and len(files) == 2:    # cam0 decoded by the stage (vio.direct.mode)
            imgs = (imgs[0], files[1])
        if len(imgs) < 2:
            raise ValueError(f"direct mode: keyframe {k} packet has no stereo images")
        left = (self.rig.cam0.check_resolution(imgs[0], f"cam0 image at t={frame.t_ns} ns")
                if isinstance(imgs[0], np.ndarray) else read_image(imgs[0], self.rig.cam0))
        # the right image (or its file) goes to the keyframe worker with the points
        self.kfs[k] = build_keyframe(k, frame.t_ns, left, imgs[1], self.rig, self.cfg, background=True)
        self.features = getattr(frame, "features", None)   # TrackFrame's second guess (hybrid)

    def prepare_update(self, k: int, pred: gtsam.NavState, leaving: list[int],
                       g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict) -> list[int]:
        removals: list[int] = []
        self.last_stats = {"k": k, "extended": 0, "closed": 0}
        self._forget(set(leaving))
        kd = self.kfs.get(k)
        if kd is None:
            return removals
        vals = self.est.values
        for f in sorted(self.kfs):     # keyframe 0 / restart keyframe: keys not yet inserted
            fd = self.kfs[f]
            if f < k and not fd.in_graph and vals.exists(X(f)):
                self._insert_keyframe(fd, np.zeros(2), g, v, stamps)
                if self._twisted():
                    self.twists[f] = self._twist(f, vals.atPose3(X(f)), vals.atVector(V(f)),
                                                 vals.atConstantBias(B(f)))
        self._host_pending()      # before TrackFrame: temporal points join its reference
        ab_k = self._track(k, kd, pred, v)
        if self._twisted():
            self.twists[k] = self._twist(k, v.atPose3(X(k)), pred.velocity(), v.atConstantBias(B(k)))
        T_k = v.atPose3(X(k))
        for h in sorted(self.hosts):
            host = self.hosts[h]
            if not host.open:
                continue
            if self._visible_fraction(host, T_k) < self.cfg.points.min_visible:
                host.open = False
                self.last_stats["closed"] += 1
                continue
            host.targets.append(k)
            host.open = len(host.targets) < self.cfg.points.max_targets
            if host.factor_index is not None:
                removals.append(host.factor_index)
                host.factor_index = None
            self._add_factor(host, g)
            self.last_stats["extended"] += 1
        self._insert_keyframe(kd, ab_k, g, v, stamps)
        return removals

    def record_factor_indices(self, indices) -> None:
        idx = list(indices)
        for host, pos in self._pending:
            host.factor_index = int(idx[pos])
        self._pending = []

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild (``vio.backend.smoother``): old -> new factor slots."""
        for host in self.hosts.values():
            host.factor_index = remap.get(host.factor_index)

    def lost(self, k: int) -> str | None:
        """Why the photometric points have lost the frames, or None, judged after keyframe
        ``k``'s update at each of the last ``points.lost_keyframes`` keyframes that had
        another host with points in the window (DSO's tracking lost; a divergence for
        ``vio.backend.health``):

        * fewer than ``points.lost_fraction * points.max_points`` (point, keyframe) pairs
          in use for keyframe k (over the hosts observing it);
        * or the median raw residual RMS of the window's pairs at their last linearization
          above ``points.lost_rms``: a window whose pairs all fit badly, which the per-target
          outlier threshold (twice the median pair RMS) keeps in use."""
        pc = self.cfg.points
        if pc.lost_keyframes == 0 or not any(h.k != k and h.pts.alive.any() for h in self.hosts.values()):
            return None
        used = sum(int((h.pts.alive & h.pts.tmask[:, h.targets.index(k)]).sum())
                   for h in self.hosts.values() if k in h.targets)
        self._coverage = [*self._coverage, used][-pc.lost_keyframes:]
        rms = np.concatenate([h.pts.rms[h.pts.alive, :len(h.targets)].ravel() for h in self.hosts.values()])
        rms = rms[np.isfinite(rms) & (rms >= 0.0)]
        self._levels = [*self._levels, float(np.median(rms)) if rms.size else 0.0][-pc.lost_keyframes:]
        if len(self._coverage) < pc.lost_keyframes:
            return None
        floor = pc.lost_fraction * pc.max_points
        if max(self._coverage) < floor:
            return (f"photometric points lost: fewer than {floor:.0f} (point, keyframe) pairs in use "
                    f"at the last {pc.lost_keyframes} keyframes")
        if min(self._levels) > pc.lost_rms:
            return (f"photometric residuals: median pair RMS above {pc.lost_rms:g} (at least "
                    f"{min(self._levels):.0f}) at the last {pc.lost_keyframes} keyframes")
        return None

    def reset(self) -> None:
        """After a solver restart: forget hosts and keys; the restart keyframe's images
        are kept and its keys inserted at the next keyframe."""
        self._coverage = []
        self._levels = []
        self.hosts = {}
        self.twists = {}
        self._pending = []
        self._unhosted = []
        kd = self.kfs.get(self.est.k)
        self.kfs = {} if kd is None else {kd.k: kd}
        if kd is not None:
            kd.in_graph = False

    # ------------------------------------------------------------ internals
    def _forget(self, leave: set[int]) -> None:
        for f in leave:
            self.hosts.pop(f, None)
            self.kfs.pop(f, None)
            self.twists.pop(f, None)

    def _timed(self) -> bool:
        return self.cfg.points.exposure_td and self.est.cfg.calib.estimate_td

    def _twisted(self) -> bool:
        """The factors need the keyframes' body twists: exposure times or a rolling shutter."""
        return self._timed() or self.rig.cam0.line_time_s > 0.0

    def _shutter(self, frames: list[int]) -> HostShutter | None:
        """The rolling shutter of a factor over ``frames`` (host first): cam0's line time,
        each frame's cam0 twist, Ad(T_c_b) [omega_b, v_b], and the cameras' sensor rows
        through their lenses (None for a global shutter)."""
        lt = float(self.rig.cam0.line_time_s)
        if lt <= 0.0:
            return None
        return HostShutter(lt, np.array([self._cam_twist(f) for f in frames]), self.rig.rows0, self.rig.rows1)

    def _cam_twist(self, f: int) -> np.ndarray:
        """Keyframe f's cam0 twist [omega_c, v_c] (6,): Ad(T_c_b) of its body twist (zero
        without one)."""
        return self.rig.T_b_c.inverse().AdjointMap() @ self.twists.get(f, np.zeros(6))

    def _twist(self, f: int, T_w_b: gtsam.Pose3, v_w: np.ndarray, bias) -> np.ndarray:
        """Keyframe f's body twist [omega_b, v_b] (6,), ``vio.backend.motion.body_motion``."""
        td = float(self.est.values.atVector(TD)[0])
        return np.concatenate(body_motion(self.est, f, T_w_b, np.asarray(v_w, float), bias, td))

    def _latest_in_graph(self, k: int) -> KeyframeData | None:
        vals = self.est.values
        cands = [f for f, fd in self.kfs.items() if f < k and fd.in_graph and vals.exists(A(f))]
        return self.kfs[max(cands)] if cands else None

    def _visible_fraction(self, host: Host, T_w_bj: gtsam.Pose3) -> float:
        """Share of ``host``'s points alive, in front of and inside a frame at ``T_w_bj``."""
        T = T_w_bj.compose(self.rig.T_b_c).between(self.est.values.atPose3(X(host.k)).compose(self.rig.T_b_c))
        uv, _, front = host_in_camera(self.rig.K0, T, host.uv, host.pts.rho)
        w, h = self.rig.cam0.resolution
        b = 4.0
        ok = front & host.pts.alive & (uv[:, 0] >= b) & (uv[:, 0] < w - b) & (uv[:, 1] >= b) & (uv[:, 1] < h - b)
        return float(ok.sum()) / max(len(host.uv), 1)

    def _add_factor(self, host: Host, g: gtsam.NonlinearFactorGraph) -> None:
        kd = self.kfs[host.k]
        keys = [X(host.k), A(host.k)]
        for j in host.targets:
            keys += [X(j), A(j)]
        stereo = StereoHost(kd.right._stack, self.rig.K1, self.rig.T_c1_c0, kd.ab_right)
        timing = None
        frames = [host.k, *host.targets]
        if self._timed():
            keys.append(TD)
            timing = HostTiming(np.array([self.twists.get(f, np.zeros(6)) for f in frames]),
                                np.array([self.est.rates.td_obs(f) for f in frames]))
        self._pending.append((host, int(g.size())))
        g.add(host_factor(keys, host.pts, [self.kfs[j].left._stack for j in host.targets],
                          self.rig.K0, self.rig.T_b_c, self.params, stereo, self.health, timing,
                          self._shutter(frames)))
        self.n_factors_built += 1

    def _insert_keyframe(self, kd: KeyframeData, ab: np.ndarray, g, v, stamps) -> None:
        """A(k) with its prior; keyframe k becomes a host of its candidate points at the
        first reader of the hosts (``_host_pending``), so the keyframe worker builds the
        points while the smoother update of keyframe k runs (no host factor needs them
        before keyframe k + 1)."""
        v.insert(A(kd.k), np.asarray(ab, float))
        g.add(gtsam.PriorFactorVector(A(kd.k), np.zeros(2), self._ab_noise))
        stamps[A(kd.k)] = kd.t_ns * 1e-9
        kd.in_graph = True
        self._unhosted.append(kd)

    def _host_pending(self) -> None:
        """Make the Host of every keyframe inserted since (waits for its points; fills
        them up with temporal depths, ``vio.direct.temporal.host_candidates``)."""
        for kd in self._unhosted:
            if self.kfs.get(kd.k) is not kd:
                continue
            uv, rho, stereo = host_candidates(kd, self.kfs, self.est.values, self.rig, self.cfg)
            if len(uv) == 0:
                continue
            patch = make_host_patch(kd.left, uv, self.rig.K0)
            pts = HostPoints.create(patch, rho, self.cfg.points.grad_c, self.cfg.points.max_targets, stereo)
            self.hosts[kd.k] = Host(kd.k, uv.copy(), pts, [])
        self._unhosted = []

    # ------------------------------------------------------------- outputs
    def n_active(self) -> int:
        self._host_pending()
        return int(sum(h.pts.alive.sum() for h in self.hosts.values()))

    def live_points(self) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
        """(host k, host pixels (N, 2), inverse depths (N,), point indices (N,)) of the
        live points of every host whose pose is in the estimate."""
        self._host_pending()
        out = []
        for h, host in self.hosts.items():
            if self.est.values.exists(X(h)):
                i = np.flatnonzero(host.pts.alive)
                out.append((h, host.uv[i], host.pts.rho[i], i))
        return out

    def snapshot(self) -> PointSnapshot | None:
        """The live points seen in the newest keyframe at the current estimate (display,
        ``vio.direct.records.snapshot``)."""
        self._host_pending()
        return snapshot(self.hosts, self.kfs, self.est.values, self.rig)
