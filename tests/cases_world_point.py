"""Jacobian cases of the world-point td projection factor (``factors/world_point.py``),
collected by ``tests/test_jacobians.py``: a point seen from n keyframes (the first one's
pose is the scene's anchor), observations with pixel-level noise, td and rolling-shutter
offsets, the extrinsic held or a key; degenerate: zero image velocity, a far point, n = 1,
and a point behind a camera."""

from __future__ import annotations

import gtsam
import numpy as np

from cases_projection import scene
from factors.world_point import world_point_factor, world_point_residual
from jacobian_case import JacobianCase

X, P, T, E = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.P, gtsam.symbol_shorthand.T, gtsam.symbol_shorthand.E


def point_case(name: str, n: int = 3, *, use_td: bool = True, vel_scale: float = 1.0, behind: bool = False,
               ext: bool = False, degenerate: bool = False, **scene_kw) -> JacobianCase:
    def build(rng: np.random.Generator):
        Ti, poses, Tc, lam, uvi, uvs = scene(rng, max(n - 1, 1), **scene_kw)
        bodies = [Ti, *poses][:n]
        uv = np.vstack([uvi[None, :], np.asarray(uvs).reshape(-1, 2)])[:n]
        p_w = Ti.compose(Tc).transformFrom(np.append(uvi, 1.0) / lam) + rng.normal(size=3) * 0.01
        if behind:   # the point behind the first camera: constant residual, zero Jacobian rows
            p_w = Ti.compose(Tc).transformFrom(np.array([0.1, 0.0, -1.0]))
        vel = rng.normal(size=(n, 2)) * vel_scale
        off = rng.uniform(-0.01, 0.01, size=n)
        td = 0.012 if use_td else None
        keys = [P(0)] + [X(i) for i in range(n)] + ([E(0)] if ext else []) + ([T(0)] if use_td else [])
        factor = world_point_factor(P(0), [X(i) for i in range(n)], T(0) if use_td else None, E(0) if ext else Tc,
                                    uv, vel, off, 0.01)
        values = gtsam.Values()
        values.insert(P(0), np.asarray(p_w, float))
        for i, B in enumerate(bodies):
            values.insert(X(i), B)
        if ext:
            values.insert(E(0), Tc)
        if use_td:
            values.insert(T(0), np.array([td]))
        kinds = [3] + ["pose3"] * (n + ext) + ([1] if use_td else [])

        def residual(v: gtsam.Values):
            args = [v.atPose3(k) if kind == "pose3" else v.atVector(k) for k, kind in zip(keys, kinds)]
            r, J = world_point_residual(args[0], args[1 + n] if ext else Tc, args[1:1 + n], uv, vel, off,
                                        float(args[-1][0]) if use_td else None, 0.01, ext=ext)
            cols = np.cumsum([0] + [6 if k == "pose3" else k for k in kinds])
            return r, [J[:, a:b] for a, b in zip(cols[:-1], cols[1:])]

        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


CASES: list[JacobianCase] = [
    point_case("world_point_td"),
    point_case("world_point_no_td", use_td=False),
    point_case("world_point_five_views", n=5),
    point_case("world_point_zero_velocity", vel_scale=0.0, degenerate=True),
    point_case("world_point_far", lam=1e-3, degenerate=True),
    point_case("world_point_single_view", n=1, degenerate=True),
    point_case("world_point_behind", behind=True, degenerate=True),
    point_case("world_point_extrinsic", ext=True),
    point_case("world_point_extrinsic_no_td", n=4, use_td=False, ext=True),
    point_case("world_point_extrinsic_single_view", n=1, ext=True, degenerate=True),
]
