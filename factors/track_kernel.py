"""One compiled pass per landmark factor evaluation: projection, key-block scatter, robust
reweighting and anchor-noise whitening (``factors.stereo`` and ``factors.landmark``).

A landmark's observations are made from "bodies": ``bodies[0]`` = ``T_w_b`` of the anchor
keyframe, ``bodies[1..k]`` = the other keyframes' ``T_w_b`` in key order (4x4 matrices).
Observation o is made by body ``target[o]``, through cam0 (``right[o]`` False) or through
cam1, modelled as cam0 of the virtual body ``T_w_b C`` (``factors.stereo``). The plain
landmark factor is the case ``target = 1..n``, no cam1 observation.

Output Jacobian columns (the factor's key order): ``lambda`` (0), ``T_b_c`` (1:7), the
anchor body (7:13), body i >= 1 at ``13 + 6 (i - 1)``, then ``td`` last when ``use_td``.
The arithmetic per observation is that of ``factors.projection._project_kernel`` (the same
helper functions); the cam1 body block is mapped through ``Ad(C^-1)``
(``T Exp(xi) C = (T C) Exp(Ad_{C^-1} xi)``) and added onto its body's columns. Then, as
``factors.robust.reweight_blocks``: block o times ``sqrt(w(|r_o| / sigma))``; then the
constant whitening ``W = I + U diag(d) U^T`` (``factors.anchor_noise``), if ``U`` has columns.

This replaces ~30 small numpy calls per callback (virtual bodies, shifted observations,
fancy-indexed scatter, whitening products) by one call; the results equal the numpy path
to rounding (tests/test_track_kernel.py).
"""

from __future__ import annotations

import numpy as np

from factors.anchor_noise import AnchorWhitening
from factors.jit import njit_inline
from factors.bearing_model import BEHIND_CAMERA_RESIDUAL, _model_into
from factors.projection import COL_TJ, _anchor_terms, _njit, _target_point, _transfer_into
from factors.robust import KERNELS, RobustKernel

_NO_D = np.zeros(0)


@_njit
def _virtual_body(bodies: np.ndarray, t: int, right: bool, C: np.ndarray, out: np.ndarray) -> None:
    """``out = bodies[t] @ C`` for cam1, else ``bodies[t]`` (4x4)."""
    for a in range(4):
        for b in range(4):
            if right:
                s = 0.0
                for c in range(4):
                    s += bodies[t, a, c] * C[c, b]
                out[a, b] = s
            else:
                out[a, b] = bodies[t, a, b]


@njit_inline
def _observation(bodies: np.ndarray, t: int, right: bool, C: np.ndarray, uv: np.ndarray,
                 vel: np.ndarray, o: int, s_j: float, Tj: np.ndarray, Rj: np.ndarray, tj: np.ndarray,
                 uj: np.ndarray) -> None:
    """Observation ``o``'s observing body ``Tj`` (``_virtual_body``), its rotation ``Rj`` and
    translation ``tj``, and ``uj = uv[o] - s_j vel[o]``, the observation moved by its time shift."""
    _virtual_body(bodies, t, right, C, Tj)
    for a in range(3):
        tj[a] = Tj[a, 3]
        for b in range(3):
            Rj[a, b] = Tj[a, b]
    uj[0] = uv[o, 0] - s_j * vel[o, 0]
    uj[1] = uv[o, 1] - s_j * vel[o, 1]


@_njit
def _shifted_anchor_terms(Ti: np.ndarray, Tc: np.ndarray, lam: float, td: float, use_td: bool,
                          anchor_uv: np.ndarray, anchor_vel: np.ndarray, anchor_off: float):
    """``factors.projection._anchor_terms`` at the anchor observation moved by
    ``(td + anchor_off) anchor_vel`` (with ``use_td``)."""
    ui = np.empty(2)
    s_i = td + anchor_off if use_td else 0.0
    ui[0] = anchor_uv[0] - s_i * anchor_vel[0]
    ui[1] = anchor_uv[1] - s_i * anchor_vel[1]
    return _anchor_terms(Ti, Tc, lam, ui)


@_njit
def track_eval(bodies: np.ndarray, target: np.ndarray, right: np.ndarray, C: np.ndarray,
               ad_inv: np.ndarray, Tc: np.ndarray, lam: float, td: float, use_td: bool,
               anchor_uv: np.ndarray, anchor_vel: np.ndarray, anchor_off: float,
               uv: np.ndarray, vel: np.ndarray, off: np.ndarray, basis: np.ndarray,
               sphere: bool, sigma: float, kind: int, kk: float, U: np.ndarray, d: np.ndarray,
               r: np.ndarray, J: np.ndarray, G: np.ndarray) -> None:
    """Fill ``r`` (2n,), ``J`` (2n, 13 + 6k [+1]; zeroed on entry) and ``G`` (n, 2, 2) =
    ``dr/duv_anchor`` (before reweighting and whitening; zero where the cheirality
    residual is returned). Shapes: ``bodies`` (k+1, 4, 4), ``target`` (n,) int,
    ``right`` (n,) bool, ``C`` (4, 4), ``ad_inv`` (6, 6), ``Tc`` (4, 4), ``anchor_*`` (2,),
    (2,), scalar, ``uv``/``vel`` (n, 2), ``off`` (n,), ``basis`` (n, 2, 3), ``U`` (2n, q),
    ``d`` (q,). With ``use_td`` the observations are shifted by ``(td + off) vel`` and
    the last column of ``J`` is ``dr/dtd``."""
    n = uv.shape[0]
    pw, wi, RcTtc, A, Sm, Gi = _shifted_anchor_terms(bodies[0], Tc, lam, td, use_td, anchor_uv, anchor_vel,
                                                     anchor_off)
    Rc, tc = Tc[:3, :3], Tc[:3, 3]
    Tj, Rj, tj = np.empty((4, 4)), np.empty((3, 3)), np.empty(3)
    Q, M, D = np.empty(3), np.empty((3, 3)), np.empty((3, 19))
    dQ, duv, ra, uj = np.empty((2, 3)), np.empty((2, 2)), np.empty(2), np.empty(2)
    blk = np.empty((2, 6))
    tdcol = J.shape[1] - 1
    for o in range(n):
        _observation(bodies, target[o], right[o], C, uv, vel, o, td + off[o] if use_td else 0.0,
                     Tj, Rj, tj, uj)
        _transfer_into(Rj, tj, Rc, tc, lam, pw, wi, RcTtc, A, Sm, Gi, Q, M, D)
        ok = _model_into(Q, uj, basis[o], sphere, ra, dQ, duv)
        for k in range(2):
            row = 2 * o + k
            if not ok:
                r[row] = BEHIND_CAMERA_RESIDUAL
                G[o, k, 0] = 0.0
                G[o, k, 1] = 0.0
                continue
            r[row] = ra[k]
            for c in range(19):
                s = dQ[k, 0] * D[0, c] + dQ[k, 1] * D[1, c] + dQ[k, 2] * D[2, c]
                if c < COL_TJ:
                    J[row, c] += s
                else:
                    blk[k, c - COL_TJ] = s
            for c in range(2):
                G[o, k, c] = dQ[k, 0] * M[0, c] + dQ[k, 1] * M[1, c] + dQ[k, 2] * M[2, c]
            if use_td:
                J[row, tdcol] = -(G[o, k, 0] * anchor_vel[0] + G[o, k, 1] * anchor_vel[1]
                                  + duv[k, 0] * vel[o, 0] + duv[k, 1] * vel[o, 1])
        if ok:
            _add_body_block(J, 2 * o, target[o], right[o], blk, ad_inv)
    _reweight_whiten(r, J, sigma, kind, kk, U, d)


@_njit
def track_eval_depth(bodies: np.ndarray, target: np.ndarray, right: np.ndarray, C: np.ndarray,
                     Tc: np.ndarray, lam: float, td: float, use_td: bool, anchor_uv: np.ndarray,
                     anchor_vel: np.ndarray, anchor_off: float, uv: np.ndarray, vel: np.ndarray,
                     off: np.ndarray, basis: np.ndarray, sphere: bool, sigma: float, kind: int,
                     kk: float, r: np.ndarray, jl: np.ndarray, G: np.ndarray) -> None:
    """:func:`track_eval`'s ``r`` (2n,) and inverse-depth column ``jl = J[:, :1]`` (2n, 1;
    Fortran order, as ``track_eval``'s J), reweighted, and, when ``G`` is (n, 2, 2) rather
    than (0, 2, 2), its ``G``, without the pose, extrinsic and td columns or the whitening: what a
    Gauss-Newton step on ``lam`` alone needs, and what the anchor-noise whitening needs
    (``factors.landmark_schur_kernel``), at a fraction of the cost. The operations are
    ``track_eval``'s in its order, so the values are the same bits
    (``tests/test_track_kernel.py``)."""
    n = uv.shape[0]
    # a flag argument instead would be a literal at each compiled call site: one more
    # compiled version per value (~3.5 s of a first run's compile each)
    with_g = G.shape[0] > 0
    pw, wi, RcTtc, A, _, _ = _shifted_anchor_terms(bodies[0], Tc, lam, td, use_td, anchor_uv, anchor_vel,
                                                   anchor_off)
    Rc, tc = Tc[:3, :3], Tc[:3, 3]
    Tj, Rj, tj = np.empty((4, 4)), np.empty((3, 3)), np.empty(3)
    Q, dl, M = np.empty(3), np.empty(3), np.empty((3, 3))
    qbj, e, Cm = np.empty(3), np.empty(3), np.empty((3, 3))
    dQ, duv, ra, uj = np.empty((2, 3)), np.empty((2, 2)), np.empty(2), np.empty(2)
    for o in range(n):
        _observation(bodies, target[o], right[o], C, uv, vel, o, td + off[o] if use_td else 0.0,
                     Tj, Rj, tj, uj)
        _target_point(Rj, tj, Rc, tc, lam, pw, wi, RcTtc, qbj, e, Cm, Q, dl)
        if with_g:   # M of factors.projection._transfer_into
            for a in range(3):
                for k in range(3):
                    M[a, k] = Cm[a, 0] * A[0, k] + Cm[a, 1] * A[1, k] + Cm[a, 2] * A[2, k]
        ok = _model_into(Q, uj, basis[o], sphere, ra, dQ, duv)
        for k in range(2):
            row = 2 * o + k
            r[row] = ra[k] if ok else BEHIND_CAMERA_RESIDUAL
            jl[row, 0] = 0.0 + (dQ[k, 0] * dl[0] + dQ[k, 1] * dl[1] + dQ[k, 2] * dl[2]) if ok else 0.0
            if with_g:
                for c in range(2):
                    G[o, k, c] = (dQ[k, 0] * M[0, c] + dQ[k, 1] * M[1, c] + dQ[k, 2] * M[2, c]) if ok else 0.0
    _reweight_whiten(r, jl, sigma, kind, kk, np.zeros((2 * n, 0)), np.zeros(0))


@_njit
def _add_body_block(J: np.ndarray, row: int, t: int, right: bool, blk: np.ndarray,
                    ad_inv: np.ndarray) -> None:
    """Add an observation's 2x6 body block ``blk`` (times ``Ad(C^-1)`` for cam1) onto
    rows ``row, row + 1`` and the columns of body ``t`` (the anchor's: 7)."""
    c0 = 7 if t == 0 else COL_TJ + 6 * (t - 1)
    for k in range(2):
        for c in range(6):
            if right:
                s = 0.0
                for e in range(6):
                    s += blk[k, e] * ad_inv[e, c]
            else:
                s = blk[k, c]
            J[row + k, c0 + c] += s


@_njit
def _reweight_whiten(r: np.ndarray, J: np.ndarray, sigma: float, kind: int, kk: float,
                     U: np.ndarray, d: np.ndarray) -> None:
    """IRLS weights per 2-row block (``factors.robust``), then ``x <- x + U (d * U^T x)``
    for the residual and every column of ``J``."""
    n = r.shape[0] // 2
    if kind != 0:
        for o in range(n):
            s = np.sqrt(r[2 * o] * r[2 * o] + r[2 * o + 1] * r[2 * o + 1]) / sigma
            if kind == 1:
                w = 1.0 if s <= kk else kk / s
            else:
                w = 1.0 / (1.0 + (s / kk) ** 2)
            sw = np.sqrt(w)
            for k in range(2):
                r[2 * o + k] *= sw
                for c in range(J.shape[1]):
                    J[2 * o + k, c] *= sw
    q = U.shape[1]
    if q == 0:
        return
    m = r.shape[0]
    y = np.empty(q)
    for c in range(-1, J.shape[1]):
        for j in range(q):
            s = 0.0
            for i in range(m):
                s += U[i, j] * (r[i] if c < 0 else J[i, c])
            y[j] = d[j] * s
        for i in range(m):
            s = 0.0
            for j in range(q):
                s += U[i, j] * y[j]
            if c < 0:
                r[i] += s
            else:
                J[i, c] += s


@_njit
def whitening_2(G: np.ndarray, U: np.ndarray, d: np.ndarray) -> int:
    """``factors.anchor_noise.anchor_whitening`` for G (m, 2) in closed form: fills
    ``U`` (m, 2) and ``d`` (2,) and returns the number q of kept columns (eigenvalues of
    ``G^T G`` above ``1e-12 max(1, s_max)``); the kept ones come first, in ascending order
    of eigenvalue as ``numpy.linalg.eigh`` orders them."""
    m = G.shape[0]
    a = b = c = 0.0
    for i in range(m):
        a += G[i, 0] * G[i, 0]
        b += G[i, 0] * G[i, 1]
        c += G[i, 1] * G[i, 1]
    h = 0.5 * (a - c)
    rad = np.sqrt(h * h + b * b)
    s_max = 0.5 * (a + c) + rad
    s_min = (a * c - b * b) / s_max if s_max > 0 else 0.0
    # eigenvector of s_max: the better conditioned of (b, s_max - a) and (s_max - c, b)
    x0, y0 = b, s_max - a
    x1, y1 = s_max - c, b
    if x0 * x0 + y0 * y0 >= x1 * x1 + y1 * y1:
        vx, vy = x0, y0
    else:
        vx, vy = x1, y1
    nv = np.sqrt(vx * vx + vy * vy)
    if nv > 0:
        vx, vy = vx / nv, vy / nv
    else:
        vx, vy = 1.0, 0.0
    tol = 1e-12 * max(1.0, s_max)
    s = np.array([s_min, s_max])
    V = np.array([[-vy, vx], [vx, vy]])   # row j: eigenvector of s[j]
    q = 0
    for j in range(2):
        if s[j] > tol:
            inv = 1.0 / np.sqrt(s[j])
            for i in range(m):
                U[i, q] = (G[i, 0] * V[j, 0] + G[i, 1] * V[j, 1]) * inv
            d[q] = 1.0 / np.sqrt(1.0 + s[j]) - 1.0
            q += 1
    return q


def evaluate(bodies: np.ndarray, target: np.ndarray, right: np.ndarray, C: np.ndarray,
             ad_inv: np.ndarray, Tc: np.ndarray, lam: float, td: float | None,
             anchor_uv: np.ndarray, anchor_vel: np.ndarray, anchor_off: float, uv: np.ndarray,
             vel: np.ndarray, off: np.ndarray, basis: np.ndarray, model: str, sigma: float,
             robust: RobustKernel | None, whiten: AnchorWhitening | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual (2n,), Jacobian (2n, 13 + 6k [+1], Fortran order) and ``dr/duv_anchor``
    (n, 2, 2) of :func:`track_eval`; ``td`` None: no td variable (no shift, no column)."""
    n, k = uv.shape[0], bodies.shape[0] - 1
    use_td = td is not None
    r = np.empty(2 * n)
    J = np.zeros((2 * n, COL_TJ + 6 * k + use_td), order="F")
    G = np.empty((n, 2, 2))
    kind = 0 if robust is None else KERNELS.index(robust.kind)
    U, d = (np.zeros((2 * n, 0)), _NO_D) if whiten is None else (whiten.U, whiten.d)
    c = np.ascontiguousarray
    track_eval(c(bodies), c(target), c(right), c(C), c(ad_inv), c(Tc), float(lam), float(td or 0.0),
               use_td, c(anchor_uv), c(anchor_vel), float(anchor_off), c(uv), c(vel), c(off),
               c(basis), model == "sphere",
               float(sigma), kind, float(robust.k) if robust is not None else 1.0,
               U if U.flags.c_contiguous else np.ascontiguousarray(U), d, r, J, G)
    return r, J, G


def whitening(G: np.ndarray) -> AnchorWhitening:
    """``factors.anchor_noise.anchor_whitening`` of ``G`` (m, 2) via :func:`whitening_2`."""
    G = np.ascontiguousarray(G, dtype=float).reshape(-1, 2)
    U, d = np.empty((G.shape[0], 2)), np.empty(2)
    q = whitening_2(G, U, d)
    return AnchorWhitening(np.ascontiguousarray(U[:, :q]), d[:q].copy())
