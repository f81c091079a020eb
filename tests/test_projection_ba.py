"""Projection factors: zero error at the truth, cheirality, td consistency, track
building, and a small bundle adjustment (poses, inverse depths, extrinsic) that
converges to the truth with ``gtsam.LevenbergMarquardtOptimizer``."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_projection import C, L, SIGMA, T, X, scene
from factors.landmark import landmark_factor, landmark_residual, make_track
from factors.bearing_model import BEHIND_CAMERA_RESIDUAL
from factors.projection import projection_factor, projection_residual
from factors.robust import RobustKernel
from factors.td_projection import TdObservation, td_projection_factor, td_projection_residual

MODELS = ["pinhole", "sphere"]
NOISE2 = gtsam.noiseModel.Isotropic.Sigma(2, SIGMA)


def _values(pairs) -> gtsam.Values:
    v = gtsam.Values()
    for k, x in pairs:
        v.insert(k, x)
    return v


@pytest.mark.parametrize("model", MODELS)
def test_error_is_zero_at_truth(model: str) -> None:
    rng = np.random.default_rng(2)
    Ti, poses, Tc, lam, uvi, uvs = scene(rng, 4, noise=0.0)
    keys = [X(k + 1) for k in range(4)]
    base = [(X(0), Ti), (C(0), Tc), (L(0), np.array([lam]))] + list(zip(keys, poses))
    # td factors: observations taken at stamp + td move by td * vel; undo it exactly
    td, vel_i, vels = 0.007, rng.normal(size=2), rng.normal(size=(4, 2))
    oi = TdObservation(uvi + td * vel_i, vel_i)
    values = _values(base + [(T(0), np.array([td]))])
    factors = [projection_factor(NOISE2, [X(0), keys[0], C(0), L(0)], uvi, uvs[0], model),
               td_projection_factor(NOISE2, [X(0), keys[1], C(0), L(0), T(0)], oi,
                                    TdObservation(uvs[1] + td * vels[1], vels[1]), model),
               landmark_factor(make_track(X(0), uvi, keys, uvs), L(0), C(0), SIGMA, model,
                               RobustKernel("cauchy")),
               landmark_factor(make_track(X(0), uvi + td * vel_i, keys, uvs + td * vels, vel_i,
                                          vels), L(0), C(0), SIGMA, model, None, T(0))]
    for f in factors:
        assert f.error(values) < 1e-20


@pytest.mark.parametrize("lam", [0.5, 1e-9, 0.0])
def test_cheirality_and_points_at_infinity(lam: float) -> None:
    Ti, Tc = gtsam.Pose3(), gtsam.Pose3()
    uvi = np.array([0.1, -0.2])
    behind = gtsam.Pose3(gtsam.Rot3.Ry(np.pi), np.array([0.0, 0.0, 1.0]))  # looks along -z
    r, J = projection_residual(Ti, behind, Tc, lam, uvi, np.array([0.1, 0.1]), "pinhole")
    assert np.all(r == BEHIND_CAMERA_RESIDUAL)
    assert all(np.all(b == 0.0) for b in J)
    r, J = projection_residual(Ti, behind, Tc, lam, uvi, np.array([0.1, 0.1]), "sphere")
    assert np.all(np.isfinite(r)) and np.linalg.norm(r) <= 2.0 + 1e-12
    assert all(np.all(np.isfinite(b)) for b in J) and np.abs(J[0]).max() > 0
    ahead = gtsam.Pose3(gtsam.Rot3(), np.array([0.2, 0.0, 0.1]))
    for model in MODELS:  # far / infinite points project finitely (homogeneous transfer)
        r, J = projection_residual(Ti, ahead, Tc, lam, uvi, uvi, model)
        assert np.all(np.isfinite(r)) and all(np.all(np.isfinite(b)) for b in J)
        if lam == 0.0:
            assert np.abs(r).max() < 1e-15  # pure rotation-free translation: no parallax


def test_landmark_factor_keeps_valid_rows_when_one_point_is_behind() -> None:
    Ti = gtsam.Pose3()
    front = gtsam.Pose3(gtsam.Rot3(), np.array([0.3, 0.0, 0.0]))
    behind = gtsam.Pose3(gtsam.Rot3.Ry(np.pi), np.array([0.0, 0.0, 1.0]))
    track = make_track(X(0), [0.0, 0.0], [X(1), X(2)], np.zeros((2, 2)))
    r, J = landmark_residual([np.array([0.25]), gtsam.Pose3(), Ti, front, behind], track)
    assert np.all(r[2:] == BEHIND_CAMERA_RESIDUAL) and np.all(r[:2] != BEHIND_CAMERA_RESIDUAL)
    assert np.abs(J[0][:2]).max() > 0 and np.all(J[0][2:] == 0.0)


@pytest.mark.parametrize("model", MODELS)
def test_td_factor_reduces_to_projection_factor(model: str) -> None:
    rng = np.random.default_rng(4)
    Ti, (Tj,), Tc, lam, uvi, uvs = scene(rng, 1)
    r0, J0 = projection_residual(Ti, Tj, Tc, lam, uvi, uvs[0], model)
    r1, J1 = td_projection_residual(Ti, Tj, Tc, lam, 0.01, TdObservation(uvi, np.zeros(2)),
                                    TdObservation(uvs[0], np.zeros(2)), model)
    np.testing.assert_allclose(r1, r0, rtol=1e-14, atol=1e-15)
    for a, b in zip(J0, J1[:4]):
        np.testing.assert_allclose(b, a, rtol=1e-14, atol=1e-15)
    assert np.all(J1[4] == 0.0)
    # td - td_obs + row time cancels: a non-zero td with matching td_obs is the raw residual
    oi = TdObservation.create(uvi, rng.normal(size=2), td_obs=0.01)
    oj = TdObservation.create(uvs[0], rng.normal(size=2), td_obs=0.01)
    r2, _ = td_projection_residual(Ti, Tj, Tc, lam, 0.01, oi, oj, model)
    np.testing.assert_allclose(r2, r0, rtol=1e-12, atol=1e-15)


def test_make_track_drops_anchor_frame_and_validates() -> None:
    uv = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    tr = make_track(X(1), [0.1, 0.2], [X(1), X(2), X(3)], uv, vel=np.ones((3, 2)))
    assert tr.keys == (X(2), X(3)) and tr.n == 2
    np.testing.assert_array_equal(tr.uv, uv[1:])
    with pytest.raises(ValueError, match="repeats"):
        make_track(X(0), [0, 0], [X(1), X(1)], uv[:2])
    with pytest.raises(ValueError, match="no observation"):
        make_track(X(0), [0, 0], [X(0)], uv[:1])
    with pytest.raises(ValueError, match="distinct"):
        projection_factor(NOISE2, [X(0), X(0), C(0), L(0)], [0, 0], [0, 0])


def test_stacked_jacobian_path_of_adapter_contains_failures() -> None:
    """The landmark factor hands the adapter one stacked Jacobian: bad output is contained."""
    from factors.adapter import FactorHealth, custom_factor
    health = FactorHealth()
    track = make_track(X(0), [0.0, 0.0], [X(1)], np.zeros((1, 2)))
    f = landmark_factor(track, L(0), C(0), SIGMA, health=health)
    v = _values([(L(0), np.array([np.nan])), (C(0), gtsam.Pose3()), (X(0), gtsam.Pose3()),
                 (X(1), gtsam.Pose3(gtsam.Rot3(), np.array([0.3, 0.0, 0.0])))])
    A, b = f.linearize(v).jacobian()
    assert np.all(A == 0) and np.all(b == 0) and health.failures == 1
    bad = custom_factor(NOISE2, [X(0)], ["pose3"], lambda a: (np.zeros(2), np.zeros((2, 7))), health)
    A, _ = bad.linearize(_values([(X(0), gtsam.Pose3())])).jacobian()
    assert np.all(A == 0) and health.failures == 2 and "stacked" in health.last_error


# ------------------------------------------------------------------ bundle adjustment

N_POSES, N_LANDMARKS, FIXED = 6, 30, (0, 1, 2)


def _ba_world(rng: np.random.Generator):
    Tc = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.05, -np.pi / 2), np.array([-0.02, -0.06, 0.01]))
    poses = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.12),
                         np.array([0.25 * k, 0.1 * np.sin(k), 0.05 * k]) + rng.normal(size=3) * 0.03)
             for k in range(N_POSES)]
    lms = []
    while len(lms) < N_LANDMARKS:
        a = len(lms) % N_POSES
        uvi, lam = rng.uniform(-0.4, 0.4, 2), rng.uniform(1 / 6, 1 / 2)
        p_w = poses[a].compose(Tc).transformFrom(np.append(uvi, 1) / lam)
        obs = []
        for k in range(N_POSES):
            p = poses[k].compose(Tc).transformTo(p_w)
            if p[2] < 0.3 or np.abs(p[:2] / p[2]).max() > 0.9:
                break
            obs.append(p[:2] / p[2])
        else:
            lms.append((a, uvi, lam, np.array(obs)))
    return Tc, poses, lms


def _perturb(T: gtsam.Pose3, rng, rot: float, trans: float) -> gtsam.Pose3:
    return T.compose(gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * rot), rng.normal(size=3) * trans))


@pytest.mark.parametrize("variant", ["per_obs_pinhole", "landmark_sphere", "landmark_pinhole_huber"])
def test_bundle_adjustment_converges_to_truth(variant: str) -> None:
    rng = np.random.default_rng(21)
    Tc, poses, lms = _ba_world(rng)
    graph, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    tight = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for k, P in enumerate(poses):
        if k in FIXED:  # gauge (7 dof) + hand-eye ambiguity: 3 known body poses
            graph.add(gtsam.PriorFactorPose3(X(k), P, tight))
        init.insert(X(k), P if k in FIXED else _perturb(P, rng, 0.03, 0.05))
    init.insert(C(0), _perturb(Tc, rng, 0.03, 0.02))
    for l, (a, uvi, lam, obs) in enumerate(lms):
        init.insert(L(l), np.array([lam * rng.uniform(0.8, 1.2)]))
        others = [k for k in range(N_POSES) if k != a]
        if variant == "per_obs_pinhole":
            for k in others:
                graph.add(projection_factor(NOISE2, [X(a), X(k), C(0), L(l)], uvi, obs[k]))
        else:
            model, kernel = ("sphere", None) if variant == "landmark_sphere" else \
                ("pinhole", RobustKernel("huber"))
            track = make_track(X(a), uvi, [X(k) for k in range(N_POSES)], obs)
            graph.add(landmark_factor(track, L(l), C(0), SIGMA, model, kernel))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-20)
    params.setMaxIterations(100)
    res = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    for k, P in enumerate(poses):
        d = gtsam.Pose3.Logmap(P.between(res.atPose3(X(k))))
        assert np.abs(d).max() < 1e-6, (k, d)
    d = gtsam.Pose3.Logmap(Tc.between(res.atPose3(C(0))))
    assert np.abs(d).max() < 1e-6, d
    for l, (_, _, lam, _) in enumerate(lms):
        assert res.atVector(L(l))[0] == pytest.approx(lam, rel=1e-6)
