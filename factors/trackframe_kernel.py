"""Numba kernel of TrackFrame's residual rows (``vio.direct.trackframe``): the temporal
photometric residual of keyframe points in a new frame, its whitened rows and their
Jacobian with respect to the new frame's pose and affine brightness, in one pass.

Same arithmetic as ``factors.photometric.temporal_eval`` with the host at the identity
and T_b_c = I (the keyframe camera is the reference) followed by ``sqrt_weights``; the
warp is the host factor's (``factors.photometric_warp._warp_any``) without its test
for clipped pixels:

    q = R f + rho t  ((R, t) = T_kf_new^-1, keyframe camera -> new camera),
    r = I_new(pi(q)) - b_j - s (I_ref - b_i),  s = e^(a_j - a_i),
    W = c^2 / (c^2 + |grad I_ref|^2) / (2 sigma_I^2 + (dr/drho)^2 V),
    row = sqrt(W) [r ; (g x q, -rho g) ; -s (I_ref - b_i), -1]     (g = dr/dq),

the pose columns along ``T Exp(xi)``, xi = [omega, v] (GTSAM). With a rolling shutter
(``lt`` > 0, ``factors.photometric_shutter.Shutter``) the keyframe points arrive moved back to
its row 0 (``bearing + rho sv``) and the new frame is sampled at each row's time along
its camera twist (``w``, ``vel``; ``factors.photometric_warp._warp_rs``, sensor rows of
the full-resolution camera ``rm``, a ``row_model``), g = dr/dq through that, and dr/drho = g (t + R sv)
- s g_s vel. Rows of pattern pixels
that are invalid (behind the camera, outside the valid image area, host pixel
invalid) get the constant ``oob`` residual and a zero Jacobian. The numpy path built
~25 temporary arrays per evaluation (``np.stack`` alone was 8% of direct mode's time).
"""

from __future__ import annotations

import math

import numpy as np

from factors.jit import njit as _njit
from factors.photometric_warp import _warp_any, _warp_rs, rho_direction


@_njit
def track_rows(bearing, Ii, grad_sq, hvalid, rho, var, R, t, K, stack, s, b_i, b_j, c2, two_s2, oob,
               r_w, J, r_raw, valid, sv, w, vel, lt, rm):
    """Fill the whitened residuals ``r_w`` (N P,), Jacobian ``J`` (N P, 8), the raw
    residuals ``r_raw`` (N, P) and ``valid`` (N, P). ``s`` the relative gain e^(a_j - a_i),
    ``b_i``, ``b_j`` the offsets; ``var`` (N,) inverse-depth variances (zeros: no V term);
    the rolling shutter ``sv`` (N, 3), ``w``, ``vel`` (3,), ``lt``, ``rm`` (9,) (module
    docstring; ``lt`` 0: none)."""
    N, P = Ii.shape
    smp = np.empty(3)
    dq = np.empty(3)
    for p in range(N):
        rp = rho[p]
        o0, o1, o2 = sv[p, 0] * rp, sv[p, 1] * rp, sv[p, 2] * rp   # rho sv
        e0, e1, e2 = rho_direction(R, t, sv, p)
        for k in range(P):
            row = p * P + k
            valid[p, k] = False
            r_raw[p, k] = 0.0
            r_w[row] = oob
            for c in range(8):
                J[row, c] = 0.0
            if not hvalid[p, k]:
                continue
            if lt > 0.0:
                ok, q0, q1, q2, _u, _v, jx = _warp_rs(bearing[p, k, 0] + o0, bearing[p, k, 1] + o1,
                                                      bearing[p, k, 2] + o2, rp, R, t, K, stack, smp, dq,
                                                      w, vel, lt, rm, False)
            else:
                ok, q0, q1, q2, _u, _v = _warp_any(bearing[p, k, 0], bearing[p, k, 1], bearing[p, k, 2],
                                                   rp, R, t, K, stack, smp, dq)
                jx = 0.0
            if not ok:
                continue
            valid[p, k] = True
            gu, gv, gz = dq[0], dq[1], dq[2]
            h = s * (Ii[p, k] - b_i)
            r = smp[0] - b_j - h
            r_raw[p, k] = r
            drho = gu * e0 + gv * e1 + gz * e2 + jx
            sw = math.sqrt(c2 / (c2 + grad_sq[p, k]) / (two_s2 + drho * drho * var[p]))
            r_w[row] = sw * r
            J[row, 0] = sw * (gv * q2 - gz * q1)
            J[row, 1] = sw * (gz * q0 - gu * q2)
            J[row, 2] = sw * (gu * q1 - gv * q0)
            J[row, 3] = -sw * rp * gu
            J[row, 4] = -sw * rp * gv
            J[row, 5] = -sw * rp * gz
            J[row, 6] = -sw * h
            J[row, 7] = -sw
