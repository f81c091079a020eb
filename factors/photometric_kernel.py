"""Numba kernels of the per-host photometric factor (``factors.photometric_host``).

One call linearizes all N points of one host keyframe observed in M target keyframes
(and, for the points flagged in ``smask``, in the host's right image): it refines every
point's inverse depth rho by a few Gauss-Newton steps with the poses held, evaluates the
Huber-weighted photometric residuals (same math and weights as ``factors.photometric``:
DSO's 8-pixel pattern, affine brightness [a, b] per keyframe, weight
w = lambda c^2 / (c^2 + |grad I_host|^2) / (2 sigma_I^2), Huber on sqrt(w) r) and
accumulates the normal equations over the frame variables with each point's rho
eliminated (Schur complement, as DSO's energy functional and GTSAM's smart factors):

    H = sum_n (H_xx^n - H_xr^n H_rx^n / H_rr^n),   g = sum_n (g_x^n - H_xr^n g_r^n / H_rr^n).

Variable layout (n = 8 (M + 1)): [xi_host (6), ab_host (2), then per target m:
xi_m (6), ab_m (2)], xi the GTSAM Pose3 tangent [omega, v] of T_w_b (retract T Exp(xi)).

Outliers (DSO's residual states): a (point, target) pair whose pattern leaves the
image, or whose raw residual RMS after the depth refinement exceeds max(``outlier_rms``,
twice the median over the host's points in that target; DSO also scales its
threshold with the frame's residual statistics), is left out of this linearization
(a pair whose whole pattern left the image is switched off for good in ``tmask``; one
with more than two pattern pixels outside or saturated sits out the linearization: at a
new keyframe's first linearization its pose is only a prediction, and a few pixels
of error there must not discard a good residual for good); a point whose static stereo RMS exceeds
``outlier_rms`` sits out the linearization, one whose depth reaches the bounds is
switched off in ``alive`` for good.

Rolling shutter (``factors.photometric_shutter.Shutter``, first order in the row time): the
host points arrive as ``bearing + rho sv`` (``factors.photometric.host_points``: each
point moved back from its row's time to the host's row 0), and each target (the right
camera for the stereo term) is sampled at its row's time along its camera twist
(``TW``, ``TV``; ``rw``, ``rv``) and the shutter vector ``sh`` (19,) = [line time (s per
sensor row; 0: global shutter, the same arithmetic as without these arguments), the
left camera's ``row_model`` (9,: the temporal targets), the right camera's (9,)]
(``factors.photometric_host.shutter_args``).

Images are (H, W, 3) float64 stacks [I, dI/du, dI/dv] (``BilinearImage._stack``),
sampled bilinearly with the validity margins of ``BilinearImage``.
"""

from __future__ import annotations

import math

import numpy as np

from factors.jit import njit as _njit
from factors.photometric_warp import _warp, _warp_rs, rho_direction

MAX_LOG_GAIN = 5.0
"""Relative log-gains a_j - a_h are clipped to +-5 (x150) so a diverging affine state can
never overflow exp (gains beyond that are not a camera's exposure change)."""
RHO_STEP_TOL = 0.05
"""Depth refinement stops after a step below 0.05 / sqrt(H_rr) (~0.07 standard deviations
of rho given the poses): a further step would not change the linearization measurably."""
@_njit
def _huber(e2, k):
    """(IRLS weight, cost) of a whitened squared residual e2 under Huber k (k <= 0: none)."""
    if k <= 0.0 or e2 <= k * k:
        return 1.0, 0.5 * e2
    e = math.sqrt(e2)
    return k / e, k * e - 0.5 * k * k


@_njit
def _rho_terms(p, rho, bearing, sv, Ii, wg, hvalid, img, K, R, t, s, b, w0, huber_k, tw, tv, lt, rm):
    """One term of point p at rho, residual I(warp) - b - s I_host (s: gain e^(a_j - a_h),
    b: offset), weight w0 wg: (H_rr, g_r, cost, raw sum r^2, n valid). The host point
    is ``bearing[p, k] + rho sv[p]`` (``factors.photometric.host_points``); ``tw``, ``tv``,
    ``lt``, ``rm`` the target's rolling shutter (:func:`_warp_rs`)."""
    P = bearing.shape[1]
    c0, c1, c2 = sv[p, 0], sv[p, 1], sv[p, 2]
    e0, e1, e2 = rho_direction(R, t, sv, p)
    smp = np.empty(3)
    dq = np.empty(3)
    Hrr = 0.0
    gr = 0.0
    cost = 0.0
    ss = 0.0
    nv = 0
    for k in range(P):
        if not hvalid[p, k]:
            continue
        if lt > 0.0:
            ok, q0, q1, q2, u, v, jx = _warp_rs(bearing[p, k, 0] + rho * c0, bearing[p, k, 1] + rho * c1,
                                                bearing[p, k, 2] + rho * c2, rho, R, t, K, img, smp, dq,
                                                tw, tv, lt, rm, True)
        else:
            ok, q0, q1, q2, u, v = _warp(bearing[p, k, 0], bearing[p, k, 1], bearing[p, k, 2], rho,
                                         R, t, K, img, smp, dq)
            jx = 0.0
        if not ok:
            continue
        r = smp[0] - b - s * Ii[p, k]
        jr = dq[0] * e0 + dq[1] * e1 + dq[2] * e2 + jx
        w = w0 * wg[p, k]
        hw, c = _huber(w * r * r, huber_k)
        Hrr += hw * w * jr * jr
        gr += hw * w * jr * r
        cost += c
        ss += r * r
        nv += 1
    return Hrr, gr, cost, ss, nv


@_njit
def _stereo_terms(p, rho, bearing, sv, Ii, wg, hvalid, st_img, K1, R_rl, t_rl, ab_r, st_w, huber_k,
                  rw, rv, sh):
    """Static stereo of point p at rho (right affine ``ab_r`` relative to the left; ``rw``,
    ``rv`` the right camera's twist, ``sh`` the shutter vector, module docstring)."""
    s = math.exp(min(max(ab_r[0], -MAX_LOG_GAIN), MAX_LOG_GAIN))
    return _rho_terms(p, rho, bearing, sv, Ii, wg, hvalid, st_img, K1, R_rl, t_rl, s, ab_r[1], st_w,
                      huber_k, rw, rv, sh[0], sh[10:19])


@_njit
def _temporal_rho(p, m, rho, bearing, sv, Ii, wg, hvalid, img, K, R, t, ab_h, ab_j, w0, huber_k,
                  tw, tv, sh):
    """Temporal term of point p in target m at rho: I_j - b_j - s (I_h - b_h)."""
    s = math.exp(min(max(ab_j[0] - ab_h[0], -MAX_LOG_GAIN), MAX_LOG_GAIN))
    return _rho_terms(p, rho, bearing, sv, Ii, wg, hvalid, img, K, R, t, s, ab_j[1] - s * ab_h[1], w0,
                      huber_k, tw, tv, sh[0], sh[1:10])


@_njit
def refine_rho(p, rho, bearing, Ii, wg, hvalid, tmask, imgs, K, R_ji, t_ji, ab_h, ab_t, w0,
               st_img, K1, R_rl, t_rl, ab_r, st_w, use_stereo, huber_k, iters, rho_min, rho_max,
               sv, TW, TV, rw, rv, sh):
    """A few damped Gauss-Newton steps on the inverse depth of point p (poses held)."""
    M = R_ji.shape[0]
    for _ in range(iters):
        Hrr = 0.0
        gr = 0.0
        if use_stereo:
            a, b, _c, _s, _n = _stereo_terms(p, rho, bearing, sv, Ii, wg, hvalid, st_img, K1, R_rl,
                                             t_rl, ab_r, st_w, huber_k, rw, rv, sh)
            Hrr += a
            gr += b
        for m in range(M):
            if tmask[p, m]:
                a, b, _c, _s, _n = _temporal_rho(p, m, rho, bearing, sv, Ii, wg, hvalid, imgs[m], K,
                                                 R_ji[m], t_ji[m], ab_h, ab_t[m], w0, huber_k,
                                                 TW[m], TV[m], sh)
                Hrr += a
                gr += b
        if Hrr <= 1e-12:
            break
        step = -gr / Hrr
        lim = 0.25 * rho + 0.02
        step = min(max(step, -lim), lim)
        rho = min(max(rho + step, rho_min), rho_max)
        if abs(step) * math.sqrt(Hrr) < RHO_STEP_TOL:
            break                   # the step was a small fraction of rho's standard deviation
    return rho


@_njit
def _refine_all(bearing, Ii, wg, hvalid, rho, alive, tmask, imgs, K, R_ji, t_ji, ab_h, ab_t, w0,
                st_img, K1, R_rl, t_rl, ab_r, st_w, smask, huber_k, outlier_rms, iters,
                rho_min, rho_max, sv, TW, TV, rw, rv, sh):
    """Pass 1 of :func:`host_system`, one point at a time (a numba ``prange`` over the
    points cost 4x more per call on the shared 2-core machine of the measurements):
    (refined rho (N,), stereo/depth ok (N,))."""
    N, P = Ii.shape
    rp = rho.copy()
    ok_p = alive.copy()
    for p in range(N):
        if not alive[p]:
            continue
        rp[p] = refine_rho(p, rho[p], bearing, Ii, wg, hvalid, tmask, imgs, K, R_ji, t_ji, ab_h, ab_t,
                           w0, st_img, K1, R_rl, t_rl, ab_r, st_w, smask[p], huber_k, iters,
                           rho_min, rho_max, sv, TW, TV, rw, rv, sh)
        if smask[p]:
            a, b, c, ss, nv = _stereo_terms(p, rp[p], bearing, sv, Ii, wg, hvalid, st_img, K1, R_rl,
                                            t_rl, ab_r, st_w, huber_k, rw, rv, sh)
            if nv < P // 2 or ss > outlier_rms * outlier_rms * nv:
                ok_p[p] = False
        if rp[p] <= rho_min or rp[p] >= rho_max:
            ok_p[p] = False
    return rp, ok_p


@_njit
def _pair_rows(bearing, Ii, wg, hvalid, rp, ok_p, tmask, imgs, K, R_ji, t_ji, R_jb, R_b_c, t_b_c,
               ab_h, ab_t, w0, sv, TW, TV, sh):
    """Pass 2 of :func:`host_system`: every (point, target) pair's residuals at the refined
    depth, stored for pass 3 so the pattern RMS that decides the outliers and the
    normal equations share one warp per pixel. Returns (rows (N, M, P, 19) =
    [r, w0 wg, dr/drho, J_host (8), J_target (8)], valid (N, M, P), pattern RMS (N, M):
    -1 for a pattern that left the image, inf for one not judged)."""
    N, P = Ii.shape
    M = R_ji.shape[0]
    lt, rm = sh[0], sh[1:10]
    rows = np.empty((N, M, P, 19))
    valid = np.zeros((N, M, P), np.bool_)
    ms = np.full((N, M), np.inf)
    smp, dq, gb, hh = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for p in range(N):
        if not ok_p[p]:
            continue
        r_p = rp[p]
        nh = 0
        for k in range(P):
            nh += hvalid[p, k]
        for m in range(M):
            if not tmask[p, m]:
                continue
            s = math.exp(min(max(ab_t[m, 0] - ab_h[0], -MAX_LOG_GAIN), MAX_LOG_GAIN))
            R, t, Rjb, tw, tv = R_ji[m], t_ji[m], R_jb[m], TW[m], TV[m]
            c0, c1, c2 = sv[p, 0], sv[p, 1], sv[p, 2]
            e0, e1, e2 = rho_direction(R, t, sv, p)
            ss = 0.0
            nv = 0
            for k in range(P):
                if not hvalid[p, k]:
                    continue
                f0 = bearing[p, k, 0] + r_p * c0     # the host point (host_points)
                f1 = bearing[p, k, 1] + r_p * c1
                f2 = bearing[p, k, 2] + r_p * c2
                if lt > 0.0:     # (a global shutter calls _warp directly: 30% faster)
                    ok, q0, q1, q2, u, v, jx = _warp_rs(f0, f1, f2, r_p, R, t, K, imgs[m], smp, dq,
                                                        tw, tv, lt, rm, True)
                else:
                    ok, q0, q1, q2, u, v = _warp(f0, f1, f2, r_p, R, t, K, imgs[m], smp, dq)
                    jx = 0.0
                if not ok:
                    continue
                row = rows[p, m, k]
                hI = s * (Ii[p, k] - ab_h[1])
                r = smp[0] - ab_t[m, 1] - hI
                ss += r * r
                nv += 1
                valid[p, m, k] = True
                row[0] = r
                row[1] = w0 * wg[p, k]
                row[2] = dq[0] * e0 + dq[1] * e1 + dq[2] * e2 + jx
                for i in range(3):      # g_b = dr/dq R_c_b (row vector)
                    gb[i] = dq[0] * R_b_c[i, 0] + dq[1] * R_b_c[i, 1] + dq[2] * R_b_c[i, 2]
                qb0 = R_b_c[0, 0] * q0 + R_b_c[0, 1] * q1 + R_b_c[0, 2] * q2 + r_p * t_b_c[0]
                qb1 = R_b_c[1, 0] * q0 + R_b_c[1, 1] * q1 + R_b_c[1, 2] * q2 + r_p * t_b_c[1]
                qb2 = R_b_c[2, 0] * q0 + R_b_c[2, 1] * q1 + R_b_c[2, 2] * q2 + r_p * t_b_c[2]
                row[11] = gb[1] * qb2 - gb[2] * qb1      # J_target: rotation, translation, ab
                row[12] = gb[2] * qb0 - gb[0] * qb2
                row[13] = gb[0] * qb1 - gb[1] * qb0
                row[14] = -r_p * gb[0]
                row[15] = -r_p * gb[1]
                row[16] = -r_p * gb[2]
                row[17] = -hI
                row[18] = -1.0
                for i in range(3):      # hh = g_b R_bj_bi
                    hh[i] = gb[0] * Rjb[0, i] + gb[1] * Rjb[1, i] + gb[2] * Rjb[2, i]
                fb0 = R_b_c[0, 0] * f0 + R_b_c[0, 1] * f1 + R_b_c[0, 2] * f2 + r_p * t_b_c[0]
                fb1 = R_b_c[1, 0] * f0 + R_b_c[1, 1] * f1 + R_b_c[1, 2] * f2 + r_p * t_b_c[1]
                fb2 = R_b_c[2, 0] * f0 + R_b_c[2, 1] * f1 + R_b_c[2, 2] * f2 + r_p * t_b_c[2]
                row[3] = fb1 * hh[2] - fb2 * hh[1]       # J_host
                row[4] = fb2 * hh[0] - fb0 * hh[2]
                row[5] = fb0 * hh[1] - fb1 * hh[0]
                row[6] = r_p * hh[0]
                row[7] = r_p * hh[1]
                row[8] = r_p * hh[2]
                row[9] = hI
                row[10] = s
            if nv == 0:
                ms[p, m] = -1.0                   # out of the image: off for good
            elif nv >= nh - 2:
                ms[p, m] = math.sqrt(ss / nv)
    return rows, valid, ms


@_njit
def host_system(bearing, Ii, wg, hvalid, rho, alive, tmask, imgs, K, R_ji, t_ji, R_jb, R_b_c,
                t_b_c, ab_h, ab_t, w0, st_img, K1, R_rl, t_rl, ab_r, st_w, smask, huber_k,
                outlier_rms, iters, rho_min, rho_max, update, rms, sv, TW, TV, rw, rv, sh):
    """Reduced normal equations of one host (module docstring).

    ``smask`` (N,) bool: the points that carry the static stereo term (their depth came
    from the stereo pair; the others' from a temporal search, ``vio.direct.temporal``).
    Returns (H (n, n), g (n,), cost, reduced cost, n points used); with ``update`` the
    refined rho and the outlier masks are written back into ``rho``/``alive``/``tmask``,
    and each (point, target) pair's pattern RMS into ``rms`` (N, >= M; ``_pair_rows``'s:
    -1 left the image, inf not judged or the point failed its stereo or depth check).
    Rolling shutter (module docstring): ``sv`` (N, 3), ``TW``, ``TV`` (M, 3), ``rw``, ``rv``
    (3,), ``sh`` (19,: line time and the two cameras' row models).
    """
    N, P = Ii.shape
    M = R_ji.shape[0]
    n = 8 * (M + 1)
    H = np.zeros((n, n))
    g = np.zeros(n)
    hx = np.zeros(n)
    cost = 0.0
    red = 0.0
    used = 0
    # pass 1: refined depths and stereo check; pass 2: residual rows and pattern RMS of
    # every (point, target)
    rp, ok_p = _refine_all(bearing, Ii, wg, hvalid, rho, alive, tmask, imgs, K, R_ji, t_ji,
                           ab_h, ab_t, w0, st_img, K1, R_rl, t_rl, ab_r, st_w, smask,
                           huber_k, outlier_rms, iters, rho_min, rho_max, sv, TW, TV, rw, rv, sh)
    rows, valid, ms = _pair_rows(bearing, Ii, wg, hvalid, rp, ok_p, tmask, imgs, K, R_ji, t_ji,
                                 R_jb, R_b_c, t_b_c, ab_h, ab_t, w0, sv, TW, TV, sh)
    if update:
        rms[:, :M] = ms          # inf where pass 1 left the point out
    # outlier thresholds per target: outlier_rms, or twice the median point RMS where
    # the whole image fits worse (blur, a changed exposure not yet estimated)
    th = np.full(M, outlier_rms)
    for m in range(M):
        col = ms[:, m][ok_p & np.isfinite(ms[:, m]) & (ms[:, m] >= 0.0)]
        if col.size:
            th[m] = max(outlier_rms, 2.0 * np.median(col))
    # pass 3: normal equations (upper triangle, mirrored at the end), rho eliminated
    for p in range(N):
        if not alive[p]:
            continue
        if not ok_p[p]:
            if update and (rp[p] <= rho_min or rp[p] >= rho_max):
                alive[p] = False            # depth out of range: for good
            continue                        # stereo misfit: off at this linearization
        Hrr = 0.0
        gr = 0.0
        cp = 0.0
        if smask[p]:
            a, b, c, ss, nv = _stereo_terms(p, rp[p], bearing, sv, Ii, wg, hvalid, st_img, K1, R_rl,
                                            t_rl, ab_r, st_w, huber_k, rw, rv, sh)
            Hrr += a
            gr += b
            cp += c
        for i in range(n):
            hx[i] = 0.0
        any_t = False
        for m in range(M):
            if not tmask[p, m]:
                continue
            if ms[p, m] < 0.0:
                if update:
                    tmask[p, m] = False     # left the image: for good
                continue
            if not ms[p, m] <= th[m]:
                continue                    # misfit or clipped: off at this linearization only
            any_t = True
            o = 8 * (m + 1)
            for k in range(P):
                if not valid[p, m, k]:
                    continue
                row = rows[p, m, k]
                r, jr = row[0], row[2]
                w = row[1]
                hw, c = _huber(w * r * r, huber_k)
                w *= hw
                cp += c
                for i in range(8):
                    wi = w * row[3 + i]
                    for j in range(i, 8):
                        H[i, j] += wi * row[3 + j]
                    for j in range(8):
                        H[i, o + j] += wi * row[11 + j]
                    g[i] += wi * r
                    hx[i] += wi * jr
                    wt = w * row[11 + i]
                    for j in range(i, 8):
                        H[o + i, o + j] += wt * row[11 + j]
                    g[o + i] += wt * r
                    hx[o + i] += wt * jr
                Hrr += w * jr * jr
                gr += w * jr * r
        cost += cp
        if update:
            rho[p] = rp[p]
        if not any_t:
            red += cp - (0.5 * gr * gr / Hrr if Hrr > 1e-12 else 0.0)
            continue
        used += 1
        if Hrr > 1e-12:
            inv = 1.0 / Hrr
            for i in range(n):
                if hx[i] == 0.0:
                    continue
                a = hx[i] * inv
                g[i] -= a * gr
                for j in range(i, n):
                    H[i, j] -= a * hx[j]
            red += cp - 0.5 * gr * gr * inv
        else:
            red += cp
    for i in range(n):
        for j in range(i + 1, n):
            H[j, i] = H[i, j]
    return H, g, cost, red, used
