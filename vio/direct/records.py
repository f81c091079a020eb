"""What the photometric source reports besides its factors: TrackFrame's outcome at each
keyframe and the newest keyframe's points (``vio.direct.source.PhotometricSource``; the
Rerun sink draws the points, ``vio.viz``)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors.photometric import temporal_eval
from vio.backend.graph import A, X


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


def snapshot(hosts: dict, kfs: dict, vals: gtsam.Values, rig) -> PointSnapshot | None:
    """The live points of ``hosts`` (``vio.direct.source.Host`` by keyframe) seen in the
    newest keyframe of ``kfs`` in ``vals`` (its own points and those of the hosts that
    target it, at the current estimate); ``rig`` the stereo rig. None before any."""
    ks = [f for f, fd in kfs.items() if fd.in_graph and vals.exists(A(f))]
    if not ks:
        return None
    k = max(ks)
    kd = kfs[k]
    uv, rmse, hosted, inv_depth = [], [], [], []
    T_ck_w = vals.atPose3(X(k)).compose(rig.T_b_c).inverse()
    for h, host in hosts.items():
        i = np.flatnonzero(host.pts.alive)
        if h == k:
            uv.extend(host.uv[i]), hosted.extend([True] * len(i)), rmse.extend([np.nan] * len(i))
            inv_depth.extend(host.pts.rho[i])
        elif k in host.targets and len(i):
            ev = temporal_eval(vals.atPose3(X(h)), vals.atPose3(X(k)), host.pts.rho[i],
                               vals.atVector(A(h)), vals.atVector(A(k)), host.pts.patch.subset(i),
                               kd.left, rig.K0, rig.T_b_c)
            n = np.maximum(ev.valid.sum(1), 1)
            uv.extend(ev.uv[:, 4]), hosted.extend([False] * len(i))
            rmse.extend(np.sqrt((ev.r ** 2).sum(1) / n))
            T_ck_ch = T_ck_w.compose(vals.atPose3(X(h)).compose(rig.T_b_c)).matrix()
            bear = host.pts.patch.subset(i).bearing[:, 4]
            p_ck = (bear / host.pts.rho[i][:, None]) @ T_ck_ch[:3, :3].T + T_ck_ch[:3, 3]
            inv_depth.extend(1.0 / p_ck[:, 2])
    uvn = rig.K0.unproject(np.array(uv).reshape(-1, 2))[:, :2]
    return PointSnapshot(k, kd.t_ns, uvn, np.array(rmse, float), np.array(hosted, bool),
                         np.array(inv_depth, float))
