"""World-point projection factor with time offset (seed 004's td shift on a ``p_w`` landmark).

One factor per landmark over its observations in several keyframes: the landmark is a
world point ``p_w`` (3-vector, m) instead of an inverse depth on an anchor ray, so every
observation, the first included, is an ordinary measurement. Residual of observation i
(normalized pinhole coordinates of cam0, 2 rows):

    p_b = R_w_b_i^T (p_w - t_w_b_i),  p_c = R_b_c^T (p_b - t_b_c)
    r_i = pi(p_c) - (uv_i - (td + off_i) vel_i),   pi(p) = (p_x / p_z, p_y / p_z)

(seed 004: the observation moved to its keyframe's time by the image velocity ``vel_i``
times the observation's offset from it, ``td`` plus the rolling-shutter / sync offset
``off_i``). Jacobians: ``d r / d p_w = dpi R_b_c^T R_w_b^T``; for the body pose with
GTSAM's right perturbation ``T Exp([w, v])``, ``d p_b / d w = [p_b]x`` and
``d p_b / d v = -I``; ``d r / d td = vel_i``. The extrinsic ``T_b_c`` is either a
constant of the factor or a key of it (online calibration), perturbed the same way:
``p_c' = Exp(-w) (p_c - v)``, so ``d p_c / d w = [p_c]x`` and ``d p_c / d v = -I``. A
point behind the camera (``p_z`` below 1 mm) gives the constant
``BEHIND_CAMERA_RESIDUAL`` and zero Jacobian rows. A robust kernel reweights each
observation's 2 rows (IRLS, ``factors.robust``).
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.adapter import custom_factor
from factors.jit import njit
from factors.bearing_model import BEHIND_CAMERA_RESIDUAL

MIN_DEPTH = 1e-3


@njit
def world_point_eval(p_w: np.ndarray, R_bc: np.ndarray, t_bc: np.ndarray, bodies: np.ndarray,
                     uv: np.ndarray, vel: np.ndarray, off: np.ndarray, td: float, use_td: bool,
                     sigma: float, kind: int, kk: float, r: np.ndarray, J: np.ndarray,
                     use_ext: bool) -> None:
    """Fill ``r`` (2n,) and ``J`` (2n, 3 + 6n [+6] [+1]; zeroed on entry): columns ``p_w``
    (0:3), body i at ``3 + 6 i``, the extrinsic at ``3 + 6 n`` when ``use_ext``, td last
    when ``use_td``. ``bodies`` (n, 4, 4) ``T_w_b``,
    ``uv`` / ``vel`` (n, 2), ``off`` (n,); ``kind`` 0 none, 1 Huber, 2 Cauchy at ``kk``
    sigmas of ``sigma``."""
    n = uv.shape[0]
    pb, pc = np.empty(3), np.empty(3)
    A, B = np.empty((2, 3)), np.empty((2, 3))
    for o in range(n):
        for a in range(3):
            s = 0.0
            for b in range(3):
                s += bodies[o, b, a] * (p_w[b] - bodies[o, b, 3])
            pb[a] = s
        for a in range(3):
            s = 0.0
            for b in range(3):
                s += R_bc[b, a] * (pb[b] - t_bc[b])
            pc[a] = s
        row = 2 * o
        if pc[2] < MIN_DEPTH:
            r[row] = BEHIND_CAMERA_RESIDUAL
            r[row + 1] = BEHIND_CAMERA_RESIDUAL
            continue
        z = pc[2]
        sh = td + off[o] if use_td else 0.0
        r[row] = pc[0] / z - (uv[o, 0] - sh * vel[o, 0])
        r[row + 1] = pc[1] / z - (uv[o, 1] - sh * vel[o, 1])
        # A = dpi/dp_c, B = A R_b_c^T  (d r / d p_b)
        for k in range(2):
            for c in range(3):
                dpi_c = (1.0 / z if c == k else 0.0) - (pc[k] / (z * z) if c == 2 else 0.0)
                A[k, c] = dpi_c
        for k in range(2):
            for c in range(3):
                s = 0.0
                for e in range(3):
                    s += A[k, e] * R_bc[c, e]
                B[k, c] = s
        col = 3 + 6 * o
        for k in range(2):
            # d r / d p_w = B R_w_b^T
            for c in range(3):
                s = 0.0
                for e in range(3):
                    s += B[k, e] * bodies[o, c, e]
                J[row + k, c] = s
            # d r / d w = B [p_b]x ; d r / d v = -B
            J[row + k, col + 0] = B[k, 1] * pb[2] - B[k, 2] * pb[1]
            J[row + k, col + 1] = B[k, 2] * pb[0] - B[k, 0] * pb[2]
            J[row + k, col + 2] = B[k, 0] * pb[1] - B[k, 1] * pb[0]
            for c in range(3):
                J[row + k, col + 3 + c] = -B[k, c]
            if use_ext:   # d r / d w_bc = A [p_c]x ; d r / d v_bc = -A
                ce = 3 + 6 * n
                J[row + k, ce + 0] = A[k, 1] * pc[2] - A[k, 2] * pc[1]
                J[row + k, ce + 1] = A[k, 2] * pc[0] - A[k, 0] * pc[2]
                J[row + k, ce + 2] = A[k, 0] * pc[1] - A[k, 1] * pc[0]
                for c in range(3):
                    J[row + k, ce + 3 + c] = -A[k, c]
            if use_td:
                J[row + k, J.shape[1] - 1] = vel[o, k]
    if kind != 0:
        for o in range(n):
            s = np.sqrt(r[2 * o] ** 2 + r[2 * o + 1] ** 2) / sigma
            w = (1.0 if s <= kk else kk / s) if kind == 1 else 1.0 / (1.0 + (s / kk) ** 2)
            sw = np.sqrt(w)
            for k in range(2):
                r[2 * o + k] *= sw
                for c in range(J.shape[1]):
                    J[2 * o + k, c] *= sw


def world_point_residual(p_w: np.ndarray, T_b_c: gtsam.Pose3, bodies: list[gtsam.Pose3], uv: np.ndarray,
                         vel: np.ndarray, off: np.ndarray, td: float | None, sigma: float = 1.0,
                         kernel: tuple[int, float] = (0, 0.0), ext: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(r (2n,), J (2n, 3 + 6n [+6] [+1]))`` of the module's residual (``ext``: with the
    extrinsic's columns; td None: no td term or column); ``kernel`` (kind, k) as
    :func:`world_point_eval`."""
    n = len(bodies)
    use_td = td is not None
    r, J = np.zeros(2 * n), np.zeros((2 * n, 3 + 6 * n + 6 * ext + use_td))
    Tb = np.array([T.matrix() for T in bodies]).reshape(n, 4, 4)
    world_point_eval(np.asarray(p_w, float), T_b_c.rotation().matrix(), np.asarray(T_b_c.translation(), float),
                     Tb, np.ascontiguousarray(uv, float).reshape(n, 2), np.ascontiguousarray(vel, float).reshape(n, 2),
                     np.ascontiguousarray(off, float).reshape(n), float(td or 0.0), use_td, float(sigma),
                     int(kernel[0]), float(kernel[1]), r, J, bool(ext))
    return r, J


def world_point_factor(point_key: int, body_keys: list[int], td_key: int | None, T_b_c: gtsam.Pose3 | int,
                       uv: np.ndarray, vel: np.ndarray, off: np.ndarray, sigma: float,
                       kernel: tuple[int, float] = (0, 0.0)) -> gtsam.CustomFactor:
    """The ``CustomFactor`` over ``p_w`` (3-vector key), the bodies' ``T_w_b``, the
    extrinsic when ``T_b_c`` is its key (an int; a ``Pose3``: held constant) and, with
    ``td_key``, td (1-vector); ``sigma`` the observation noise (normalized units)."""
    n = len(body_keys)
    uv = np.ascontiguousarray(uv, float).reshape(n, 2)
    vel = np.ascontiguousarray(vel, float).reshape(n, 2)
    off = np.ascontiguousarray(off, float).reshape(n)
    use_ext = not isinstance(T_b_c, gtsam.Pose3)
    if not use_ext:
        R_bc, t_bc = T_b_c.rotation().matrix(), np.asarray(T_b_c.translation(), float)
    use_td = td_key is not None
    kind, kk = int(kernel[0]), float(kernel[1])
    keys = ([int(point_key), *[int(k) for k in body_keys]] + ([int(T_b_c)] if use_ext else [])
            + ([int(td_key)] if use_td else []))
    kinds = [3] + ["pose3"] * (n + use_ext) + ([1] if use_td else [])
    cols = 3 + 6 * (n + use_ext) + use_td

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        r, J = np.zeros(2 * n), np.zeros((2 * n, cols), order="F")
        Tb = np.array([T.matrix() for T in args[1:1 + n]])
        if use_ext:
            E = args[1 + n].matrix()
            R, t = np.ascontiguousarray(E[:3, :3]), E[:3, 3].copy()
        else:
            R, t = R_bc, t_bc
        world_point_eval(args[0], R, t, Tb, uv, vel, off, float(args[-1][0]) if use_td else 0.0,
                         use_td, float(sigma), kind, kk, r, J, use_ext)
        return r, J

    return custom_factor(gtsam.noiseModel.Isotropic.Sigma(2 * n, float(sigma)), keys, kinds, fn, cache=True)
