"""Numba warps of the photometric kernels (``factors.photometric_kernel``,
``factors.trackframe_kernel``): a host point's scaled form q = R f + rho t into a target
image, bilinear sampling of [I, dI/du, dI/dv], dr/dq, and the rolling-shutter variant
(``factors.photometric.Shutter``, first order in the row time). The numpy reference of
the same arithmetic is ``factors.photometric._warp``, whose Jacobians the shared suite
checks numerically.
"""

from __future__ import annotations

from factors.jit import njit as _njit

MIN_Z = 1e-6
SATURATED = 250.0
DARK = 5.0
"""Intensities at or above ``SATURATED`` or at or below ``DARK`` are clipped by the sensor:
such target samples (and host pixels, ``HostPoints.create``) carry no residual (the
affine brightness model does not hold there)."""


@_njit
def sample(stack, u, v, out):
    """Bilinear [I, gx, gy] at (u, v) into ``out`` (3,); False outside the valid area."""
    h, w = stack.shape[0], stack.shape[1]
    if not (u >= 1.0 and u < w - 2.0 and v >= 1.0 and v < h - 2.0):
        return False
    u0, v0 = int(u), int(v)
    fx, fy = u - u0, v - v0
    for c in range(3):
        a = stack[v0, u0, c] + fx * (stack[v0, u0 + 1, c] - stack[v0, u0, c])
        b = stack[v0 + 1, u0, c] + fx * (stack[v0 + 1, u0 + 1, c] - stack[v0 + 1, u0, c])
        out[c] = a + fy * (b - a)
    return True


@_njit
def _warp_any(f0, f1, f2, rho, R, t, K, stack, smp, dq):
    """Target pixel of the scaled point q = R f + rho t; fills smp = [I, gx, gy] and
    dq = dr/dq (3,) and returns (ok, q0, q1, q2, u, v); ok: in front of the camera and
    inside the valid image area, whatever the intensity."""
    q0 = R[0, 0] * f0 + R[0, 1] * f1 + R[0, 2] * f2 + rho * t[0]
    q1 = R[1, 0] * f0 + R[1, 1] * f1 + R[1, 2] * f2 + rho * t[1]
    q2 = R[2, 0] * f0 + R[2, 1] * f1 + R[2, 2] * f2 + rho * t[2]
    if q2 <= MIN_Z:
        return False, q0, q1, q2, 0.0, 0.0
    u = K[0] * q0 / q2 + K[2]
    v = K[1] * q1 / q2 + K[3]
    if not sample(stack, u, v, smp):
        return False, q0, q1, q2, u, v
    gu = smp[1] * K[0] / q2
    gv = smp[2] * K[1] / q2
    dq[0] = gu
    dq[1] = gv
    dq[2] = -(gu * q0 + gv * q1) / q2
    return True, q0, q1, q2, u, v


@_njit
def _warp(f0, f1, f2, rho, R, t, K, stack, smp, dq):
    """:func:`_warp_any`, not ok on a clipped target sample (>= ``SATURATED``, <= ``DARK``)."""
    ok, q0, q1, q2, u, v = _warp_any(f0, f1, f2, rho, R, t, K, stack, smp, dq)
    return ok and not (smp[0] >= SATURATED or smp[0] <= DARK), q0, q1, q2, u, v


@_njit
def rho_direction(R, t, sv, p):
    """d q / d rho of point p's scaled warp q = R (f + rho sv[p]) + rho t: t + R sv[p]
    (3 floats; t without a rolling shutter, where sv is zero)."""
    c0, c1, c2 = sv[p, 0], sv[p, 1], sv[p, 2]
    return (t[0] + R[0, 0] * c0 + R[0, 1] * c1 + R[0, 2] * c2,
            t[1] + R[1, 0] * c0 + R[1, 1] * c1 + R[1, 2] * c2,
            t[2] + R[2, 0] * c0 + R[2, 1] * c1 + R[2, 2] * c2)


@_njit
def _warp_rs(f0, f1, f2, rho, R, t, K, stack, smp, dq, w, vel, lt, rf, rc, clip):
    """:func:`_warp` (``clip``; else :func:`_warp_any`) in a rolling-shutter target
    (``factors.photometric.Shutter``: twist ``w``, ``vel`` of the target camera, ``lt`` s
    per row of the full-resolution image, whose row of a point q is rf q1 / q2 + rc: K's
    own fy, cy at full resolution, a pyramid level's TrackFrame passes level 0's): q = R f +
    rho t is the point in the row-0 camera, the image is sampled at q_s = q - s (w x q +
    rho vel), s = lt * row(q). Returns (ok, q0, q1, q2 (q, not q_s), u, v, jx) with
    dq = dr/dq through q_s and s, and jx = dr/drho at fixed q, -s dr/dq_s vel."""
    q0 = R[0, 0] * f0 + R[0, 1] * f1 + R[0, 2] * f2 + rho * t[0]
    q1 = R[1, 0] * f0 + R[1, 1] * f1 + R[1, 2] * f2 + rho * t[1]
    q2 = R[2, 0] * f0 + R[2, 1] * f1 + R[2, 2] * f2 + rho * t[2]
    if q2 <= MIN_Z:
        return False, q0, q1, q2, 0.0, 0.0, 0.0
    s = lt * (rf * q1 / q2 + rc)
    a0 = w[1] * q2 - w[2] * q1 + rho * vel[0]
    a1 = w[2] * q0 - w[0] * q2 + rho * vel[1]
    a2 = w[0] * q1 - w[1] * q0 + rho * vel[2]
    r0, r1, r2 = q0 - s * a0, q1 - s * a1, q2 - s * a2
    if r2 <= MIN_Z:
        return False, q0, q1, q2, 0.0, 0.0, 0.0
    u = K[0] * r0 / r2 + K[2]
    v = K[1] * r1 / r2 + K[3]
    if not sample(stack, u, v, smp) or (clip and (smp[0] >= SATURATED or smp[0] <= DARK)):
        return False, q0, q1, q2, u, v, 0.0
    gu = smp[1] * K[0] / r2
    gv = smp[2] * K[1] / r2
    gz = -(gu * r0 + gv * r1) / r2
    jx = -s * (gu * vel[0] + gv * vel[1] + gz * vel[2])
    # dq_s/dq = I - s [w]x - a (ds/dq)^T, ds/dq = lt rf [0, 1/q2, -q1/q2^2]
    da = gu * a0 + gv * a1 + gz * a2
    k = lt * rf / q2
    dq[0] = gu - s * (gv * w[2] - gz * w[1])
    dq[1] = gv - s * (gz * w[0] - gu * w[2]) - da * k
    dq[2] = gz - s * (gu * w[1] - gv * w[0]) + da * k * q1 / q2
    return True, q0, q1, q2, u, v, jx
