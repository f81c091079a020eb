"""Inverse-depth projection factor (seed 004, ``projection_factor``) in GTSAM conventions.

Variables: body poses ``T_w_bi`` (anchor) and ``T_w_bj`` (``gtsam.Pose3``), camera
extrinsic ``T_b_c`` (``gtsam.Pose3``, camera in body) and the inverse depth ``lambda``
(1-vector, 1/m) of the landmark along its anchor bearing: ``P_ci = [u_i, v_i, 1] / lambda``
(normalized-plane coordinates ``uv``, unitless). Transfer (seed 004, first equation)::

    P_cj = T_b_c^-1 * T_w_bj^-1 * T_w_bi * T_b_c * P_ci

Internally the homogeneous point ``Q = lambda * P_cj = M m_i + lambda h`` with
``M = R_c^T R_j^T R_i R_c`` and ``h = R_c^T (R_j^T (R_i t_c + t_i - t_j) - t_c)`` is used: it
projects identically for ``lambda > 0`` and stays finite for far points (``lambda -> 0``).

Residual models (pinhole and unit sphere) and cheirality: :mod:`factors.bearing_model`.

Jacobians are exact for GTSAM's retraction ``T * Exp([omega, v])``; the numeric test in
``tests/test_jacobians.py`` is the judge. VINS perturbs translations in the world frame,
so its blocks differ and are not used.

Every entry point (:func:`projection_residual`, :func:`projection_factor`, the td factor
and the per-landmark factor) runs the same Numba-compiled batch kernel,
:func:`project_batch`, over n observations of one landmark (n = 1 for single factors).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.bearing_model import BEHIND_CAMERA_RESIDUAL, _model_into, check_model, tangent_basis
from factors.jit import njit as _njit, njit_inline

# ---------------------------------------------------------------------------------------
# Batched kernel. Written as explicit loops over 3-vectors so that Numba compiles it (a
# numpy-vectorized version spent ~60 us per 10-observation landmark in ~40 small numpy
# calls; this kernel takes ~3 us). Without Numba it runs as plain Python.
#
# Derivation (right perturbations R -> R (I + [w]x), t -> t + R v; seed 004 transfer):
#   q_b  = R_c m_i + lam t_c                        (lam * point in body i)
#   q_bj = R_j^T (R_i q_b + lam (t_i - t_j))        (lam * point in body j)
#   Q    = R_c^T (q_bj - lam t_c) = M m_i + lam h,  M = R_c^T R_j^T R_i R_c
#   dQ/dT_i = R_c^T R_j^T R_i [-[q_b]x, lam I]      dQ/dT_j = R_c^T [[q_bj]x, -lam I]
#   dQ/dT_c = [[Q]x - M [m_i]x, lam (M - I)]        dQ/dlam = h,  dQ/duv_i = M[:, :2]
# then r = f(Q) with f the pinhole or sphere model, J = df/dQ * dQ/dx.
# ---------------------------------------------------------------------------------------

COL_LAM, COL_TC, COL_TI, COL_TJ = 0, 1, 7, 13
"""Column layout of the batched Jacobian: lambda, T_b_c, T_w_bi, then one T_w_bj per row pair."""


@_njit
def _skew_into(v: np.ndarray, out: np.ndarray) -> None:
    out[0, 0], out[0, 1], out[0, 2] = 0.0, -v[2], v[1]
    out[1, 0], out[1, 1], out[1, 2] = v[2], 0.0, -v[0]
    out[2, 0], out[2, 1], out[2, 2] = -v[1], v[0], 0.0


@_njit
def _anchor_terms(Ti: np.ndarray, Tc: np.ndarray, lam: float, uv_i: np.ndarray):
    """Per-landmark constants: m_i, lam*P_w = R_i q_b + lam t_i, w_i = R_i t_c + t_i,
    R_c^T t_c, A = R_i R_c, [m_i]x and G = R_i [-[q_b]x, lam I] (3, 6)."""
    Ri, ti, Rc, tc = Ti[:3, :3], Ti[:3, 3], Tc[:3, :3], Tc[:3, 3]
    m = np.array([uv_i[0], uv_i[1], 1.0])
    qb, pw, wi, RcTtc = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    A, Sm, Sq, G = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 6))
    for a in range(3):
        for k in range(3):
            qb[a] += Rc[a, k] * m[k]
            RcTtc[a] += Rc[k, a] * tc[k]
        qb[a] += lam * tc[a]
    _skew_into(qb, Sq)
    _skew_into(m, Sm)
    for a in range(3):
        for k in range(3):
            pw[a] += Ri[a, k] * qb[k]
            wi[a] += Ri[a, k] * tc[k]
            for c in range(3):
                A[a, c] += Ri[a, k] * Rc[k, c]
                G[a, c] -= Ri[a, k] * Sq[k, c]
            G[a, 3 + k] = lam * Ri[a, k]
        pw[a] += lam * ti[a]
        wi[a] += ti[a]
    return pw, wi, RcTtc, A, Sm, G


@njit_inline
def _target_point(Rj: np.ndarray, tj: np.ndarray, Rc: np.ndarray, tc: np.ndarray, lam: float,
                  pw: np.ndarray, wi: np.ndarray, RcTtc: np.ndarray, qbj: np.ndarray, e: np.ndarray,
                  C: np.ndarray, Q: np.ndarray, dl: np.ndarray) -> None:
    """:func:`_transfer_into`'s Q, ``dl = dQ/dlam`` (3,) and its scratch ``qbj``, ``e`` (3,),
    ``C = (R_j R_c)^T``: all a depth step needs (``track_kernel.track_eval_depth``)."""
    for a in range(3):
        qbj[a] = 0.0
        for k in range(3):
            qbj[a] += Rj[k, a] * (pw[k] - lam * tj[k])
            C[a, k] = 0.0
            for c in range(3):
                C[a, k] += Rc[c, a] * Rj[k, c]  # (R_j R_c)^T = R_c^T R_j^T
        e[a] = wi[a] - tj[a]
    for a in range(3):
        Q[a] = 0.0
        dl[a] = -RcTtc[a]
        for k in range(3):
            Q[a] += Rc[k, a] * (qbj[k] - lam * tc[k])
            dl[a] += C[a, k] * e[k]


@_njit
def _transfer_into(Rj: np.ndarray, tj: np.ndarray, Rc: np.ndarray, tc: np.ndarray, lam: float,
                   pw: np.ndarray, wi: np.ndarray, RcTtc: np.ndarray, A: np.ndarray,
                   Sm: np.ndarray, G: np.ndarray, Q: np.ndarray, M: np.ndarray,
                   D: np.ndarray) -> None:
    """Q (3,), M (3, 3) and D = dQ/d[lam, T_c, T_i, T_j] (3, 19) for one target frame."""
    qbj, e, C, Sq = np.empty(3), np.empty(3), np.empty((3, 3)), np.empty((3, 3))
    _target_point(Rj, tj, Rc, tc, lam, pw, wi, RcTtc, qbj, e, C, Q, D[:, COL_LAM])
    for a in range(3):
        for k in range(3):
            M[a, k] = C[a, 0] * A[0, k] + C[a, 1] * A[1, k] + C[a, 2] * A[2, k]
        for c in range(6):
            D[a, COL_TI + c] = C[a, 0] * G[0, c] + C[a, 1] * G[1, c] + C[a, 2] * G[2, c]
    _skew_into(qbj, Sq)
    for a in range(3):
        for c in range(3):
            D[a, COL_TJ + c] = Rc[0, a] * Sq[0, c] + Rc[1, a] * Sq[1, c] + Rc[2, a] * Sq[2, c]
            D[a, COL_TJ + 3 + c] = -lam * Rc[c, a]
            D[a, COL_TC + 3 + c] = lam * (M[a, c] - (1.0 if a == c else 0.0))
    _skew_into(Q, Sq)
    for a in range(3):
        for c in range(3):
            D[a, COL_TC + c] = Sq[a, c] - (M[a, 0] * Sm[0, c] + M[a, 1] * Sm[1, c]
                                           + M[a, 2] * Sm[2, c])


@_njit
def _project_kernel(Ti: np.ndarray, Tjs: np.ndarray, Tc: np.ndarray, lam: float,
                    uv_i: np.ndarray, uv_j: np.ndarray, basis: np.ndarray, sphere: bool,
                    vel_i: np.ndarray, vel_j: np.ndarray, vel_col: int,
                    r: np.ndarray, J: np.ndarray, Juvi: np.ndarray, Juvj: np.ndarray,
                    valid: np.ndarray) -> None:
    """Fill r (n, 2), J (2n, >= 13 + 6n; zeroed, COL_* layout), Juvi/Juvj (n, 2, 2), valid (n,).

    If ``vel_col >= 0``, ``J[:, vel_col] = -(dr/duv_i vel_i + dr/duv_j vel_j)``.
    """
    pw, wi, RcTtc, A, Sm, G = _anchor_terms(Ti, Tc, lam, uv_i)
    Rc, tc = Tc[:3, :3], Tc[:3, 3]
    Q, M, D = np.empty(3), np.empty((3, 3)), np.empty((3, 19))
    dQ, duv, ra = np.empty((2, 3)), np.empty((2, 2)), np.empty(2)
    for o in range(Tjs.shape[0]):
        _transfer_into(Tjs[o, :3, :3], Tjs[o, :3, 3], Rc, tc, lam, pw, wi, RcTtc, A, Sm, G,
                       Q, M, D)
        ok = _model_into(Q, uv_j[o], basis[o], sphere, ra, dQ, duv)
        valid[o] = ok
        for k in range(2):
            row = 2 * o + k
            if not ok:
                r[o, k] = BEHIND_CAMERA_RESIDUAL
                continue  # J, Juvi, Juvj stay zero
            r[o, k] = ra[k]
            for c in range(19):
                s = dQ[k, 0] * D[0, c] + dQ[k, 1] * D[1, c] + dQ[k, 2] * D[2, c]
                J[row, c if c < COL_TJ else c + 6 * o] = s
            for c in range(2):
                Juvi[o, k, c] = dQ[k, 0] * M[0, c] + dQ[k, 1] * M[1, c] + dQ[k, 2] * M[2, c]
                Juvj[o, k, c] = duv[k, c]
            if vel_col >= 0:
                J[row, vel_col] = -(Juvi[o, k, 0] * vel_i[0] + Juvi[o, k, 1] * vel_i[1]
                                    + duv[k, 0] * vel_j[o, 0] + duv[k, 1] * vel_j[o, 1])


@_njit
def _anchor_jacobian_kernel(Ti: np.ndarray, Tjs: np.ndarray, Tc: np.ndarray, lam: float,
                            uv_i: np.ndarray, uv_j: np.ndarray, basis: np.ndarray, sphere: bool,
                            Juvi: np.ndarray) -> None:
    """Only ``Juvi`` (n, 2, 2) of :func:`_project_kernel` (same arithmetic, so the same
    bits; zero where the cheirality residual is returned)."""
    pw, wi, RcTtc, A, Sm, G = _anchor_terms(Ti, Tc, lam, uv_i)
    Rc, tc = Tc[:3, :3], Tc[:3, 3]
    Q, M, D = np.empty(3), np.empty((3, 3)), np.empty((3, 19))
    dQ, duv, ra = np.empty((2, 3)), np.empty((2, 2)), np.empty(2)
    for o in range(Tjs.shape[0]):
        _transfer_into(Tjs[o, :3, :3], Tjs[o, :3, 3], Rc, tc, lam, pw, wi, RcTtc, A, Sm, G,
                       Q, M, D)
        if not _model_into(Q, uv_j[o], basis[o], sphere, ra, dQ, duv):
            continue
        for k in range(2):
            for c in range(2):
                Juvi[o, k, c] = dQ[k, 0] * M[0, c] + dQ[k, 1] * M[1, c] + dQ[k, 2] * M[2, c]


def anchor_jacobian_batch(Ti: np.ndarray, Tjs: np.ndarray, Tc: np.ndarray, lam: float,
                          uv_i: np.ndarray, uv_j: np.ndarray, model: str,
                          basis: np.ndarray) -> np.ndarray:
    """``dr/duv_i`` (n, 2, 2) of :func:`project_batch` (its ``uvi``) without the rest of
    the Jacobian: the anchor-noise whitening needs only this (``factors.anchor_noise``)."""
    n = Tjs.shape[0]
    Juvi = np.zeros((n, 2, 2))
    _anchor_jacobian_kernel(np.ascontiguousarray(Ti, dtype=float), np.ascontiguousarray(Tjs, dtype=float),
                            np.ascontiguousarray(Tc, dtype=float), float(lam),
                            np.ascontiguousarray(uv_i, dtype=float), np.ascontiguousarray(uv_j, dtype=float),
                            np.ascontiguousarray(basis, dtype=float), model == "sphere", Juvi)
    return Juvi


@_njit
def _transfer_kernel(Ti: np.ndarray, Tj: np.ndarray, Tc: np.ndarray, lam: float, uv_i: np.ndarray,
                     Q: np.ndarray, M: np.ndarray, D: np.ndarray) -> None:
    pw, wi, RcTtc, A, Sm, G = _anchor_terms(Ti, Tc, lam, uv_i)
    _transfer_into(np.ascontiguousarray(Tj[:3, :3]), np.ascontiguousarray(Tj[:3, 3]),
                   np.ascontiguousarray(Tc[:3, :3]), np.ascontiguousarray(Tc[:3, 3]), lam, pw, wi,
                   RcTtc, A, Sm, G, Q, M, D)


def transfer_point(Ti: np.ndarray, Tj: np.ndarray, Tc: np.ndarray, lam: float,
                   uv_i: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The seed-004 transfer of one anchored point into camera j, with its derivatives.

    ``Ti``, ``Tj``, ``Tc`` (4, 4): ``T_w_bi``, ``T_w_bj``, ``T_b_c``; ``lam`` (1/m) and ``uv_i``
    (2,) the anchor's inverse depth and ray. Returns ``Q = lam * P_cj`` (3,), ``M = dQ/dm_i``
    (3, 3) and ``D = dQ/d[lam, T_c, T_i, T_j]`` (3, 19) in the ``COL_*`` layout.
    """
    Q, M, D = np.empty(3), np.empty((3, 3)), np.empty((3, 19))
    _transfer_kernel(np.ascontiguousarray(Ti, dtype=float), np.ascontiguousarray(Tj, dtype=float),
                     np.ascontiguousarray(Tc, dtype=float), float(lam),
                     np.ascontiguousarray(uv_i, dtype=float), Q, M, D)
    return Q, M, D


_NO_VEL_I = np.zeros(2)


class Projected(NamedTuple):
    """Batched residuals of n observations of one landmark and their Jacobians."""

    r: np.ndarray  # (n, 2)
    J: np.ndarray  # (2n, 13 + 6n [+ 1]), Fortran order, COL_* layout
    uvi: np.ndarray  # (n, 2, 2) d r / d uv_i (anchor observation)
    uvj: np.ndarray  # (n, 2, 2) d r / d uv_j (target observation)
    valid: np.ndarray  # (n,) bool, False where the cheirality residual was returned


def project_batch(Ti: np.ndarray, Tjs: np.ndarray, Tc: np.ndarray, lam: float,
                  uv_i: np.ndarray, uv_j: np.ndarray, model: str, basis: np.ndarray,
                  vel_i: np.ndarray | None = None, vel_j: np.ndarray | None = None) -> Projected:
    """Residuals of n observations ``uv_j`` (n, 2) of one landmark anchored at ``uv_i`` (2,).

    ``Ti`` (4, 4) = ``T_w_bi``, ``Tjs`` (n, 4, 4) = ``T_w_bj``, ``Tc`` (4, 4) = ``T_b_c`` as
    homogeneous matrices; ``lam`` inverse depth (1/m); ``basis`` (n, 2, 3) the sphere tangent
    bases (:func:`tangent_basis`; ignored by ``"pinhole"``). ``J`` columns: ``COL_LAM``,
    ``COL_TC:+6``, ``COL_TI:+6``, then ``COL_TJ + 6k:+6`` nonzero only in rows ``2k, 2k+1``.
    With observation velocities ``vel_i`` (2,), ``vel_j`` (n, 2) one more column holds
    ``d r(uv_i - s vel_i, uv_j - s vel_j) / d s`` at ``s = 0`` (the td chain rule).
    """
    check_model(model)
    n = Tjs.shape[0]
    with_vel = vel_i is not None
    r = np.empty((n, 2))
    J = np.zeros((2 * n, COL_TJ + 6 * n + with_vel), order="F")
    Juvi, Juvj = np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
    valid = np.empty(n, dtype=np.bool_)
    if with_vel:
        vel_i = np.ascontiguousarray(vel_i, dtype=float)
        vel_j = np.ascontiguousarray(vel_j, dtype=float)
    else:
        vel_i, vel_j = _NO_VEL_I, np.zeros((n, 2))
    _project_kernel(np.ascontiguousarray(Ti, dtype=float), np.ascontiguousarray(Tjs, dtype=float),
                    np.ascontiguousarray(Tc, dtype=float), float(lam),
                    np.ascontiguousarray(uv_i, dtype=float), np.ascontiguousarray(uv_j, dtype=float),
                    np.ascontiguousarray(basis, dtype=float), model == "sphere",
                    vel_i, vel_j, J.shape[1] - 1 if with_vel else -1, r, J, Juvi, Juvj, valid)
    return Projected(r, J, Juvi, Juvj, valid)


def single_blocks(J: np.ndarray) -> list[np.ndarray]:
    """Split a one-observation batched Jacobian (2, 19) into ``[J_Ti, J_Tj, J_Tbc, J_lam]``."""
    return [J[:, COL_TI:COL_TI + 6], J[:, COL_TJ:COL_TJ + 6], J[:, COL_TC:COL_TC + 6],
            J[:, COL_LAM:COL_LAM + 1]]


def projection_residual(T_w_bi: gtsam.Pose3, T_w_bj: gtsam.Pose3, T_b_c: gtsam.Pose3,
                        inv_depth: float, uv_i: np.ndarray, uv_j: np.ndarray,
                        model: str = "pinhole") -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual (2,) of one observation and ``[J_Ti (2,6), J_Tj (2,6), J_Tbc (2,6), J_lam (2,1)]``.

    ``uv_i``, ``uv_j``: normalized-plane observations (2,) in the anchor and target camera;
    ``inv_depth``: 1/m along the anchor bearing. Unwhitened; tangents ``[omega, v]``.
    """
    check_model(model)
    uv_j = np.asarray(uv_j, dtype=float).reshape(1, 2)
    p = project_batch(T_w_bi.matrix(), T_w_bj.matrix()[None], T_b_c.matrix(), float(inv_depth),
                      np.asarray(uv_i, dtype=float).reshape(2), uv_j, model, tangent_basis(uv_j))
    return p.r[0], single_blocks(p.J)


def projection_factor(noise: gtsam.noiseModel.Base, keys: Sequence[int], uv_i: np.ndarray,
                      uv_j: np.ndarray, model: str = "pinhole",
                      health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """``gtsam.CustomFactor`` on keys ``(T_w_bi, T_w_bj, T_b_c, lambda)`` for one observation.

    ``noise`` is any 2-D noise model (e.g. ``factors.robust.robust_noise(...)`` for Huber
    or Cauchy through ``gtsam.noiseModel.Robust``).
    """
    check_model(model)
    keys = [int(k) for k in keys]
    if len(keys) != 4 or len(set(keys)) != 4:
        raise ValueError(f"projection_factor needs 4 distinct keys (Ti, Tj, Tbc, lambda), got {keys}")
    uv_i = np.ascontiguousarray(uv_i, dtype=float).reshape(2)
    uv_j = np.ascontiguousarray(uv_j, dtype=float).reshape(1, 2)
    basis = tangent_basis(uv_j)

    def fn(args: list) -> tuple[np.ndarray, list[np.ndarray]]:
        Ti, Tj, Tc, lam = args
        p = project_batch(Ti.matrix(), Tj.matrix()[None], Tc.matrix(), lam[0], uv_i, uv_j,
                          model, basis)
        return p.r[0], single_blocks(p.J)

    return custom_factor(noise, keys, ["pose3", "pose3", "pose3", 1], fn, health)
