"""Jacobian cases of the projection factors (``factors/projection.py``,
``factors/td_projection.py``, ``factors/landmark.py``), collected by ``tests/test_jacobians.py``.

States are built around a true landmark seen by all frames; the observations get
~0.01 (normalized units) of noise so that residuals, and with them the target-dependent
Jacobian terms, are non-zero. Robust landmark cases plant an outlier so that some IRLS
weights are < 1; their residual function freezes the weights at the case's state (the
factor treats them as constants of the linearization, see ``factors/landmark.py``).
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.landmark import (landmark_anchor_jacobian, landmark_factor, landmark_residual,
                              landmark_weights, make_track)
from factors.anchor_noise import anchor_whitening
from factors.projection import projection_factor, projection_residual
from factors.robust import RobustKernel, robust_noise
from factors.td_projection import TdObservation, td_projection_factor, td_projection_residual
from jacobian_case import JacobianCase

X = gtsam.symbol_shorthand.X  # body poses
C = gtsam.symbol_shorthand.C  # extrinsic T_b_c
L = gtsam.symbol_shorthand.L  # inverse depth
T = gtsam.symbol_shorthand.T  # td
SIGMA = 0.01
U_MAX, V_MAX = 0.69, 0.52  # image border in normalized units (640x480, f = 460)


def random_pose(rng: np.random.Generator, rot: float, trans: float) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * rot), rng.normal(size=3) * trans)


def project(T_w_b: gtsam.Pose3, T_b_c: gtsam.Pose3, p_w: np.ndarray) -> np.ndarray | None:
    """Normalized observation of world point ``p_w``, or None when behind the camera."""
    p = T_w_b.compose(T_b_c).transformTo(p_w)
    return p[:2] / p[2] if p[2] > 0.05 * np.linalg.norm(p) else None


def scene(rng: np.random.Generator, n: int, *, parallax: float = 0.3, rot: float = 0.15,
          lam: float | None = None, uv_i: np.ndarray | None = None, same_pose: bool = False,
          noise: float = 0.01):
    """Anchor pose, n target poses, extrinsic, inverse depth, anchor uv and n target uvs."""
    for _ in range(500):
        T_b_c = random_pose(rng, 0.5, 0.1)
        T_i = random_pose(rng, 1.0, 2.0)
        lam_ = rng.uniform(0.1, 1.5) if lam is None else lam
        uvi = rng.uniform([-0.5, -0.4], [0.5, 0.4]) if uv_i is None else np.asarray(uv_i, float)
        p_w = T_i.compose(T_b_c).transformFrom(np.append(uvi, 1.0) / lam_)
        poses, uvs = [], []
        for _ in range(n):
            Tj = T_i if same_pose else T_i.compose(random_pose(rng, rot, parallax))
            uvj = project(Tj, T_b_c, p_w)
            if uvj is None or np.abs(uvj).max() > 1.5:
                break
            poses.append(Tj)
            uvs.append(uvj + rng.normal(size=2) * noise)
        if len(poses) == n:
            return T_i, poses, T_b_c, lam_, uvi, np.array(uvs)
    raise RuntimeError("no valid random scene")


def _values(pairs: list) -> gtsam.Values:
    v = gtsam.Values()
    for k, x in pairs:
        v.insert(k, x)
    return v


def projection_case(name: str, model: str, *, robust: str | None = None,
                    degenerate: bool = False, **scene_kw) -> JacobianCase:
    def build(rng: np.random.Generator):
        Ti, (Tj,), Tc, lam, uvi, uvj = scene(rng, 1, **scene_kw)
        keys = [X(0), X(1), C(0), L(0)]
        noise = gtsam.noiseModel.Isotropic.Sigma(2, SIGMA)
        if robust:
            noise = robust_noise(noise, RobustKernel(robust))
        factor = projection_factor(noise, keys, uvi, uvj[0], model)
        values = _values(list(zip(keys, [Ti, Tj, Tc, np.array([lam])])))

        def residual(v: gtsam.Values):
            return projection_residual(v.atPose3(keys[0]), v.atPose3(keys[1]), v.atPose3(keys[2]),
                                       v.atVector(keys[3])[0], uvi, uvj[0], model)

        return factor, values, residual, ["pose3", "pose3", "pose3", 1]

    return JacobianCase(name, build, degenerate)


def td_case(name: str, model: str, *, td: float = 0.012, vel_scale: float = 1.0,
            readout: float = 0.03, degenerate: bool = False, **scene_kw) -> JacobianCase:
    def build(rng: np.random.Generator):
        Ti, (Tj,), Tc, lam, uvi, uvj = scene(rng, 1, **scene_kw)
        oi = TdObservation.create(uvi, rng.normal(size=2) * vel_scale, row=rng.uniform(0, 480),
                                  rows=480, t_readout=readout, td_obs=rng.uniform(-0.01, 0.01))
        oj = TdObservation.create(uvj[0], rng.normal(size=2) * vel_scale,
                                  row=rng.uniform(0, 480), rows=480, t_readout=readout)
        keys = [X(0), X(1), C(0), L(0), T(0)]
        factor = td_projection_factor(gtsam.noiseModel.Isotropic.Sigma(2, SIGMA), keys, oi, oj,
                                      model)
        values = _values(list(zip(keys, [Ti, Tj, Tc, np.array([lam]), np.array([td])])))

        def residual(v: gtsam.Values):
            return td_projection_residual(v.atPose3(keys[0]), v.atPose3(keys[1]),
                                          v.atPose3(keys[2]), v.atVector(keys[3])[0],
                                          v.atVector(keys[4])[0], oi, oj, model)

        return factor, values, residual, ["pose3", "pose3", "pose3", 1, 1]

    return JacobianCase(name, build, degenerate)


def landmark_case(name: str, model: str, *, n: int = 5, use_td: bool = False,
                  robust: str | None = None, with_anchor_obs: bool = False,
                  anchor_noise: bool = False, degenerate: bool = False,
                  **scene_kw) -> JacobianCase:
    """``anchor_noise``: the factor whitens its residual with the anchor-noise matrix W of
    the case's state (a constant of the factor, as in the backend)."""
    def build(rng: np.random.Generator):
        Ti, poses, Tc, lam, uvi, uvs = scene(rng, n, **scene_kw)
        if robust:
            uvs[1] += [0.08, -0.05]  # an outlier: its IRLS weight drops well below 1
        frame_keys = [X(k + 1) for k in range(n)]
        obs_keys, obs_uv = list(frame_keys), uvs
        if with_anchor_obs:  # dropped by make_track (constant residual)
            obs_keys, obs_uv = [X(0)] + obs_keys, np.vstack([uvi, uvs])
        m = len(obs_keys)
        track = make_track(X(0), uvi, obs_keys, obs_uv, anchor_vel=rng.normal(size=2),
                           vel=rng.normal(size=(m, 2)), anchor_offset=0.004,
                           offset=rng.uniform(-0.01, 0.02, m))
        kernel = RobustKernel(robust) if robust else None
        values = _values([(L(0), np.array([lam])), (C(0), Tc), (X(0), Ti)]
                         + list(zip(frame_keys, poses))
                         + ([(T(0), np.array([0.009]))] if use_td else []))
        kinds = [1, "pose3", "pose3"] + ["pose3"] * n + ([1] if use_td else [])

        def args_of(v: gtsam.Values) -> list:
            return [v.atVector(L(0)), v.atPose3(C(0)), v.atPose3(X(0))] + [
                v.atPose3(k) for k in frame_keys] + ([v.atVector(T(0))] if use_td else [])

        W = (anchor_whitening(landmark_anchor_jacobian(args_of(values), track, model, use_td))
             if anchor_noise else None)
        factor = landmark_factor(track, L(0), C(0), SIGMA, model, kernel,
                                 T(0) if use_td else None, whiten=W)

        w0 = landmark_weights(args_of(values), track, model, SIGMA, kernel, use_td)
        if robust:
            assert w0.min() < 0.9, "robust case must have an active (down-weighted) observation"

        def residual(v: gtsam.Values):
            return landmark_residual(args_of(v), track, model, SIGMA, kernel, use_td, weights=w0,
                                     whiten=W)

        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


BORDER = np.array([U_MAX - 0.01, -V_MAX + 0.01])

CASES: list[JacobianCase] = [
    projection_case("projection_pinhole", "pinhole"),
    projection_case("projection_sphere", "sphere"),
    projection_case("projection_pinhole_gtsam_huber", "pinhole", robust="huber", noise=0.05),
    projection_case("projection_sphere_gtsam_cauchy", "sphere", robust="cauchy", noise=0.05),
    td_case("td_pinhole", "pinhole"),
    td_case("td_sphere", "sphere"),
    landmark_case("landmark_pinhole", "pinhole"),
    landmark_case("landmark_sphere", "sphere"),
    landmark_case("landmark_pinhole_td", "pinhole", use_td=True),
    landmark_case("landmark_sphere_td", "sphere", use_td=True),
    landmark_case("landmark_pinhole_huber", "pinhole", robust="huber"),
    landmark_case("landmark_sphere_td_cauchy", "sphere", use_td=True, robust="cauchy"),
    landmark_case("landmark_pinhole_td_anchor_noise", "pinhole", use_td=True, anchor_noise=True),
    landmark_case("landmark_sphere_huber_anchor_noise", "sphere", robust="huber", anchor_noise=True),
    # degenerate states
    projection_case("projection_pinhole_tiny_parallax", "pinhole", parallax=1e-6, rot=1e-6,
                    degenerate=True),
    projection_case("projection_sphere_tiny_parallax", "sphere", parallax=1e-6, rot=1e-6,
                    degenerate=True),
    projection_case("projection_pinhole_same_pose", "pinhole", same_pose=True, degenerate=True),
    projection_case("projection_sphere_same_pose", "sphere", same_pose=True, degenerate=True),
    projection_case("projection_pinhole_border", "pinhole", uv_i=BORDER, rot=0.02,
                    parallax=0.05, degenerate=True),
    projection_case("projection_sphere_far", "sphere", lam=1e-3, degenerate=True),
    projection_case("projection_pinhole_far", "pinhole", lam=1e-3, degenerate=True),
    td_case("td_pinhole_td0_zero_velocity", "pinhole", td=0.0, vel_scale=0.0, readout=0.0,
            degenerate=True),
    td_case("td_sphere_td0", "sphere", td=0.0, degenerate=True),
    td_case("td_sphere_zero_velocity", "sphere", vel_scale=0.0, degenerate=True),
    td_case("td_sphere_tiny_parallax", "sphere", parallax=1e-6, rot=1e-6, degenerate=True),
    td_case("td_pinhole_far_border", "pinhole", lam=1e-3, uv_i=BORDER, rot=0.02,
            degenerate=True),
    landmark_case("landmark_sphere_td_far", "sphere", use_td=True, lam=1e-3, degenerate=True),
    landmark_case("landmark_pinhole_same_pose_anchor_obs", "pinhole", same_pose=True,
                  with_anchor_obs=True, degenerate=True),
    landmark_case("landmark_pinhole_td_tiny_parallax", "pinhole", use_td=True, n=3,
                  parallax=1e-6, rot=1e-6, degenerate=True),
    landmark_case("landmark_pinhole_anchor_noise_same_pose", "pinhole", same_pose=True,
                  anchor_noise=True, degenerate=True),
    landmark_case("landmark_sphere_td_anchor_noise_far", "sphere", use_td=True, lam=1e-3,
                  anchor_noise=True, n=2, degenerate=True),
]
