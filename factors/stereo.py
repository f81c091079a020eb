"""Stereo (second-camera) observations of an inverse-depth landmark.

The landmark is anchored in cam0 of keyframe a (``P_c0a = [u, v, 1] / lambda``);
an observation by cam1 of keyframe m (m may be a itself: the static stereo
constraint that gives depth at once) is the projection through
``T_w_c1m = T_w_bm * T_b_c1``. Writing ``T_b_c1 = C * T_b_c0`` with the constant
``C = T_b_c1 * T_b_c0^-1`` (the stereo rig is rigid and calibrated), the cam1 view is
the cam0 view of a *virtual body* ``T_w_bm * C``, so the batched projection kernel
of :mod:`factors.projection` (and its td variant) is reused unchanged. For GTSAM's
retraction, ``T Exp(xi) C = (T C) Exp(Ad_{C^-1} xi)``, hence
``dr/dxi_m = dr/dxi_virtual * Ad_{C^-1}``. The extrinsic key ``T_b_c0`` enters through
the anchor and the virtual-body projection with ``C`` held constant: exact when the
extrinsic is fixed (the default), a first-order approximation when it is estimated.

Keys: ``[lambda, T_b_c0, T_w_b_anchor, T_w_b_m1 ... T_w_b_mk]`` (+ ``td``), the
``m`` distinct and different from the anchor (right observations of the anchor
keyframe map onto the anchor key). Residuals: one 2-vector per observation.

Mixed tracks: ``cams`` marks each observation as cam1 (the virtual body ``T C``) or
cam0 (``C = I``, the plain projection factor of :mod:`factors.landmark`), so all
observations of a stereo landmark (left and right) share one factor and one Python
callback per linearization instead of two. A cam0 observation of the anchor
keyframe itself constrains nothing and is rejected.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence, Union

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.anchor_noise import AnchorWhitening
from factors import track_kernel
from factors.bearing_model import check_model, tangent_basis
from factors.projection import Projected, project_batch
from factors.robust import RobustKernel
from factors.td_projection import td_project_batch


@dataclass(frozen=True)
class StereoTrack:
    """Right-camera observations of one landmark.

    ``anchor_key`` and the anchor's cam0 observation ``anchor_uv`` (2,) with its
    velocity and time offset; ``target`` (n,) index of each observation's body key
    (0 = anchor, i >= 1 = ``keys[i - 1]``); ``uv`` (n, 2) cam1 normalized points,
    ``vel`` (n, 2) their velocities (1/s), ``offset`` (n,) row-time minus td_obs (s);
    ``C`` (4, 4) = ``T_b_c1 * T_b_c0^-1``; ``right`` (n,) bool: True for a cam1
    observation (virtual body ``T C``), False for a cam0 one (``C = I``).
    """

    anchor_key: int
    anchor_uv: np.ndarray
    anchor_vel: np.ndarray
    anchor_offset: float
    keys: tuple
    target: np.ndarray
    uv: np.ndarray
    vel: np.ndarray
    offset: np.ndarray
    C: np.ndarray
    ad_inv: np.ndarray
    basis: np.ndarray
    right: np.ndarray

    @property
    def n(self) -> int:
        return int(self.target.shape[0])


class StereoRig(NamedTuple):
    """``C = T_b_c1 T_b_c0^-1`` as a (4, 4) matrix and ``Ad(C^-1)`` (6, 6), computed once
    per rig instead of once per track (:func:`stereo_rig`)."""

    C: np.ndarray
    ad_inv: np.ndarray


def stereo_rig(C: gtsam.Pose3) -> StereoRig:
    """The constants of a rig ``C`` for :func:`make_stereo_track`."""
    return StereoRig(C.matrix(), C.inverse().AdjointMap())


def make_stereo_track(anchor_key: int, anchor_uv: np.ndarray, obs_keys: Sequence[int],
                      uv: np.ndarray, C: Union[gtsam.Pose3, StereoRig], anchor_vel: np.ndarray | None = None,
                      vel: np.ndarray | None = None, anchor_offset: float = 0.0,
                      offset: np.ndarray | None = None,
                      right: Sequence[bool] | None = None) -> StereoTrack:
    """Pack observations made from the body keys ``obs_keys``: cam1 observations
    (``right[i]`` True, the default) may come from the anchor, cam0 ones may not;
    each (key, camera) pair at most once. ``C``: the rig (a ``Pose3`` or its
    :func:`stereo_rig`)."""
    obs_keys = [int(k) for k in obs_keys]
    n = len(obs_keys)
    right_a = np.ones(n, bool) if right is None else np.asarray(right, bool).reshape(n)
    if n == 0:
        raise ValueError("stereo track without observations")
    pairs = list(zip(obs_keys, right_a.tolist()))
    if len(set(pairs)) != n:
        raise ValueError(f"stereo track repeats a (body key, camera) pair: {pairs}")
    if any(k == int(anchor_key) and not r for k, r in pairs):
        raise ValueError("a cam0 observation of the anchor keyframe constrains nothing")
    others = list(dict.fromkeys(k for k in obs_keys if k != int(anchor_key)))
    index = {k: i + 1 for i, k in enumerate(others)}
    index[int(anchor_key)] = 0
    uv = np.asarray(uv, float).reshape(n, 2)
    rig = C if isinstance(C, StereoRig) else stereo_rig(C)
    return StereoTrack(int(anchor_key), np.asarray(anchor_uv, float).reshape(2),
                       np.zeros(2) if anchor_vel is None else np.asarray(anchor_vel, float).reshape(2),
                       float(anchor_offset), tuple(others),
                       np.array([index[k] for k in obs_keys], dtype=np.int64), uv,
                       np.zeros((n, 2)) if vel is None else np.asarray(vel, float).reshape(n, 2),
                       np.zeros(n) if offset is None else np.asarray(offset, float).reshape(n),
                       rig.C, rig.ad_inv, tangent_basis(uv), right_a)


def stereo_keys(track: StereoTrack, lam_key: int, extrinsic_key: int,
                td_key: int | None = None) -> list[int]:
    keys = [int(lam_key), int(extrinsic_key), track.anchor_key, *track.keys]
    return keys + ([int(td_key)] if td_key is not None else [])


def _virtual_bodies(args: list, track: StereoTrack) -> np.ndarray:
    """(n, 4, 4): ``T_w_b`` of each observation's body key, times ``C`` for cam1 ones."""
    bodies = [T.matrix() for T in args[2:3 + len(track.keys)]]
    return np.array([bodies[t] @ track.C if rt else bodies[t]
                     for t, rt in zip(track.target.tolist(), track.right.tolist())])


def _project(args: list, track: StereoTrack, model: str, use_td: bool) -> Projected:
    k = len(track.keys)
    Tjs = _virtual_bodies(args, track)
    Ti, Tc, lam = args[2].matrix(), args[1].matrix(), float(args[0][0])
    if use_td:
        return td_project_batch(Ti, Tjs, Tc, lam, float(args[3 + k][0]), track.anchor_uv,
                                track.anchor_vel, track.anchor_offset, track.uv, track.vel,
                                track.offset, model, track.basis)
    return project_batch(Ti, Tjs, Tc, lam, track.anchor_uv, track.uv, model, track.basis)


def _kernel_eval(args: list, track: StereoTrack, model: str, sigma: float,
                 robust: RobustKernel | None, use_td: bool, whiten: AnchorWhitening | None):
    """``factors.track_kernel.evaluate`` of the track at ``args``."""
    k = len(track.keys)
    bodies = np.array([T.matrix() for T in args[2:3 + k]])
    return track_kernel.evaluate(bodies, track.target, track.right, track.C, track.ad_inv,
                                 args[1].matrix(), float(args[0][0]),
                                 float(args[3 + k][0]) if use_td else None, track.anchor_uv,
                                 track.anchor_vel, track.anchor_offset, track.uv, track.vel,
                                 track.offset, track.basis, model, sigma, robust, whiten)


def stereo_anchor_jacobian(args: list, track: StereoTrack, model: str = "pinhole",
                           use_td: bool = False) -> np.ndarray:
    """``G = dr/duv_anchor`` (2n, 2) at ``args`` (:func:`stereo_residual` order), for
    :func:`factors.anchor_noise.anchor_whitening`."""
    return _kernel_eval(args, track, model, 1.0, None, use_td, None)[2].reshape(2 * track.n, 2)


def stereo_residual(args: list, track: StereoTrack, model: str = "pinhole", sigma: float = 1.0,
                    robust: RobustKernel | None = None, use_td: bool = False,
                    whiten: AnchorWhitening | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residual (2n,) and Jacobian (2n, 13 + 6k [+1]) in :func:`stereo_keys` order.

    ``args``: ``[lambda (1,), T_b_c0, T_anchor, T_m1..T_mk]`` (+ ``td (1,)``); ``whiten``:
    constant whitening applied last (anchor noise, :func:`factors.anchor_noise.anchor_whitening`).
    One compiled pass (``factors.track_kernel``): each observation's body block
    (the virtual body ``T C`` for cam1) is mapped through ``Ad(C^-1)`` onto its body key's
    columns (the anchor's: 7), then the robust weights and the whitening.
    """
    check_model(model)
    robust = robust if robust is not None and robust.kind != "none" else None
    r, J, _ = _kernel_eval(args, track, model, sigma, robust, use_td, whiten)
    return r, J


def stereo_factor(track: StereoTrack, lam_key: int, extrinsic_key: int, sigma: float,
                  model: str = "pinhole", robust: RobustKernel | None = None,
                  td_key: int | None = None, health: FactorHealth | None = None,
                  whiten: AnchorWhitening | None = None) -> gtsam.CustomFactor:
    """``gtsam.CustomFactor`` of a landmark's right-camera (and, mixed, cam0) observations;
    ``whiten`` as in :func:`stereo_residual`."""
    check_model(model)
    keys = stereo_keys(track, lam_key, extrinsic_key, td_key)
    use_td = td_key is not None
    kinds = [1, "pose3", "pose3"] + ["pose3"] * len(track.keys) + ([1] if use_td else [])
    noise = gtsam.noiseModel.Isotropic.Sigma(2 * track.n, float(sigma))

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        return stereo_residual(args, track, model, sigma, robust, use_td, whiten)

    return custom_factor(noise, keys, kinds, fn, health)
