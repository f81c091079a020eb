"""Jacobian cases of the stereo (cam1) landmark factor (``factors/stereo.py``),
collected by ``tests/test_jacobians.py``. Right observations include the anchor
keyframe itself (static stereo), so the anchor key receives two Jacobian terms."""

from __future__ import annotations

import gtsam
import numpy as np

from cases_projection import random_pose
from factors.robust import RobustKernel
from factors.anchor_noise import anchor_whitening
from factors.stereo import make_stereo_track, stereo_anchor_jacobian, stereo_factor, stereo_residual
from jacobian_case import JacobianCase

X, E, L, T = (gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.E, gtsam.symbol_shorthand.L,
              gtsam.symbol_shorthand.T)
SIGMA = 0.01


def _scene(rng: np.random.Generator, n: int, far: bool, tiny: bool):
    """Anchor + n bodies, stereo rig (~11 cm baseline), a point in front of all cams."""
    T_b_c0 = random_pose(rng, 0.3, 0.05)
    T_c0_c1 = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.01), np.array([0.11, 0, 0]))
    T_b_c1 = T_b_c0.compose(T_c0_c1)
    for _ in range(500):
        Ta = random_pose(rng, 1.0, 2.0)
        lam = 1e-3 if far else rng.uniform(0.2, 1.0)
        uva = rng.uniform([-0.4, -0.3], [0.4, 0.3])
        p_w = Ta.compose(T_b_c0).transformFrom(np.append(uva, 1.0) / lam)
        bodies = [Ta] + [Ta.compose(random_pose(rng, 1e-6 if tiny else 0.1,
                                                1e-6 if tiny else 0.3)) for _ in range(n)]
        uvs, uvs0 = [], []
        for Tb in bodies:
            p = Tb.compose(T_b_c1).transformTo(p_w)
            p0 = Tb.compose(T_b_c0).transformTo(p_w)
            if p[2] < 0.2 * np.linalg.norm(p) or p0[2] < 0.2 * np.linalg.norm(p0):
                break
            uvs.append(p[:2] / p[2] + rng.normal(size=2) * 0.01)
            uvs0.append(p0[:2] / p0[2] + rng.normal(size=2) * 0.01)
        if len(uvs) == len(bodies):
            return T_b_c0, T_b_c1, Ta, bodies[1:], lam, uva, np.array(uvs), np.array(uvs0[1:])
    raise RuntimeError("no valid stereo scene")


def stereo_case(name: str, model: str, *, n: int = 3, use_td: bool = False,
                robust: str | None = None, far: bool = False, tiny: bool = False,
                degenerate: bool = False, mixed: bool = False,
                anchor_noise: bool = False) -> JacobianCase:
    """``mixed``: the cam0 observations of the non-anchor bodies join the cam1 ones
    in the same factor (one callback per stereo landmark); ``anchor_noise``: the factor
    whitens with the anchor-noise matrix of the case's state."""
    def build(rng: np.random.Generator):
        Tc0, Tc1, Ta, others, lam, uva, uvs, uvs0 = _scene(rng, n, far, tiny)
        C = Tc1.compose(Tc0.inverse())
        body_keys = [X(0)] + [X(k + 1) for k in range(n)]
        obs_keys, right = body_keys, [True] * (n + 1)
        if mixed:   # interleave cam0 observations of bodies 1..n
            obs_keys = body_keys + body_keys[1:]
            right = right + [False] * n
            uvs = np.vstack([uvs, uvs0.reshape(-1, 2)])
        m = len(obs_keys)
        track = make_stereo_track(X(0), uva, obs_keys, uvs, C, anchor_vel=rng.normal(size=2),
                                  vel=rng.normal(size=(m, 2)), anchor_offset=0.003,
                                  offset=rng.uniform(-0.01, 0.01, m), right=right)
        kernel = RobustKernel(robust) if robust else None
        values = gtsam.Values()
        values.insert(L(0), np.array([lam]))
        values.insert(E(0), Tc0)
        for k, Tb in zip(body_keys, [Ta] + others):
            values.insert(k, Tb)
        if use_td:
            values.insert(T(0), np.array([0.007]))
        kinds = [1, "pose3", "pose3"] + ["pose3"] * n + ([1] if use_td else [])

        def args_of(v: gtsam.Values) -> list:
            return [v.atVector(L(0)), v.atPose3(E(0))] + [v.atPose3(k) for k in body_keys] + (
                [v.atVector(T(0))] if use_td else [])

        W = (anchor_whitening(stereo_anchor_jacobian(args_of(values), track, model, use_td))
             if anchor_noise else None)
        factor = stereo_factor(track, L(0), E(0), SIGMA, model, kernel, T(0) if use_td else None,
                               whiten=W)

        def residual(v: gtsam.Values):
            r, J = stereo_residual(args_of(v), track, model, SIGMA, None, use_td, W)
            ends = np.cumsum([1, 6, 6] + [6] * n + ([1] if use_td else []))
            return r, [J[:, a:b] for a, b in zip(np.r_[0, ends[:-1]], ends)]

        if robust:  # frozen-weight check is in the landmark cases; here weights stay 1
            r0, _ = residual(values)
            assert np.abs(r0).max() / SIGMA < 1.345, "robust stereo case must stay in the quadratic zone"
        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


CASES: list[JacobianCase] = [
    stereo_case("stereo_pinhole", "pinhole"),
    stereo_case("stereo_sphere", "sphere"),
    stereo_case("stereo_pinhole_td", "pinhole", use_td=True),
    stereo_case("stereo_sphere_td", "sphere", use_td=True),
    stereo_case("stereo_pinhole_far", "pinhole", far=True, degenerate=True),
    stereo_case("stereo_sphere_tiny_motion", "sphere", tiny=True, degenerate=True),
    stereo_case("stereo_pinhole_anchor_only", "pinhole", n=0, degenerate=True),
    stereo_case("stereo_mixed_pinhole_td", "pinhole", use_td=True, mixed=True),
    stereo_case("stereo_mixed_sphere", "sphere", mixed=True, n=4),
    stereo_case("stereo_mixed_tiny_motion", "pinhole", tiny=True, mixed=True, degenerate=True),
    stereo_case("stereo_mixed_pinhole_td_anchor_noise", "pinhole", use_td=True, mixed=True,
                anchor_noise=True),
    stereo_case("stereo_sphere_anchor_noise_anchor_only", "sphere", n=0, anchor_noise=True,
                degenerate=True),
]
