"""Robust kernels and MAD scale (``factors/robust.py``, seed 003), and per-observation
robust weighting inside the per-landmark factor (``factors/landmark.py``)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_projection import C, L, SIGMA, X, scene
from factors.landmark import landmark_factor, make_track
from factors.projection import projection_factor
from factors.robust import (CAUCHY_C, HUBER_K, RobustKernel, block_sqrt_weights, mad_sigma,
                            reweight_blocks, robust_noise)

S_GRID = np.concatenate([[0.0, 1e-9, HUBER_K, CAUCHY_C], np.linspace(-12, 12, 97),
                         np.geomspace(1e-3, 1e4, 30)])


@pytest.mark.parametrize("kind", ["huber", "cauchy", "none"])
def test_weights_and_losses_match_gtsam(kind: str) -> None:
    kernel = RobustKernel(kind)
    est = kernel.estimator()
    w_ref = np.array([est.weight(float(s)) for s in S_GRID])
    loss_ref = np.array([est.loss(float(s)) for s in S_GRID])
    np.testing.assert_allclose(kernel.weight(S_GRID), w_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(kernel.loss(S_GRID), loss_ref, rtol=1e-12, atol=1e-15)


def test_kernel_parameters_and_validation() -> None:
    assert RobustKernel("huber").k == 1.345 and RobustKernel("cauchy").k == 2.3849
    assert RobustKernel("huber", 2.0).k == 2.0
    with pytest.raises(ValueError, match="unknown robust kernel"):
        RobustKernel("tukey")
    with pytest.raises(ValueError, match="> 0"):
        RobustKernel("cauchy", -1.0)


def test_robust_noise_wraps_gaussian() -> None:
    base = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
    assert robust_noise(base, RobustKernel("none")) is base
    rn = robust_noise(base, RobustKernel("cauchy"))
    assert isinstance(rn, gtsam.noiseModel.Robust)
    r = np.array([3.0, -4.0])  # whitened norm 10
    assert rn.robust().weight(10.0) == pytest.approx(1.0 / (1.0 + (10.0 / CAUCHY_C) ** 2))
    assert rn.loss(np.linalg.norm(base.whiten(r)) ** 2) == pytest.approx(
        RobustKernel("cauchy").loss(10.0), rel=1e-9)


@pytest.mark.parametrize("sigma", [0.01, 1.0, 37.0])
def test_mad_recovers_gaussian_sigma(sigma: float) -> None:
    rng = np.random.default_rng(7)
    r = rng.normal(0.0, sigma, size=20000)
    assert mad_sigma(r) == pytest.approx(sigma, rel=0.03)
    r_out = r.copy()  # 10% gross outliers barely move it (std would be ~30x off)
    r_out[:2000] = rng.uniform(-1000 * sigma, 1000 * sigma, 2000)
    assert mad_sigma(r_out) == pytest.approx(sigma, rel=0.15)
    assert mad_sigma(r + 5 * sigma, center=True) == pytest.approx(sigma, rel=0.03)


def test_mad_rejects_empty() -> None:
    with pytest.raises(ValueError, match="at least one"):
        mad_sigma(np.array([np.nan]))


def test_block_weights_are_gtsam_weights_of_block_norms() -> None:
    rng = np.random.default_rng(3)
    r = rng.normal(size=(50, 2)) * rng.uniform(0.001, 0.2, size=(50, 1))
    for kind in ("huber", "cauchy"):
        est = RobustKernel(kind).estimator()
        ref = [np.sqrt(est.weight(float(np.linalg.norm(b) / 0.01))) for b in r]
        np.testing.assert_allclose(block_sqrt_weights(r, 0.01, RobustKernel(kind)), ref, rtol=1e-12)
    np.testing.assert_array_equal(block_sqrt_weights(r, 0.01, None), np.ones(50))


@pytest.mark.parametrize("model", ["pinhole", "sphere"])
@pytest.mark.parametrize("kind", ["huber", "cauchy"])
def test_landmark_factor_equals_stacked_gtsam_robust_factors(model: str, kind: str) -> None:
    """Per-block IRLS inside the landmark factor == one gtsam Robust factor per observation."""
    rng = np.random.default_rng(11)
    n = 6
    Ti, poses, Tc, lam, uvi, uvs = scene(rng, n, noise=0.02)
    uvs[2] += [0.1, 0.05]
    keys = [X(k + 1) for k in range(n)]
    kernel = RobustKernel(kind)
    lm = landmark_factor(make_track(X(0), uvi, keys, uvs), L(0), C(0), SIGMA, model, kernel)
    values = gtsam.Values()
    for k, v in [(L(0), np.array([lam])), (C(0), Tc), (X(0), Ti)] + list(zip(keys, poses)):
        values.insert(k, v)
    A, b = lm.linearize(values).jacobian()
    cols = {L(0): slice(0, 1), C(0): slice(1, 7), X(0): slice(7, 13)}
    noise = robust_noise(gtsam.noiseModel.Isotropic.Sigma(2, SIGMA), kernel)
    weights = []
    for k in range(n):
        f = projection_factor(noise, [X(0), keys[k], C(0), L(0)], uvi, uvs[k], model)
        Ak, bk = f.linearize(values).jacobian()
        rows = slice(2 * k, 2 * k + 2)
        np.testing.assert_allclose(b[rows], bk, rtol=1e-10, atol=1e-12)
        ref_blocks = {X(0): Ak[:, 0:6], keys[k]: Ak[:, 6:12], C(0): Ak[:, 12:18], L(0): Ak[:, 18:19]}
        for key, block in ref_blocks.items():
            c = cols.get(key, slice(13 + 6 * k, 19 + 6 * k))
            np.testing.assert_allclose(A[rows, c], block, rtol=1e-10, atol=1e-10)
        e = np.linalg.norm(np.asarray(f.unwhitenedError(values))) / SIGMA
        weights.append(kernel.weight(e))
    assert min(weights) < 0.5  # the planted outlier was actually down-weighted
    # other observations' rows are zero in this observation's pose columns
    assert np.all(A[2:, 13:19] == 0.0)


def _pose_error_with_outliers(kind: str, drop_outliers: bool = False) -> float:
    """One free pose, 40 landmarks with known depths, every 4th observation a gross outlier."""
    sigma = 0.003  # ~1.4 px
    Ti = gtsam.Pose3()
    Tc = gtsam.Pose3(gtsam.Rot3.Ypr(0.1, -0.05, 0.02), np.array([0.05, 0.0, 0.01]))
    Tj = gtsam.Pose3(gtsam.Rot3.Expmap([0.02, -0.05, 0.03]), np.array([0.3, -0.1, 0.05]))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    tight = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for k, T in [(X(0), Ti), (C(0), Tc)]:
        graph.add(gtsam.PriorFactorPose3(k, T, tight))
        values.insert(k, T)
    values.insert(X(1), Tj.compose(gtsam.Pose3(gtsam.Rot3.Expmap([0.02, 0, -0.01]),
                                                np.array([0.05, 0.02, -0.03]))))
    rng = np.random.default_rng(9)
    for l in range(40):
        uvi, lam = rng.uniform(-0.4, 0.4, 2), rng.uniform(0.2, 0.6)
        p = Tj.compose(Tc).transformTo(Ti.compose(Tc).transformFrom(np.append(uvi, 1) / lam))
        uvj = p[:2] / p[2] + rng.normal(size=2) * sigma
        outlier = l % 4 == 0
        if outlier:
            uvj += rng.uniform(-0.2, 0.2, 2)
            if drop_outliers:
                continue
        graph.add(landmark_factor(make_track(X(0), uvi, [X(1)], uvj[None]), L(l), C(0),
                                  sigma, "sphere", RobustKernel(kind)))
        graph.add(gtsam.PriorFactorVector(L(l), np.array([lam]),
                                          gtsam.noiseModel.Isotropic.Sigma(1, 1e-6)))
        values.insert(L(l), np.array([lam]))
    res = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return float(np.linalg.norm(gtsam.Pose3.Logmap(Tj.between(res.atPose3(X(1))))))


def test_robust_landmark_factor_rejects_outliers() -> None:
    """With 25% gross outliers Huber/Cauchy land near the inlier-only (oracle) estimate."""
    oracle = _pose_error_with_outliers("none", drop_outliers=True)
    err = {k: _pose_error_with_outliers(k) for k in ("none", "huber", "cauchy")}
    assert err["none"] > 4 * oracle, (oracle, err)
    assert err["huber"] < 1.6 * oracle, (oracle, err)
    assert err["cauchy"] < 1.3 * oracle, (oracle, err)


@pytest.mark.parametrize("kind", ["huber", "cauchy", "none"])
def test_fused_reweighting_matches_block_weights(kind: str) -> None:
    rng = np.random.default_rng(8)
    r = rng.normal(size=(7, 2)) * rng.uniform(0.001, 0.1, size=(7, 1))
    J = np.asfortranarray(rng.normal(size=(14, 9)))
    sw = block_sqrt_weights(r, 0.01, RobustKernel(kind))
    r2, J2 = r.copy(), J.copy(order="F")
    reweight_blocks(r2, J2, 0.01, RobustKernel(kind))
    np.testing.assert_allclose(r2, r * sw[:, None], rtol=1e-14)
    np.testing.assert_allclose(J2, J * np.repeat(sw, 2)[:, None], rtol=1e-14)
