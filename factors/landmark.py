"""One factor per landmark carrying all its observations (vectorized projection factor).

Python callbacks cost ~50x a C++ factor, so instead of one ``CustomFactor`` per
observation this factor evaluates all n observations of a landmark in one compiled pass
(the same :func:`factors.projection.project_batch` / :func:`factors.td_projection.td_project_batch`
code as the single-observation factors) and hands the adapter one stacked Jacobian.
Measured (``benchmarks/bench_factor_cost.py``, 200 landmarks x 10 frames): ~4-5 us per
observation vs ~21 us for one CustomFactor per observation and ~0.5 us for
``GenericProjectionFactorCal3_S2``.

Keys, in order: ``[lambda, T_b_c, T_w_b_anchor, T_w_b_j1, ..., T_w_b_jn]`` plus ``td`` last
for the td variant. Residual: the n 2-vectors stacked, shape (2n,), normalized units, with
an isotropic noise ``sigma`` (normalized units, e.g. pixel sigma / focal length).

Observations in the anchor frame itself are dropped by :func:`make_track`: with
``T_w_bj == T_w_bi`` the transfer is the identity (``M = I, h = 0``), so the residual
``proj(m_i) - uv_i`` is a constant (zero for the anchor observation, also with td since
both sides shift identically) and constrains nothing. Each other frame may appear once.

Robust kernels are applied per 2-row block (IRLS): with ``s_k = |r_k| / sigma`` at the
current state, block k of the residual and Jacobian is multiplied by ``sqrt(w(s_k))``,
exactly what ``gtsam.noiseModel.Robust`` does to a single-observation factor.
(``noiseModel.Robust`` on this stacked factor would instead reweight the whole landmark by
its total norm.) The weights are treated as constants of the linearization, as in GTSAM,
so the returned Jacobian is ``sqrt(w) J`` and the factor's error (what LM uses to accept
steps) is ``0.5 * sum_k w(s_k) s_k^2``, an IRLS surrogate rather than ``sum rho(s_k)``:
Huber gives ``s^2/2`` inside and ``k s / 2`` outside (half the slope of rho), Cauchy gives
the bounded ``s^2 / (2 (1 + s^2/c^2))``. Both are robust, and equal rho for inliers.
Pass ``weights=`` to freeze the weights (used by the Jacobian tests).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.anchor_noise import AnchorWhitening
from factors import track_kernel
from factors.bearing_model import check_model, tangent_basis
from factors.projection import COL_LAM, COL_TC, COL_TI, COL_TJ, Projected, project_batch
from factors.robust import RobustKernel, block_sqrt_weights
from factors.td_projection import td_project_batch


@dataclass(frozen=True)
class LandmarkTrack:
    """All observations of one landmark, anchor first (build with :func:`make_track`).

    ``anchor_uv`` (2,), ``uv`` (n, 2): normalized-plane observations; ``keys`` (n,) the body
    pose keys of the n non-anchor frames. td variant: ``anchor_vel`` (2,), ``vel`` (n, 2)
    image velocities (normalized units / s); ``anchor_offset``, ``offset`` (n,) =
    ``row / ROWS * t_readout - td_obs`` (s), see :class:`factors.td_projection.TdObservation`.
    ``basis`` (n, 2, 3): sphere tangent bases of the raw ``uv``.
    """

    anchor_key: int
    anchor_uv: np.ndarray
    keys: tuple
    uv: np.ndarray
    anchor_vel: np.ndarray
    vel: np.ndarray
    anchor_offset: float
    offset: np.ndarray
    basis: np.ndarray

    @property
    def n(self) -> int:
        """Number of (non-anchor) observations."""
        return len(self.keys)


def make_track(anchor_key: int, anchor_uv: np.ndarray, keys: Sequence[int], uv: np.ndarray,
               anchor_vel: np.ndarray | None = None, vel: np.ndarray | None = None,
               anchor_offset: float = 0.0, offset: np.ndarray | None = None) -> LandmarkTrack:
    """Validate and pack a track; observations whose key is ``anchor_key`` are dropped.

    Raises ``ValueError`` on wrong shapes, repeated frame keys or no remaining observation.
    """
    keys_a = np.asarray(keys, dtype=np.int64).reshape(-1)
    n0 = keys_a.size
    uv = np.asarray(uv, dtype=float).reshape(n0, 2)
    vel = np.zeros((n0, 2)) if vel is None else np.asarray(vel, dtype=float).reshape(n0, 2)
    offset = np.zeros(n0) if offset is None else np.asarray(offset, dtype=float).reshape(n0)
    keep = keys_a != int(anchor_key)
    if not keep.all():
        keys_a, uv, vel, offset = keys_a[keep], uv[keep], vel[keep], offset[keep]
    if keys_a.size == 0:
        raise ValueError("landmark track has no observation outside its anchor frame")
    if len(set(keys_a.tolist())) != keys_a.size:
        raise ValueError(f"landmark track repeats a frame key: {keys_a.tolist()}")
    a_vel = np.zeros(2) if anchor_vel is None else np.asarray(anchor_vel, float).reshape(2)
    return LandmarkTrack(int(anchor_key), np.asarray(anchor_uv, dtype=float).reshape(2),
                         tuple(int(k) for k in keys_a), uv, a_vel, vel, float(anchor_offset),
                         offset, tangent_basis(uv))


def landmark_keys(track: LandmarkTrack, lam_key: int, extrinsic_key: int,
                  td_key: int | None = None) -> list[int]:
    """Factor keys ``[lambda, T_b_c, T_anchor, T_j1..T_jn] (+ td)``."""
    keys = [int(lam_key), int(extrinsic_key), track.anchor_key, *track.keys]
    return keys + ([int(td_key)] if td_key is not None else [])


@lru_cache(maxsize=256)
def _block_cols(n: int, use_td: bool) -> tuple:
    """Column ranges of the key blocks in the batched Jacobian (``factors.projection.COL_*``)."""
    ends = [COL_LAM, COL_TC, COL_TI, *range(COL_TJ, COL_TJ + 6 * n + 1, 6)]
    ends += [COL_TJ + 6 * n + 1] if use_td else []
    return tuple(zip(ends[:-1], ends[1:]))


def _project(args: list, track: LandmarkTrack, model: str, use_td: bool) -> Projected:
    n = track.n
    Tjs = np.array([T.matrix() for T in args[3:3 + n]])
    if use_td:
        return td_project_batch(args[2].matrix(), Tjs, args[1].matrix(), args[0][0], args[3 + n][0],
                                track.anchor_uv, track.anchor_vel, track.anchor_offset,
                                track.uv, track.vel, track.offset, model, track.basis)
    return project_batch(args[2].matrix(), Tjs, args[1].matrix(), args[0][0], track.anchor_uv,
                         track.uv, model, track.basis)


_EYE4, _EYE6 = np.eye(4), np.eye(6)


@lru_cache(maxsize=256)
def _layout(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``factors.track_kernel`` layout of a cam0-only track: observation o made by body
    o + 1, no cam1 observation."""
    return np.arange(1, n + 1, dtype=np.int64), np.zeros(n, dtype=np.bool_)


def _kernel_eval(args: list, track: LandmarkTrack, model: str, sigma: float,
                 robust: RobustKernel | None, use_td: bool, whiten: AnchorWhitening | None):
    """``factors.track_kernel.evaluate`` of the track at ``args``."""
    n = track.n
    target, right = _layout(n)
    bodies = np.array([T.matrix() for T in args[2:3 + n]])
    return track_kernel.evaluate(bodies, target, right, _EYE4, _EYE6, args[1].matrix(),
                                 float(args[0][0]), float(args[3 + n][0]) if use_td else None,
                                 track.anchor_uv, track.anchor_vel, track.anchor_offset, track.uv,
                                 track.vel, track.offset, track.basis, model, sigma, robust, whiten)


def landmark_anchor_jacobian(args: list, track: LandmarkTrack, model: str = "pinhole",
                             use_td: bool = False) -> np.ndarray:
    """``G = dr/duv_anchor`` (2n, 2) at ``args`` (:func:`landmark_residual` order), for
    :func:`factors.anchor_noise.anchor_whitening`."""
    return _kernel_eval(args, track, model, 1.0, None, use_td, None)[2].reshape(2 * track.n, 2)


def _evaluate(args: list, track: LandmarkTrack, model: str, sigma: float,
              robust: RobustKernel | None, use_td: bool, weights: np.ndarray | None,
              whiten: AnchorWhitening | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residual (2n,) and Jacobian (2n, sum of key dims), key blocks side by side.
    Without frozen ``weights``: one compiled pass (``factors.track_kernel``)."""
    n = track.n
    if weights is None:
        robust = robust if robust is not None and robust.kind != "none" else None
        r, J, _ = _kernel_eval(args, track, model, sigma, robust, use_td, whiten)
        return r, J
    p = _project(args, track, model, use_td)
    sw = np.sqrt(np.asarray(weights, dtype=float).reshape(n))
    r = p.r * sw[:, None]
    J = p.J * np.repeat(sw, 2)[:, None]
    if whiten is not None:   # anchor noise (constant W, like a noise model)
        return whiten.apply(r.reshape(2 * n)), whiten.apply(J)
    return r.reshape(2 * n), J


def landmark_residual(args: list, track: LandmarkTrack, model: str = "pinhole",
                      sigma: float = 1.0, robust: RobustKernel | None = None,
                      use_td: bool = False, weights: np.ndarray | None = None,
                      whiten: AnchorWhitening | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """Stacked residual (2n,) and one Jacobian block per key, in :func:`landmark_keys` order.

    ``args``: ``[lambda (1,), T_b_c, T_anchor, T_j1..T_jn]`` (+ ``td (1,)`` if ``use_td``).
    ``sigma`` (normalized units) whitens block norms for the robust weights; ``weights``
    (n,) overrides the IRLS weights ``w_k`` (not their square roots); ``whiten``:
    constant, applied after the robust weights (the anchor-noise whitening of
    :func:`factors.anchor_noise.anchor_whitening`).
    """
    r, J = _evaluate(args, track, model, sigma, robust, use_td, weights, whiten)
    return r, [J[:, a:b] for a, b in _block_cols(track.n, use_td)]


def landmark_weights(args: list, track: LandmarkTrack, model: str, sigma: float,
                     robust: RobustKernel | None, use_td: bool = False) -> np.ndarray:
    """Current IRLS weights ``w_k`` (n,) of the observations (ones without a kernel)."""
    r, _ = _evaluate(args, track, model, sigma, None, use_td, None)
    return block_sqrt_weights(r.reshape(-1, 2), sigma, robust) ** 2


def landmark_factor(track: LandmarkTrack, lam_key: int, extrinsic_key: int, sigma: float,
                    model: str = "pinhole", robust: RobustKernel | None = None,
                    td_key: int | None = None,
                    health: FactorHealth | None = None,
                    whiten: AnchorWhitening | None = None) -> gtsam.CustomFactor:
    """``gtsam.CustomFactor`` over :func:`landmark_keys` with isotropic noise ``sigma``.

    ``td_key`` selects the td variant. ``whiten``: constant whitening of the
    stacked residual (anchor noise, :func:`factors.anchor_noise.anchor_whitening`).
    Construction is cheap (no evaluation): rebuild it when the landmark gains an
    observation or is re-anchored.
    """
    check_model(model)
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    keys = landmark_keys(track, lam_key, extrinsic_key, td_key)
    if len(set(keys)) != len(keys):
        raise ValueError(f"landmark factor keys must be distinct, got {keys}")
    use_td = td_key is not None
    kinds = [1, "pose3", "pose3"] + ["pose3"] * track.n + ([1] if use_td else [])
    noise = gtsam.noiseModel.Isotropic.Sigma(2 * track.n, float(sigma))

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        return _evaluate(args, track, model, sigma, robust, use_td, None, whiten)  # stacked J

    return custom_factor(noise, keys, kinds, fn, health)
