"""Jacobian cases of the stacked factor (``factors/stack.py``), collected by
``tests/test_jacobians.py``: a re-anchored landmark's farewell observation (a projection
residual of the new key) and its depth transfer, stacked with a second landmark's
transfer that shares the extrinsic and the poses, as ``vio.backend.tracks`` stacks them."""

from __future__ import annotations

import gtsam
import numpy as np

from cases_projection import scene
from factors.projection import projection_residual
from factors.reanchor import depth_transfer_member
from factors.stack import Member, stacked_factor
from jacobian_case import JacobianCase

X, C, L, T = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.L,
              gtsam.symbol_shorthand.T)


def _farewell(uv_i: np.ndarray, uv_j: np.ndarray, sigma: float) -> Member:
    """Projection of the new key's point (anchor X(1)) into the leaving keyframe X(0)."""
    def fn(args):
        lam, T_b_c, T_i, T_j = args
        r, J = projection_residual(T_i, T_j, T_b_c, float(lam[0]), uv_i, uv_j)
        return r, _reorder(J)
    return Member((L(1), C(0), X(1), X(0)), (1, "pose3", "pose3", "pose3"), fn, 2, sigma)


def _reorder(J: list) -> list:
    """projection_residual's [Ti, Tj, Tbc, lam] blocks in the member's key order."""
    return [J[3], J[2], J[0], J[1]]


def stack_case(name: str, *, use_td: bool = False, degenerate: bool = False, **scene_kw) -> JacobianCase:
    def build(rng: np.random.Generator):
        T0, (T1,), Tc, lam0, uv0, (uv1,) = scene(rng, 1, **scene_kw)
        p_w = T0.compose(Tc).transformFrom(np.append(uv0, 1.0) / lam0)
        lam1 = (1.0 + rng.uniform(-0.05, 0.05)) / T1.compose(Tc).transformTo(p_w)[2]
        lam2, lam3 = rng.uniform(0.2, 1.0, size=2)
        uv2 = rng.uniform(-0.4, 0.4, size=2)
        vel, off = rng.normal(size=(2, 2)), rng.uniform(-0.01, 0.01, size=2)
        td = [T(0)] if use_td else []
        farewell = _farewell(uv1, uv0 + rng.normal(size=2) * 0.01, 0.01)
        t1 = depth_transfer_member([L(0), L(1), C(0), X(0), X(1)] + td, uv0, lam0, 1e-3,
                                   vel[0] if use_td else None, off[0])
        t2 = depth_transfer_member([L(2), L(3), C(0), X(0), X(1)] + td, uv2, lam2, 2e-3,
                                   vel[1] if use_td else None, off[1])
        members = [farewell, t1, t2]
        factor = stacked_factor(members)
        keys = [int(k) for k in factor.keys()]   # the members' keys, first seen first
        kind_of = {k: kind for mem in members for k, kind in zip(mem.keys, mem.kinds)}
        kinds = [kind_of[k] for k in keys]
        val_of = {L(1): np.array([lam1]), C(0): Tc, X(1): T1, X(0): T0, L(0): np.array([lam0]),
                  L(2): np.array([lam2]), L(3): np.array([lam3]), T(0): np.array([0.007])}
        values = gtsam.Values()
        for k in keys:
            values.insert(k, val_of[k])

        def residual(v: gtsam.Values):
            r, J = [], []
            for mem in members:
                args = [v.atPose3(k) if kind == "pose3" else v.atVector(k) for k, kind in zip(mem.keys, mem.kinds)]
                rm, Jm = mem.fn(args)
                blocks = {k: np.asarray(j, float) / mem.sigma for k, j in zip(mem.keys, Jm)}
                r.append(np.asarray(rm, float) / mem.sigma)
                J.append([blocks.get(k, np.zeros((mem.m, 6 if kind == "pose3" else kind)))
                          for k, kind in zip(keys, kinds)])
            return np.concatenate(r), [np.vstack([Jm[i] for Jm in J]) for i in range(len(keys))]

        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


CASES: list[JacobianCase] = [
    stack_case("stack_farewell_transfers"),
    stack_case("stack_farewell_transfers_td", use_td=True),
    stack_case("stack_tiny_motion", parallax=1e-6, rot=1e-6, degenerate=True),
]
