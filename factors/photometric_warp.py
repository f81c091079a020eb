"""Numba warps of the photometric kernels (``factors.photometric_kernel``,
``factors.trackframe_kernel``): a host point's scaled form q = R f + rho t into a target
image, bilinear sampling of [I, dI/du, dI/dv], dr/dq, and the rolling-shutter variant
(``factors.photometric_shutter.Shutter``, first order in the row time). The numpy reference of
the same arithmetic is ``factors.photometric._warp``, whose Jacobians the shared suite
checks numerically.

A rolling shutter exposes the *sensor's* rows one after the other; the photometric terms
work on undistorted pinhole images, where a sensor row is a curve (up to ~50 rows from a
straight row at the corners of EuRoC's k1 = -0.28 lens). ``row_model`` describes the
camera a row time comes from (intrinsics and lens) and ``sensor_row`` gives the sensor row
of an undistorted point with its derivatives; a pinhole model (no lens) is the pinhole row.
"""

from __future__ import annotations

import numpy as np

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


PINHOLE, RADTAN, EQUIDISTANT = 0.0, 1.0, 2.0
_MODELS = {"none": PINHOLE, "radial-tangential": RADTAN, "equidistant": EQUIDISTANT}


def row_model(K, model: str = "none", D=(0.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """The sensor-row model (9,) of a camera: [fx, fy, cx, cy] of its full-resolution
    intrinsics (the undistorted image keeps them), the lens (``model`` "none",
    "radial-tangential" (D = k1, k2, p1, p2) or "equidistant" (D = k1..k4)) as a code,
    and D."""
    if model not in _MODELS:
        raise ValueError(f"row_model: unknown distortion model {model!r}")
    d = np.zeros(4) if model == "none" else np.asarray(D, float).reshape(4)
    return np.concatenate([np.asarray(K, float).reshape(4), [_MODELS[model]], d])


def rows_or_pinhole(rows: np.ndarray | None, K) -> np.ndarray:
    """``rows`` (a ``row_model``), or where None (no lens) the pinhole row model of ``K``
    (anything with fx, fy, cx, cy)."""
    return row_model((K.fx, K.fy, K.cx, K.cy)) if rows is None else rows


@_njit
def sensor_row(x, y, m):
    """Sensor row (full-resolution pixels) of the undistorted normalized point (x, y) in
    the camera of row model ``m`` (:func:`row_model`), and its derivatives in x and y:
    fy y_d + cy with y_d the lens's distorted y (y itself without a lens)."""
    fy, cy, kind = m[1], m[3], m[4]
    if kind == PINHOLE:
        return fy * y + cy, 0.0, fy
    if kind == RADTAN:
        k1, k2, p1, p2 = m[5], m[6], m[7], m[8]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        c = 2.0 * (k1 + 2.0 * k2 * r2)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        dx = c * x * y + 2.0 * p1 * x + 2.0 * p2 * y
        dy = radial + c * y * y + 6.0 * p1 * y + 2.0 * p2 * x
        return fy * yd + cy, fy * dx, fy * dy
    r = np.sqrt(x * x + y * y)        # equidistant: y_d = y theta_d / r
    if r < 1e-9:
        return fy * y + cy, 0.0, fy
    th = np.arctan(r)
    t2 = th * th
    td = th * (1.0 + t2 * (m[5] + t2 * (m[6] + t2 * (m[7] + t2 * m[8]))))
    dtd = 1.0 + t2 * (3.0 * m[5] + t2 * (5.0 * m[6] + t2 * (7.0 * m[7] + t2 * 9.0 * m[8])))
    f = td / r
    df = (dtd / (1.0 + r * r) * r - td) / (r * r)      # d(theta_d / r) / dr
    return fy * y * f + cy, fy * y * df * x / r, fy * (f + y * df * y / r)


@_njit
def sensor_rows(x, y, m):
    """:func:`sensor_row` of 1-D arrays ``x``, ``y``: (rows, d/dx, d/dy), each (N,)."""
    n = x.shape[0]
    row, gx, gy = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        row[i], gx[i], gy[i] = sensor_row(x[i], y[i], m)
    return row, gx, gy


def pixel_row_s(line_time_s: float, uv: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """Row times (N,) s of undistorted full-resolution pixels ``uv`` (N, 2): ``line_time_s``
    times their sensor row (``rows``: a :func:`row_model`; None: the pixel row itself)."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    if rows is None:
        return line_time_s * uv[:, 1]
    x = np.ascontiguousarray((uv[:, 0] - rows[2]) / rows[0])
    y = np.ascontiguousarray((uv[:, 1] - rows[3]) / rows[1])
    return line_time_s * sensor_rows(x, y, rows)[0]


@_njit
def _warp_rs(f0, f1, f2, rho, R, t, K, stack, smp, dq, w, vel, lt, rm, clip):
    """:func:`_warp` (``clip``; else :func:`_warp_any`) in a rolling-shutter target
    (``factors.photometric_shutter.Shutter``: twist ``w``, ``vel`` of the target camera, ``lt`` s
    per sensor row, ``rm`` the target camera's :func:`row_model` at full resolution, which a
    pyramid level's TrackFrame passes too): q = R f + rho t is the point in the row-0
    camera, the image is sampled at q_s = q - s (w x q + rho vel), s = lt * row(q).
    Returns (ok, q0, q1, q2 (q, not q_s), u, v, jx) with dq = dr/dq through q_s and s,
    and jx = dr/drho at fixed q, -s dr/dq_s vel."""
    q0 = R[0, 0] * f0 + R[0, 1] * f1 + R[0, 2] * f2 + rho * t[0]
    q1 = R[1, 0] * f0 + R[1, 1] * f1 + R[1, 2] * f2 + rho * t[1]
    q2 = R[2, 0] * f0 + R[2, 1] * f1 + R[2, 2] * f2 + rho * t[2]
    if q2 <= MIN_Z:
        return False, q0, q1, q2, 0.0, 0.0, 0.0
    lens = rm[4] != PINHOLE
    if lens:
        row, rx, ry = sensor_row(q0 / q2, q1 / q2, rm)
        s = lt * row
    else:
        s = lt * (rm[1] * q1 / q2 + rm[3])
        rx, ry = 0.0, 0.0
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
    # dq_s/dq = I - s [w]x - a (ds/dq)^T, ds/dq = lt (rx d(q0/q2)/dq + ry d(q1/q2)/dq),
    # without a lens lt fy [0, 1/q2, -q1/q2^2]
    da = gu * a0 + gv * a1 + gz * a2
    dq[0] = gu - s * (gv * w[2] - gz * w[1])
    dq[1] = gv - s * (gz * w[0] - gu * w[2])
    dq[2] = gz - s * (gu * w[1] - gv * w[0])
    if lens:
        kx, ky = lt * rx / q2, lt * ry / q2
        dq[0] -= da * kx
        dq[1] -= da * ky
        dq[2] += da * (kx * q0 + ky * q1) / q2
    else:
        k = lt * rm[1] / q2
        dq[1] -= da * k
        dq[2] += da * k * q1 / q2
    return True, q0, q1, q2, u, v, jx
