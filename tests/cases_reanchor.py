"""Jacobian cases of the depth-transfer factor (``factors/reanchor.py``), collected by
``tests/test_jacobians.py``. The new key is set near the true depth of the old anchor's
point in the new anchor camera, off by a few percent so the residual is non-zero."""

from __future__ import annotations

import gtsam
import numpy as np

from cases_projection import scene
from factors.reanchor import depth_transfer_factor, depth_transfer_residual
from jacobian_case import JacobianCase

X, C, L, T = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.L,
              gtsam.symbol_shorthand.T)


def transfer_case(name: str, *, use_td: bool = False, vel_scale: float = 1.0,
                  degenerate: bool = False, **scene_kw) -> JacobianCase:
    def build(rng: np.random.Generator):
        Ti, (Tj,), Tc, lam, uvi, _ = scene(rng, 1, **scene_kw)
        z_new = Tj.compose(Tc).transformTo(Ti.compose(Tc).transformFrom(np.append(uvi, 1.0) / lam))[2]
        lam_n = (1.0 + rng.uniform(-0.05, 0.05)) / z_new
        vel, off = rng.normal(size=2) * vel_scale, float(rng.uniform(-0.01, 0.01))
        keys = [L(0), L(1), C(0), X(0), X(1)] + ([T(0)] if use_td else [])
        factor = depth_transfer_factor(keys, uvi, lam, 1e-3, vel if use_td else None, off)
        vals = [np.array([lam]), np.array([lam_n]), Tc, Ti, Tj] + ([np.array([0.011])] if use_td else [])
        values = gtsam.Values()
        for k, x in zip(keys, vals):
            values.insert(k, x)
        kinds = [1, 1, "pose3", "pose3", "pose3"] + ([1] if use_td else [])

        def residual(v: gtsam.Values):
            args = [v.atPose3(k) if kind == "pose3" else v.atVector(k) for k, kind in zip(keys, kinds)]
            return depth_transfer_residual(args, uvi, lam, vel if use_td else None, off)

        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


CASES: list[JacobianCase] = [
    transfer_case("depth_transfer"),
    transfer_case("depth_transfer_td", use_td=True),
    transfer_case("depth_transfer_far", use_td=True, lam=1e-3, degenerate=True),
    transfer_case("depth_transfer_tiny_motion", parallax=1e-6, rot=1e-6, degenerate=True),
    transfer_case("depth_transfer_td_zero_velocity", use_td=True, vel_scale=0.0, degenerate=True),
]
