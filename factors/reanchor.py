"""Depth transfer between two inverse-depth keys of one landmark (re-anchoring).

A landmark anchored in keyframe a (key ``lambda_o``, ray ``uv_a``) whose anchor leaves the
fixed-lag window gets a new key ``lambda_n`` anchored in a later keyframe a'. The old key
carries information from observations already marginalized (a prior on ``lambda_o`` and
the poses); this factor states that both keys describe the same point, so when
``lambda_o`` is marginalized that information moves to ``lambda_n`` instead of decaying
into two-view constraints. With the seed-004 transfer of the old anchor's point into
camera a' (:func:`factors.projection.transfer_point`, ``Q = lambda_o P_ca'``), its depth
there is ``z = Q_z / lambda_o``, and the residual

    r = (lambda_n * Q_z - lambda_o) / lambda_ref      (dimensionless, 1-vector)

is ``lambda_o / lambda_ref * (lambda_n z - 1)``: the relative depth error at the build-time
inverse depth ``lambda_ref`` (a constant), bilinear in the two keys and smooth for far
points (``lambda_o -> 0``), where dividing by ``lambda_o`` would not be.

Only the depth is tied: the new anchor's own ray fixes the point's direction. With td the
old anchor's ray is the shifted ``uv_a - (td + offset_a) vel_a`` of the td factors.

Keys: ``[lambda_o, lambda_n, T_b_c, T_w_ba, T_w_ba']`` (+ ``td``). Jacobians are exact for
GTSAM's retraction (``tests/cases_reanchor.py``).
"""

from __future__ import annotations

from typing import Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.stack import Member
from factors.projection import COL_LAM, COL_TC, COL_TI, COL_TJ, transfer_point
from factors.td_projection import shift_uv


def depth_transfer_residual(args: list, uv_a: np.ndarray, lam_ref: float,
                            vel_a: np.ndarray | None = None, offset_a: float = 0.0
                            ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual (1,) and Jacobians in key order.

    ``args``: ``[lambda_o (1,), lambda_n (1,), T_b_c, T_w_ba, T_w_ba']`` (+ ``td (1,)``, which
    uses ``vel_a`` (2,), the old anchor's image velocity in 1/s, and ``offset_a`` (s));
    ``lam_ref`` (1/m, > 0): the scale of the relative error.
    """
    lam_o, lam_n = float(args[0][0]), float(args[1][0])
    use_td = len(args) > 5
    uv = np.asarray(uv_a, float)
    vel = np.zeros(2) if vel_a is None else np.asarray(vel_a, float)
    if use_td:
        uv = shift_uv(uv, vel, offset_a, float(args[5][0]))
    Q, M, D = transfer_point(args[3].matrix(), args[4].matrix(), args[2].matrix(), lam_o, uv)
    s = lam_n / lam_ref
    r = np.array([(lam_n * Q[2] - lam_o) / lam_ref])
    J = [np.array([[(lam_n * D[2, COL_LAM] - 1.0) / lam_ref]]),
         np.array([[Q[2] / lam_ref]]),
         s * D[2:3, COL_TC:COL_TC + 6], s * D[2:3, COL_TI:COL_TI + 6], s * D[2:3, COL_TJ:COL_TJ + 6]]
    if use_td:
        J.append(np.array([[-s * (M[2, :2] @ vel)]]))
    return r, J


def depth_transfer_factor(keys: Sequence[int], uv_a: np.ndarray, lam_ref: float, sigma: float = 1e-4,
                          vel_a: np.ndarray | None = None, offset_a: float = 0.0,
                          health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """``gtsam.CustomFactor`` on ``[lambda_o, lambda_n, T_b_c, T_w_ba, T_w_ba']`` (+ ``td``):
    the two inverse depths describe one point, to a relative depth ``sigma`` at the old
    key's inverse depth ``lam_ref`` (1/m, its estimate when the factor is built)."""
    mem = depth_transfer_member(keys, uv_a, lam_ref, sigma, vel_a, offset_a)
    return custom_factor(gtsam.noiseModel.Isotropic.Sigma(1, float(sigma)), mem.keys, mem.kinds, mem.fn,
                         health, cache=True)


def depth_transfer_member(keys: Sequence[int], uv_a: np.ndarray, lam_ref: float, sigma: float = 1e-4,
                          vel_a: np.ndarray | None = None, offset_a: float = 0.0) -> Member:
    """The depth-transfer residual (``depth_transfer_factor``) for a stack (``factors.stack``)."""
    keys = [int(k) for k in keys]
    if len(keys) not in (5, 6) or len(set(keys)) != len(keys):
        raise ValueError(f"depth_transfer_factor needs 5 or 6 distinct keys, got {keys}")
    if not (sigma > 0 and lam_ref > 0):
        raise ValueError(f"sigma and lam_ref must be > 0, got {sigma}, {lam_ref}")
    kinds = [1, 1, "pose3", "pose3", "pose3"] + [1] * (len(keys) - 5)
    uv = np.asarray(uv_a, float).reshape(2)
    vel_a = None if vel_a is None else np.array(vel_a, float)   # owned: fn is pure, cached

    def fn(args: list) -> tuple[np.ndarray, list[np.ndarray]]:
        return depth_transfer_residual(args, uv, lam_ref, vel_a, offset_a)

    return Member(tuple(keys), tuple(kinds), fn, 1, float(sigma))
