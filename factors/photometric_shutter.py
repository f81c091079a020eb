"""The rolling shutter of the photometric terms (seed 004's row time, first order in it).

Row y of an image is exposed ``y * line_time`` after row 0, the frame's state time; over
the readout each camera moves along a constant twist [omega, v] in its own frame. A host
point is moved back to its row 0 (``rolled_bearings``); a target point's row time is its
projected row's (``target_row_s``: through the lens where a ``row_model`` is given). The
warps that use them: ``factors.photometric`` (the numpy reference), the compiled kernels
of ``factors.photometric_warp`` and ``factors.trackframe_kernel``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.photometric_warp import sensor_rows


def cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """a x b over the last axis into ``out`` (np.cross is slow for small arrays)."""
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


@dataclass(frozen=True, eq=False)
class Shutter:
    """Rolling shutter of one photometric term (seed 004's row time, to first order in it):
    row y of an image is exposed ``y * line_time_s`` after its row 0, whose time is the
    frame's state time, and over the readout each camera moves along a constant twist
    ``[omega (rad/s), v (m/s)]`` (6,) in its own frame, so a point p_c of the row-0 camera
    is at p_c - s (omega x p_c + v) in the camera of the row exposed s later.
    ``host``, ``target``: the two cameras' twists (constants of the factor, as the KLT
    factors' predicted image velocities). The host's whole pattern takes its centre row's
    time (``HostPatch.uv``; 2 rows are ~60 us); the target row is the projected row.
    ``host_rows``, ``target_rows``: the two cameras' ``factors.photometric_warp.row_model``
    where a lens bends the sensor rows (a row's time is its *sensor* row's); None: the
    undistorted pinhole row."""

    line_time_s: float
    host: np.ndarray
    target: np.ndarray
    host_rows: np.ndarray | None = None
    target_rows: np.ndarray | None = None


def rolled_bearings(bearing: np.ndarray, row_s: np.ndarray, twist: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Host bearings f (N, P, 3) of points seen ``row_s`` (N,) s after the host's row 0,
    moved back to row 0 along the host camera's ``twist`` [omega, v] (6,) to first order:
    (f + s (omega x f) (N, P, 3), s v (N, 3)); the scaled point is the first plus rho times
    the second."""
    s = np.asarray(row_s, float)[:, None, None]
    w, v = np.asarray(twist[:3], float), np.asarray(twist[3:], float)
    f = bearing + s * cross(np.broadcast_to(w, bearing.shape), bearing, np.empty(bearing.shape))
    return f, s[:, :, 0] * v


def target_row_s(shutter: Shutter, K, q: np.ndarray, z: np.ndarray):
    """Row time s (..., 1) of the target points q (..., 3) (depth ``z``) and its
    derivatives in q0 / z and q1 / z (...,): the sensor row of ``shutter.target_rows``, or
    the pinhole row of ``K`` (``factors.photometric.Pinhole``: fy, cy)."""
    lt = shutter.line_time_s
    if shutter.target_rows is None:
        return (lt * (K.fy * q[..., 1] / z + K.cy))[..., None], np.zeros(z.shape), np.full(z.shape, lt * K.fy)
    x, y = (q[..., 0] / z).ravel(), (q[..., 1] / z).ravel()
    row, gx, gy = sensor_rows(np.ascontiguousarray(x), np.ascontiguousarray(y), shutter.target_rows)
    return (lt * row).reshape(z.shape)[..., None], (lt * gx).reshape(z.shape), (lt * gy).reshape(z.shape)
