"""Numba kernels of :mod:`factors.landmark_schur` (the bundle factor of landmark tracks with
their inverse depths eliminated inside; the math and the column layout are in that module's
docstring): per-landmark evaluation through ``factors.track_kernel.track_eval``, depth
refinement, the row-pair ``J^T J`` sums and the Schur accumulation, and the anchor-noise
whitening of a bundle. Pure numerics; the factor, ``Bundle`` and its packing stay in
:mod:`factors.landmark_schur`."""

from __future__ import annotations

import numpy as np

from factors.jit import njit as _njit
from factors.track_kernel import track_eval, track_eval_depth, whitening_2



@_njit
def _local_bodies(bodies, lbodies, b0, b1):
    out = np.empty((b1 - b0, 4, 4))
    for i in range(b1 - b0):
        out[i] = bodies[lbodies[b0 + i]]
    return out


@_njit
def _eval_one(i, bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel, a_off, target,
              right, uv, vel, off, basis, C, ad_inv, sphere, sigma, kind, kk, lam):
    """Reweighted (not whitened) r (2n,), J (2n, 13 + 6k [+1]) and G of landmark i at lam."""
    s0, s1 = start[i], start[i + 1]
    lb = _local_bodies(bodies, lbodies, lb_start[i], lb_start[i + 1])
    n = s1 - s0
    r = np.empty(2 * n)
    # the argument types of track_eval's Python caller (factors.track_kernel.evaluate):
    # Fortran-order J, writable empty U and d (not read-only globals), so that one
    # compiled version serves both (each further signature cost ~2 s of first-run compile)
    J = np.zeros((13 + 6 * (lb.shape[0] - 1) + (1 if use_td else 0), 2 * n)).T
    G = np.empty((n, 2, 2))
    track_eval(lb, target[s0:s1], right[s0:s1], C, ad_inv, Tc, lam, td, use_td, a_uv[i], a_vel[i],
               a_off[i], uv[s0:s1], vel[s0:s1], off[s0:s1], basis[s0:s1], sphere, sigma, kind, kk,
               np.zeros((2 * n, 0)), np.zeros(0), r, J, G)
    return r, J, G


@_njit
def _eval_depth(i, bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel, a_off, target,
                right, uv, vel, off, basis, C, sphere, sigma, kind, kk, lam, G):
    """``_eval_one``'s r (2n,), J[:, 0] (2n,) and, into ``G`` when it is (n, 2, 2) rather
    than (0, 2, 2), its G (``track_eval_depth``): a depth step's inputs, the whitening's,
    without the pose columns."""
    s0, s1 = start[i], start[i + 1]
    lb = _local_bodies(bodies, lbodies, lb_start[i], lb_start[i + 1])
    r = np.empty(2 * (s1 - s0))
    jl = np.empty((1, 2 * (s1 - s0))).T   # Fortran order: _reweight_whiten's J type
    track_eval_depth(lb, target[s0:s1], right[s0:s1], C, Tc, lam, td, use_td, a_uv[i], a_vel[i],
                     a_off[i], uv[s0:s1], vel[s0:s1], off[s0:s1], basis[s0:s1], sphere, sigma, kind,
                     kk, r, jl, G)
    return r, jl[:, 0]


@_njit
def _depth_terms(r, jl, U, dw):
    """(j^T j, j^T r) of the whitened system (W^2 = I + U diag(dw) U^T) for the depth
    column ``jl`` (2n,)."""
    m = r.shape[0]
    hll, gl = 0.0, 0.0
    for a in range(m):
        hll += jl[a] * jl[a]
        gl += jl[a] * r[a]
    for q in range(2):
        pr, pj = 0.0, 0.0
        for a in range(m):
            pr += U[a, q] * r[a]
            pj += U[a, q] * jl[a]
        hll += dw[q] * pj * pj
        gl += dw[q] * pj * pr
    return hll, gl


@_njit
def bundle_system(bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel, a_off, target,
                  right, uv, vel, off, basis, C, ad_inv, sphere, sigma, kind, kk, U, d, lam,
                  active, p_lam, p_info, hll_out, iters, lam_min, lam_max, H, g, schur=True):
    """Fill ``H`` (D, D) and ``g`` (D,) (zeroed on entry) of the bundle (module docstring),
    refining ``lam`` in place; returns E. Landmarks with ``active`` False are skipped;
    ``schur`` False: refine only (H, g untouched; E and ``hll_out`` at the last evaluation,
    before the last step; at least one step). A landmark
    with ``p_info[i] > 0`` has the depth prior ``p_info (lam - p_lam)^2 / 2`` (whitened
    units); ``hll_out[i]``: its depth information ``j^T j`` (prior included) at the end."""
    inv = 1.0 / sigma
    D = H.shape[0]
    E = 0.0
    dw = np.empty(2)
    no_g = np.empty((0, 2, 2))
    for i in range(lam.shape[0]):
        if not active[i]:
            continue
        s0, s1 = start[i], start[i + 1]
        Ui = U[2 * s0:2 * s1]
        for q in range(2):
            dw[q] = 2.0 * d[i, q] + d[i, q] * d[i, q]
        li = lam[i]
        # `iters` depth steps (refine only: at least one; E and hll_out before the last),
        # then, for the elimination, one evaluation of every column at the refined depth
        ei = 0.0
        for it in range(iters if schur else max(iters, 1)):
            r, jl = _eval_depth(i, bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel,
                                a_off, target, right, uv, vel, off, basis, C, sphere, sigma, kind,
                                kk, li, no_g)
            r *= inv
            jl *= inv
            hll, gl = _depth_terms(r, jl, Ui, dw)
            hll += p_info[i]
            gl += p_info[i] * (li - p_lam[i])
            if not hll > 0.0:
                break
            new = min(max(li - gl / hll, 0.5 * li, lam_min), 2.0 * li, lam_max)
            if not schur:
                hll_out[i] = hll
                ei = 0.5 * (np.sum(r * r) + dw[0] * np.sum(Ui[:, 0] * r) ** 2
                            + dw[1] * np.sum(Ui[:, 1] * r) ** 2 + p_info[i] * (li - p_lam[i]) ** 2)
            if abs(new - li) <= 1e-9 * li:
                break
            li = new
        lam[i] = li
        if not schur:
            E += ei
            continue
        r, J, _ = _eval_one(i, bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel, a_off,
                            target, right, uv, vel, off, basis, C, ad_inv, sphere, sigma, kind, kk, li)
        r *= inv
        J *= inv
        pres = li - p_lam[i]
        E += _schur_add(r, J, Ui, dw, target[s0:s1], lbodies[lb_start[i]:lb_start[i + 1]], use_td, D, H, g,
                        p_info[i], pres, hll_out, i)
    # the sums went into the lower triangle (the entries the Cholesky of
    # factors.photometric_host.square_root_kernel reads, each summed as before): mirrored
    if schur:
        for a in range(D):
            for b in range(a + 1, D):
                H[a, b] = H[b, a]
    return E


@_njit
def _column_map(lb, ncol, use_td, D):
    """Group column of each local column (-1 for lambda)."""
    cmap = np.empty(ncol, np.int64)
    cmap[0] = -1
    for e in range(6):
        cmap[1 + e] = e
        for t in range(lb.shape[0]):
            cmap[7 + 6 * t + e] = 6 + 6 * lb[t] + e
    if use_td:
        cmap[ncol - 1] = D - 1
    return cmap


@_njit
def _by_group_column(cols, k, cmap):
    """Sort ``cols[:k]`` (local columns) in place by their group column ``cmap[cols]``
    (insertion sort: ~20 entries, nearly in order)."""
    for x in range(1, k):
        c = cols[x]
        y = x - 1
        while y >= 0 and cmap[cols[y]] > cmap[c]:
            cols[y + 1] = cols[y]
            y -= 1
        cols[y + 1] = c


@_njit
def _add_row_pairs(J, target, cmap, use_td, H):
    """``H += J_x^T J_x`` summed over each row pair's non-zero columns (``T_b_c``, the anchor,
    the observation's own body, td), scattered through ``cmap``: the lower triangle only
    (``bundle_system`` mirrors it)."""
    ncol = J.shape[1]
    nz = np.empty(20, np.int64)
    for o in range(target.shape[0]):
        k = 0
        for c in range(1, 13):
            nz[k] = c
            k += 1
        t = target[o]
        if t > 0:
            for e in range(6):
                nz[k] = 7 + 6 * t + e
                k += 1
        if use_td:
            nz[k] = ncol - 1
            k += 1
        _by_group_column(nz, k, cmap)
        for x in range(k):
            a = nz[x]
            ga = cmap[a]
            for y in range(x + 1):
                b = nz[y]
                H[ga, cmap[b]] += J[2 * o, a] * J[2 * o, b] + J[2 * o + 1, a] * J[2 * o + 1, b]


@_njit
def _schur_add(r, J, U, dw, target, lb, use_td, D, H, g, pinfo, pres, hll_out, i):
    """Add one landmark's lambda-eliminated H, g onto the group's (depth prior ``pinfo``
    at residual ``pres``); store its depth information in ``hll_out[i]``; return its E."""
    m, ncol = J.shape[0], J.shape[1]
    cmap = _column_map(lb, ncol, use_td, D)
    P = np.zeros((2, ncol))
    p = np.zeros(2)
    for q in range(2):
        for a in range(m):
            p[q] += U[a, q] * r[a]
            for c in range(ncol):
                P[q, c] += U[a, q] * J[a, c]
    # lambda column and gradient terms (dense over the landmark's columns)
    hx = np.zeros(ncol)
    gx = np.zeros(ncol)
    rr = 0.0
    for a in range(m):
        rr += r[a] * r[a]
        for c in range(ncol):
            hx[c] += J[a, c] * J[a, 0]
            gx[c] += J[a, c] * r[a]
    for q in range(2):
        rr += dw[q] * p[q] * p[q]
        for c in range(ncol):
            hx[c] += dw[q] * P[q, c] * P[q, 0]
            gx[c] += dw[q] * P[q, c] * p[q]
    hx[0] += pinfo
    gx[0] += pinfo * pres
    rr += pinfo * pres * pres
    hll, gl = hx[0], gx[0]
    hll_out[i] = hll
    if not hll > 0.0:
        hll, gl = 1.0, 0.0
        for c in range(ncol):
            hx[c] = 0.0
    _add_row_pairs(J, target, cmap, use_td, H)
    # whitening (rank 2) and elimination (rank 1), dense over the lower triangle
    for a in range(1, ncol):
        g[cmap[a]] += gx[a] - hx[a] * gl / hll
    cols = np.arange(1, ncol)
    _by_group_column(cols, ncol - 1, cmap)
    for x in range(ncol - 1):
        a = cols[x]
        ga = cmap[a]
        for y in range(x + 1):
            b = cols[y]
            H[ga, cmap[b]] += dw[0] * P[0, a] * P[0, b] + dw[1] * P[1, a] * P[1, b] - hx[a] * hx[b] / hll
    return 0.5 * (rr - gl * gl / hll)


@_njit
def _set_whitening(bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel, a_off, target,
                   right, uv, vel, off, basis, C, sphere, sigma, kind, kk, lam, U, d):
    """U, d of every landmark, from ``track_eval_depth``'s ``dr/duv_anchor`` at ``lam``;
    ``sigma``, ``kind``, ``kk`` (1, 0, 1: unweighted) come from Python so that
    ``_eval_depth`` has bundle_system's argument types (a literal 0 here would compile a
    second version of it)."""
    for i in range(lam.shape[0]):
        s0, s1 = start[i], start[i + 1]
        G = np.empty((s1 - s0, 2, 2))
        _eval_depth(i, bodies, Tc, td, use_td, start, lb_start, lbodies, a_uv, a_vel, a_off,
                    target, right, uv, vel, off, basis, C, sphere, sigma, kind, kk, lam[i], G)
        Ui = np.zeros((2 * (s1 - s0), 2))
        di = np.zeros(2)
        whitening_2(G.reshape(2 * (s1 - s0), 2), Ui, di)
        for a in range(Ui.shape[0]):   # element loops: a slice assignment compiles Numba's
            for q in range(2):         # shape-mismatch message formatting (~2.5 s)
                U[2 * s0 + a, q] = Ui[a, q]
        for q in range(2):
            d[i, q] = di[q]
