"""The factor of one landmark over its cam0 and cam1 observations, built in one pass.

Same factor as ``graph.build_stereo_factor`` (a track with cam1 matches) and
``graph.build_landmark_factor`` (cam0 only): keys ``[L, T_b_c, X(anchor), X(f1..fk)]``
(+ ``td``), residuals of the cam0 observations of the non-anchor keyframes, then of the
cam1 observations of every keyframe that has one, evaluated by
``factors.track_kernel`` (cam1 as cam0 of the virtual body ``T_w_b C``). Those builders
went through ``make_track`` / ``make_stereo_track``, ``_cam0_shifts`` and the
anchor-Jacobian helpers, ~40 small numpy and Python calls per landmark at every keyframe
(~17 % of the backend's time on real MH_01 stereo); here the arrays are gathered once
(the td velocity caps and row offsets are still ``graph._cam0_shifts`` / ``_td_velocity``).
The numbers are those of the two builders (same kernel, same inputs;
tests/test_factor_speedups.py compares the linearizations).
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors import track_kernel
from factors.adapter import custom_factor
from factors.projection import tangent_basis
from factors.stack import Member
from factors.stereo import StereoRig
from vio.backend import graph
from vio.backend.config import BackendConfig
from vio.backend.landmarks import Track

_EYE4, _EYE6 = np.eye(4), np.eye(6)
_NOISE: dict[tuple[int, float], gtsam.noiseModel.Base] = {}


def _noise(m: int, sigma: float) -> gtsam.noiseModel.Base:
    """Isotropic noise of dimension m (shared: GTSAM noise models are immutable)."""
    key = (m, sigma)
    if key not in _NOISE:
        _NOISE[key] = gtsam.noiseModel.Isotropic.Sigma(m, sigma)
    return _NOISE[key]


def member_factor(mem: Member) -> gtsam.NonlinearFactor:
    """A ``track_member`` as its own ``gtsam.CustomFactor`` (isotropic noise)."""
    return custom_factor(_noise(mem.m, mem.sigma), mem.keys, mem.kinds, mem.fn, cache=True)  # fn is pure


def track_member(track: Track, frames: list[int], rig: StereoRig | None, cfg: BackendConfig,
                 sigma: float, line_time_s: float, vel: np.ndarray | None = None,
                 rvel: np.ndarray | None = None, at: graph.LinPoint | None = None) -> Member:
    """The residual of ``track`` over ``frames`` (anchor first), for a factor or a stack
    (``factors.stack``).

    ``rig``: the stereo rig (None: cam1 observations are ignored, mono); ``sigma``
    (normalized units) the observation noise; ``vel`` / ``rvel`` (n, 2): cam0 /
    cam1 td velocities of the observations in ``frames`` (default: the measured ones;
    ``rvel`` rows without a cam1 match are ignored); ``at``: the estimate for the
    anchor-noise whitening (none without it). The cam0 td velocities, row offsets and
    ``track.td_shift`` come from ``graph._cam0_shifts``, as in the two builders.
    """
    robust, td_key = graph._vision_options(cfg)
    vc = cfg.vision
    obs = [track.obs[f] for f in frames]
    v0, off = graph._cam0_shifts(track, frames, obs, vel, vc.td_velocity_max, line_time_s)
    uv, vel_all, target, right, offset, C, ad_inv = _layout(obs, v0, off, rig, rvel, vc.td_velocity_max)
    a_uv, a_vel, a_off = np.array(obs[0].uv, float), v0[0].copy(), float(off[0])
    basis = tangent_basis(uv)
    model = vc.model
    use_td = td_key is not None
    W = None
    if at is not None and vc.anchor_noise:
        bodies = np.array([at.poses[f].matrix() for f in frames])
        G = track_kernel.evaluate(bodies, target, right, C, ad_inv, at.T_b_c.matrix(), at.lam,
                                  at.td if use_td else None, a_uv, a_vel, a_off, uv, vel_all,
                                  offset, basis, model, sigma, None, None)[2]
        W = track_kernel.whitening(G)
    k = len(frames) - 1
    fkeys = [int(track.key), graph.EXTRINSIC] + [graph.X(f) for f in frames] + ([int(td_key)] if use_td else [])
    kinds = [1, "pose3", "pose3"] + ["pose3"] * k + ([1] if use_td else [])

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        bodies = np.array([T.matrix() for T in args[2:3 + k]])
        r, J, _ = track_kernel.evaluate(bodies, target, right, C, ad_inv, args[1].matrix(),
                                        float(args[0][0]), float(args[3 + k][0]) if use_td else None,
                                        a_uv, a_vel, a_off, uv, vel_all, offset, basis, model,
                                        sigma, robust, W)
        return r, J

    return Member(tuple(fkeys), tuple(kinds), fn, 2 * len(uv), float(sigma))


def _layout(obs: list, v0: np.ndarray, off: np.ndarray, rig: StereoRig | None,
            rvel: np.ndarray | None, vmax: float) -> tuple:
    """The residual rows of a track's observations ``obs`` (anchor first): the cam0 ones
    of the non-anchor keyframes, then the cam1 ones of every keyframe with a match (none
    without ``rig``). Returns ``uv``, ``vel`` (n, 2), ``target`` (n,) body index,
    ``right`` (n,) cam1 flags, ``offset`` (n,) and the rig's ``C`` (4, 4), ``Ad(C^-1)``
    (6, 6) (identities without cam1 rows). ``v0`` (n0, 2) / ``off`` (n0,): the cam0 td
    velocities and row offsets; ``rvel``: predicted cam1 velocities (None: measured)."""
    n0 = len(obs)
    st_i = [i for i, o in enumerate(obs) if o.right_uv is not None] if rig is not None else []
    n1 = len(st_i)
    n = n0 - 1 + n1
    if n == 0:
        raise ValueError("landmark track has no observation outside its anchor frame")
    uv, vel, offset = np.empty((n, 2)), np.empty((n, 2)), np.empty(n)
    target, right = np.empty(n, np.int64), np.zeros(n, np.bool_)
    if n0 > 1:
        uv[:n0 - 1] = [o.uv for o in obs[1:]]
    vel[:n0 - 1] = v0[1:]
    target[:n0 - 1] = np.arange(1, n0)
    offset[:n0 - 1] = off[1:]
    if not n1:
        return uv, vel, target, right, offset, _EYE4, _EYE6
    uv[n0 - 1:] = [obs[i].right_uv for i in st_i]
    rv = np.array([obs[i].right_velocity for i in st_i]) if rvel is None else np.asarray(rvel)[st_i]
    vel[n0 - 1:] = graph._td_velocity(rv, vmax)
    target[n0 - 1:] = st_i
    right[n0 - 1:] = True
    offset[n0 - 1:] = off[st_i]
    return uv, vel, target, right, offset, rig.C, rig.ad_inv
