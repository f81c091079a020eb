"""Jacobian cases of the constant-velocity motion prior (``factors/motion_prior.py``, the
IMU-gap bridge), collected by ``tests/test_jacobians.py``: random keyframe pairs; degenerate:
identical attitudes (Log at the identity), a rotation near pi, and a tiny interval."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.motion_prior import motion_prior_factor, motion_prior_residual
from jacobian_case import JacobianCase

X, V = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V


def prior_case(name: str, *, rot: float = 0.3, dt: float = 0.2, same_attitude: bool = False,
               degenerate: bool = False) -> JacobianCase:
    def build(rng: np.random.Generator):
        Ti = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
        axis = rng.normal(size=3)
        d = axis / np.linalg.norm(axis) * rot
        Rj = Ti.rotation() if same_attitude else Ti.rotation().compose(gtsam.Rot3.Expmap(d))
        vi = rng.normal(size=3)
        Tj = gtsam.Pose3(Rj, Ti.translation() + vi * dt + rng.normal(size=3) * 0.05)
        vj = vi + rng.normal(size=3) * 0.3
        keys = [X(0), V(0), X(1), V(1)]
        factor = motion_prior_factor(keys, dt, 1.0, 0.5)
        values = gtsam.Values()
        for k, x in zip(keys, [Ti, vi, Tj, vj]):
            values.insert(k, x)
        kinds = ["pose3", 3, "pose3", 3]

        def residual(v: gtsam.Values):
            args = [v.atPose3(k) if kind == "pose3" else v.atVector(k) for k, kind in zip(keys, kinds)]
            return motion_prior_residual(args, dt)

        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


CASES: list[JacobianCase] = [
    prior_case("motion_prior"),
    prior_case("motion_prior_long_gap", rot=1.2, dt=3.0),
    prior_case("motion_prior_same_attitude", same_attitude=True, degenerate=True),
    prior_case("motion_prior_near_pi", rot=np.pi - 1e-3, degenerate=True),
    prior_case("motion_prior_tiny_interval", rot=1e-7, dt=1e-3, degenerate=True),
]
