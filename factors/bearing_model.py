"""The bearing residual models of the projection factors (seed 004), on a point ``Q`` in
camera j (any positive scale: ``factors.projection`` passes ``lambda * P_cj``) and the
measured normalized-plane observation ``uv_j``.

Residual models (2-vectors, normalized-plane / radian units):

* ``"pinhole"``: ``r = Q_xy / Q_z - uv_j`` (seed 004, non-unit-sphere section).
* ``"sphere"``: ``r = B (Q/|Q| - m_j/|m_j|)``, ``m_j = [u_j, v_j, 1]`` and ``B`` (2x3) an
  orthonormal tangent basis of the *measured* bearing (seed 004, unit-sphere section).
  ``B`` is a constant of the measurement (see :func:`tangent_basis`).

Cheirality: a pinhole residual whose point is not in front of camera j
(``Q_z <= MIN_COS * |Q|``, i.e. more than ~89.9 deg off axis or behind) and a sphere
residual with ``|Q| <= MIN_NORM`` return the constant residual
``[BEHIND_CAMERA_RESIDUAL] * 2`` with all-zero Jacobians (like GTSAM's
``GenericProjectionFactor`` with ``throwCheirality=false``): finite, it penalizes LM steps
that move the point behind the camera but never pulls on the linear system. The sphere
residual of a point behind camera j is smooth and stays bounded (``|r| <= 2``), so it is
evaluated normally. ``lambda < 0`` (point behind the anchor) is not rejected here; the
backend must treat it as a failed landmark. A NaN state gives a NaN residual, which the
adapter contains (factor zeroed, counted in ``FactorHealth``).
"""

from __future__ import annotations

import numpy as np

from factors.jit import njit as _njit

MODELS = ("pinhole", "sphere")
BEHIND_CAMERA_RESIDUAL = 2.0
"""Residual component returned for a point not in front of camera j (normalized units)."""
MIN_COS = 1e-3
"""Pinhole cheirality threshold on ``Q_z / |Q|``."""
MIN_NORM = 1e-12
"""Sphere degeneracy threshold on ``|Q|`` (``|Q| ~ |m_i|`` >= 1 for sane states)."""


def check_model(model: str) -> str:
    """Return ``model`` if it is one of :data:`MODELS`, else raise ``ValueError``."""
    if model not in MODELS:
        raise ValueError(f"unknown residual model {model!r}; use one of {MODELS}")
    return model


def homogeneous(uv: np.ndarray) -> np.ndarray:
    """``[u, v] -> [u, v, 1]`` for (2,) or (n, 2) normalized-plane points."""
    uv = np.asarray(uv, dtype=float)
    return np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1)


def tangent_basis(uv: np.ndarray) -> np.ndarray:
    """Orthonormal tangent basis ``B`` (n, 2, 3) of the bearings of ``uv`` (n, 2).

    Row 0 is ``[1, 0, -u] / sqrt(1 + u^2)`` (orthogonal to ``[u, v, 1]``), row 1 is
    ``b x row0 = [-u v, 1 + u^2, -v] / (sqrt(1 + u^2) |m|)`` with ``b = m / |m|`` the unit
    bearing. Smooth in ``uv`` everywhere (unlike VINS's
    switch on the z axis). The td factor builds ``B`` from the raw (unshifted) observation,
    so ``B`` never depends on a variable. Compiled (a landmark's factor is built at every
    keyframe; ~10 numpy calls on a few rows cost ~15 us, this ~1 us; same arithmetic).
    """
    uv = np.ascontiguousarray(uv, dtype=float).reshape(-1, 2)
    B = np.zeros((uv.shape[0], 2, 3))
    _tangent_basis_into(uv, B)
    return B


@_njit
def _tangent_basis_into(uv: np.ndarray, B: np.ndarray) -> None:
    for i in range(uv.shape[0]):
        u, v = uv[i, 0], uv[i, 1]
        s = np.sqrt(1.0 + u * u)
        sn = s * np.sqrt(1.0 + u * u + v * v)
        B[i, 0, 0], B[i, 0, 2] = 1.0 / s, -u / s
        B[i, 1, 0], B[i, 1, 1], B[i, 1, 2] = -u * v / sn, (1.0 + u * u) / sn, -v / sn


@_njit
def _model_into(Q: np.ndarray, uv: np.ndarray, B: np.ndarray, sphere: bool, r: np.ndarray,
                dQ: np.ndarray, duv: np.ndarray) -> bool:
    """Residual r (2,), dr/dQ (2, 3) and dr/duv_j (2, 2) of one point; False if invalid."""
    nQ = np.sqrt(Q[0] * Q[0] + Q[1] * Q[1] + Q[2] * Q[2])
    if not sphere:
        if Q[2] <= MIN_COS * nQ:  # (a NaN state falls through and stays NaN)
            return False
        iz = 1.0 / Q[2]
        x, y = Q[0] * iz, Q[1] * iz
        r[0], r[1] = x - uv[0], y - uv[1]
        dQ[0, 0], dQ[0, 1], dQ[0, 2] = iz, 0.0, -x * iz
        dQ[1, 0], dQ[1, 1], dQ[1, 2] = 0.0, iz, -y * iz
        duv[0, 0], duv[0, 1], duv[1, 0], duv[1, 1] = -1.0, 0.0, 0.0, -1.0
        return True
    if nQ <= MIN_NORM:
        return False
    nm = np.sqrt(uv[0] * uv[0] + uv[1] * uv[1] + 1.0)
    b = np.array([uv[0] / nm, uv[1] / nm, 1.0 / nm])
    for k in range(2):
        Bq = (B[k, 0] * Q[0] + B[k, 1] * Q[1] + B[k, 2] * Q[2]) / nQ
        Bb = B[k, 0] * b[0] + B[k, 1] * b[1] + B[k, 2] * b[2]
        r[k] = Bq - Bb
        for c in range(3):
            dQ[k, c] = (B[k, c] - Bq * Q[c] / nQ) / nQ
        for c in range(2):
            duv[k, c] = -(B[k, c] - Bb * b[c]) / nm
    return True
