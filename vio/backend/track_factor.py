"""The factor of one landmark over its cam0 and cam1 observations.

Same factor as ``graph.build_stereo_factor`` (a track with cam1 matches) and
``graph.build_landmark_factor`` (cam0 only): keys ``[L, T_b_c, X(anchor), X(f1..fk)]``
(+ ``td``), residuals of the cam0 observations of the non-anchor keyframes, then of the
cam1 observations of every keyframe that has one, evaluated by
``factors.track_kernel`` (cam1 as cam0 of the virtual body ``T_w_b C``). The rows
(velocities, offsets, tangent bases) come from ``vio.backend.track_arrays``, built for
all tracks of an update at once. The numbers are those of the two builders (same kernel,
same inputs; tests/test_factor_speedups.py compares the linearizations).
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors import track_kernel
from factors.adapter import custom_factor
from factors.stack import Member
from factors.stereo import StereoRig
from vio.backend import graph
from vio.backend.config import BackendConfig
from vio.backend.landmarks import Track
from vio.backend.track_arrays import TrackRows

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


def track_member(track: Track, frames: list[int], rows: TrackRows, rig: StereoRig | None,
                 cfg: BackendConfig, sigma: float, at: graph.LinPoint | None = None) -> Member:
    """The residual of ``track`` over ``frames`` (anchor first), for a factor or a stack
    (``factors.stack``).

    ``rows``: the track's residual rows (``vio.backend.track_arrays.track_rows``, cam1
    rows only with a rig); ``rig``: the stereo rig (None: mono); ``sigma`` (normalized
    units) the observation noise; ``at``: the estimate for the anchor-noise whitening
    (none without it).
    """
    robust, td_key = graph._vision_options(cfg)
    vc = cfg.vision
    uv, vel_all, target, right, offset, basis = rows.uv, rows.vel, rows.target, rows.right, rows.offset, rows.basis
    C, ad_inv = (rig.C, rig.ad_inv) if rig is not None and right.any() else (_EYE4, _EYE6)
    a_uv, a_vel, a_off = rows.a_uv, rows.a_vel, rows.a_off
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
