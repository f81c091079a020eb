"""The anchor-noise whitening of the inverse-depth landmark factors is the right noise model.

With isotropic pixel noise on every observation of a landmark, the anchor one included,
the stacked residual at the true state has covariance ``sigma^2 (I + G G^T)``; after
``factors.anchor_noise.anchor_whitening`` it is ``sigma^2 I`` (Monte Carlo here), so each
observation weighs what it measures instead of the anchor's error being counted once per
target."""

from __future__ import annotations

import numpy as np

from cases_projection import scene
from factors.landmark import landmark_anchor_jacobian, landmark_residual, make_track
from factors.anchor_noise import anchor_whitening


def test_whitened_residuals_have_unit_covariance():
    rng = np.random.default_rng(4)
    Ti, poses, Tc, lam, uvi, uvs = scene(rng, 4, noise=0.0)
    n, sigma, draws = len(poses), 2e-3, 4000
    keys = list(range(1, n + 1))
    args = [np.array([lam]), Tc, Ti] + poses
    W = anchor_whitening(landmark_anchor_jacobian(args, make_track(0, uvi, keys, uvs)))
    raw = np.empty((draws, 2 * n))
    for d in range(draws):
        track = make_track(0, uvi + rng.normal(0, sigma, 2), keys, uvs + rng.normal(0, sigma, (n, 2)))
        raw[d] = landmark_residual(args, track)[0]
    cov_raw = np.cov(raw.T) / sigma**2
    cov_w = np.cov(W.apply(raw.T)) / sigma**2
    assert np.allclose(W.apply(raw.T), W.matrix() @ raw.T)
    assert np.abs(cov_w - np.eye(2 * n)).max() < 0.12, np.round(cov_w, 2)
    assert np.abs(cov_raw - np.eye(2 * n)).max() > 0.5        # the anchor's error is shared


def test_whitening_of_no_anchor_sensitivity_is_identity():
    assert np.allclose(anchor_whitening(np.zeros((6, 2))).matrix(), np.eye(6))
    G = np.array([[1.0, 0.0], [0.0, 1.0]])
    W = anchor_whitening(G)                          # one target: (I + I)^(-1/2)
    assert np.allclose(W.matrix(), np.eye(2) / np.sqrt(2.0))
