"""Inverse depths of a keyframe's candidates that the stereo pair did not place, by an
epipolar search in an earlier keyframe's left image (seed eq. 4.1/4.2 with the
keyframes' baseline instead of the stereo one; DSO traces its immature points likewise,
over every new frame, and activates them once the search interval is small).

A host keyframe k takes its points' depths from the stereo pair (``vio.direct.keyframe``).
Candidates whose right-image search fails (a covered or blinded right camera, occlusion,
an edge along the stereo epipolar lines) get one more chance here once X(k) is estimated,
when the stereo ones are fewer than ``max_points``:

1. search in the left image of the one of the last ``temporal_refs`` keyframes before k
   whose camera centre lies farthest from k's (default 1: the previous keyframe), with the
   relative pose of the current estimate; keep a depth that passes the search's checks
   (``vio.direct.epipolar``), lies in ``PointsConfig``'s depth range and whose standard
   deviation (the match error along the line over the line's pixels per inverse depth) is
   at most ``temporal_max_rel_std`` of the inverse depth, so a short baseline or an edge
   along the line yields no point rather than a wrong one;
2. search again in each of the ``temporal_checks`` keyframes before those (``agree``): a
   depth the second baseline contradicts (beyond ``temporal_agree_k`` standard deviations)
   is dropped.

The host factor (``factors.photometric_host``) gives these points no static stereo term
(``HostPoints.stereo``). Real MH_01 (benchmarks/README.md, stop 56): with the right camera
covered for 2 s direct mode keeps its points and its ATE; wider baselines (3-5 keyframes
back) placed points whose errors let a covered window run away.
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.photometric import Pinhole
from vio.backend.graph import A, X
from vio.direct.config import DirectConfig
from vio.direct.epipolar import epipolar_search
from vio.direct.keyframe import KeyframeData, StereoRig
from vio.direct.select import spread



def widest_baseline(T_w_ck: gtsam.Pose3, refs: dict[int, gtsam.Pose3]) -> int | None:
    """Of ``refs`` (keyframe -> T_w_c), the keyframe whose camera centre is farthest from
    ``T_w_ck``'s (None when ``refs`` is empty)."""
    if not refs:
        return None
    c = T_w_ck.translation()
    return max(refs, key=lambda f: float(np.linalg.norm(refs[f].translation() - c)))


def temporal_depths(host: KeyframeData, ref: KeyframeData, T_cr_ch: gtsam.Pose3, gain: float,
                    K: Pinhole, cfg: DirectConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uv (K, 2), inverse depth (K,) 1/m, variance (K,) 1/m^2) of the host's unplaced
    candidates (``KeyframePoints.uv_rest``, undistorted cam0 pixels) that the search in
    ``ref``'s left image places (module docstring). ``T_cr_ch``: host camera -> reference
    camera (cam0 of both, intrinsics ``K``); ``gain``: log brightness of the reference
    relative to the host (a_ref - a_host)."""
    uv = host.points.uv_rest
    pc = cfg.points
    if len(uv) == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    ep = epipolar_search(host.left, ref.left, uv, K, K, T_cr_ch, cfg.epipolar, (gain, 0.0))
    rho = np.where(ep.ok, ep.idepth, 0.0)
    ok = ep.ok & (rho >= 1.0 / pc.max_depth_m) & (rho <= 1.0 / pc.min_depth_m)
    ok &= np.sqrt(np.where(ok, ep.variance, np.inf)) <= pc.temporal_max_rel_std * rho
    return uv[ok], ep.idepth[ok], ep.variance[ok]


def agree(host: KeyframeData, other: KeyframeData, uv: np.ndarray, rho: np.ndarray, var: np.ndarray,
          T_co_ch: gtsam.Pose3, gain: float, K: Pinhole, cfg: DirectConfig) -> np.ndarray:
    """(K,) bool: the inverse depths ``rho`` (variances ``var``) of the host pixels ``uv``
    agree with a second search in ``other``'s left image (``T_co_ch``: host camera ->
    other camera; ``gain`` a_other - a_host) within ``temporal_agree_k`` standard
    deviations of the difference. A point the second search does not place passes (no
    evidence): the test rejects a match whose depth the second baseline contradicts, as a
    wrong match on a repeated texture or along an edge does."""
    if len(uv) == 0:
        return np.zeros(0, bool)
    ep = epipolar_search(host.left, other.left, uv, K, K, T_co_ch, cfg.epipolar, (gain, 0.0))
    d2 = (np.where(ep.ok, ep.idepth, rho) - rho) ** 2
    return ~ep.ok | (d2 <= cfg.points.temporal_agree_k ** 2 * (var + np.where(ep.ok, ep.variance, 0.0)))


def host_candidates(kd: KeyframeData, kfs: dict[int, KeyframeData], values: gtsam.Values,
                    rig: StereoRig, cfg: DirectConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points keyframe ``kd`` hosts: (uv (N, 2), inverse depth (N,), stereo (N,) bool).
    Up to ``max_points`` of its stereo-placed candidates (evenly spread), then, when they
    are fewer and ``temporal_depth`` is on, as many temporally placed ones (``place``,
    once per keyframe: a keyframe hosted again after a restart reuses them)."""
    pc = cfg.points
    n_st = kd.n_stereo
    idx = spread(kd.uv[:n_st], pc.max_points)
    need = pc.max_points - len(idx)
    if need > 0 and pc.temporal_depth:
        if len(kd.uv) == n_st:
            place(kd, kfs, values, rig, cfg)
        idx = np.concatenate([idx, n_st + spread(kd.uv[n_st:], need)])
    return kd.uv[idx], kd.idepth[idx], idx < n_st


def place(kd: KeyframeData, kfs: dict[int, KeyframeData], values: gtsam.Values, rig: StereoRig,
          cfg: DirectConfig) -> None:
    """Place ``kd``'s unplaced candidates by ``temporal_depths`` against the widest-baseline
    one of the last ``temporal_refs`` keyframes of ``kfs`` in ``values`` and keep those
    that ``agree`` with the ``temporal_checks`` keyframes before (module docstring); they
    join the keyframe's points (``KeyframeData.add_points``: TrackFrame's reference too).
    Nothing happens before X(k) and A(k) are in ``values``."""
    pc = cfg.points
    if not (values.exists(X(kd.k)) and values.exists(A(kd.k))):
        return
    T_w_ch = values.atPose3(X(kd.k)).compose(rig.T_b_c)
    prev = [f for f in sorted(kfs) if f < kd.k and values.exists(X(f)) and values.exists(A(f))]
    refs = {f: values.atPose3(X(f)).compose(rig.T_b_c) for f in prev[-pc.temporal_refs:]}
    f = widest_baseline(T_w_ch, refs)
    if f is None:
        return
    a_k = float(values.atVector(A(kd.k))[0])
    gain = float(values.atVector(A(f))[0]) - a_k
    uv, rho, var = temporal_depths(kd, kfs[f], refs[f].between(T_w_ch), gain, rig.K0, cfg)
    others = [g for g in prev if g != f]
    for o in others[len(others) - min(pc.temporal_checks, len(others)):]:
        T_w_co = values.atPose3(X(o)).compose(rig.T_b_c)
        ok = agree(kd, kfs[o], uv, rho, var, T_w_co.between(T_w_ch),
                   float(values.atVector(A(o))[0]) - a_k, rig.K0, cfg)
        uv, rho, var = uv[ok], rho[ok], var[ok]
    if len(uv):
        kd.add_points(uv, rho, var)
