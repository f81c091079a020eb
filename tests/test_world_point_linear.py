"""``factors.world_point.world_point_linear`` (the farewell observations of world points,
linearized in one pass) against the callback factor's own linearization: the same
quadratic at the linearization point, with and without td, a robust kernel and a point
behind a camera, and (without a kernel, whose weights the callback recomputes) the
first-order shift of ``LinearContainerFactor`` at nearby values."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_projection import scene
from factors.world_point import world_point_factor, world_point_linear

X, P, T = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.P, gtsam.symbol_shorthand.T
SIGMA = 0.01


def _setup(seed: int, n: int, use_td: bool, behind: bool):
    rng = np.random.default_rng(seed)
    Ti, poses, Tc, lam, uvi, uvs = scene(rng, max(n - 1, 1))
    bodies = [Ti, *poses][:n]
    uv = np.vstack([uvi[None, :], np.asarray(uvs).reshape(-1, 2)])[:n]
    p_w = Ti.compose(Tc).transformFrom(np.append(uvi, 1.0) / lam) + rng.normal(size=3) * 0.01
    if behind:
        p_w = Ti.compose(Tc).transformFrom(np.array([0.1, 0.0, -1.0]))
    vel, off = rng.normal(size=(n, 2)), rng.uniform(-0.01, 0.01, size=n)
    values = gtsam.Values()
    values.insert(P(0), np.asarray(p_w, float))
    for i, B in enumerate(bodies):
        values.insert(X(i), B)
    if use_td:
        values.insert(T(0), np.array([0.012]))
    return rng, Tc, uv, vel, off, values


def _quadratic(factors, values: gtsam.Values, keys: list[int]) -> np.ndarray:
    g = gtsam.GaussianFactorGraph()
    for f in factors:
        g.push_back(f.linearize(values))
    return g.augmentedHessian(gtsam.Ordering(keys))


@pytest.mark.parametrize("seed,n,use_td,kernel,behind", [
    (0, 3, True, (0, 0.0), False), (1, 5, True, (1, 1.5), False), (2, 4, False, (2, 1.0), False),
    (3, 1, True, (0, 0.0), False), (4, 3, True, (1, 1.5), True)])
def test_linear_farewell_is_the_callback_factors_linearization(seed, n, use_td, kernel, behind):
    rng, Tc, uv, vel, off, values = _setup(seed, n, use_td, behind)
    td_key = T(0) if use_td else None
    body_keys = [X(i) for i in range(n)]
    keys = [P(0), *body_keys] + ([T(0)] if use_td else [])
    uv_noisy = uv + rng.normal(size=uv.shape) * 0.02     # residuals the kernel reweights
    ref = world_point_factor(P(0), body_keys, td_key, Tc, uv_noisy, vel, off, SIGMA, kernel)
    lin = world_point_linear(P(0), body_keys, td_key, Tc, values, uv_noisy, vel, off, SIGMA, kernel)
    assert len(lin) == n
    assert all(set(f.keys()) == ({P(0), X(o)} | ({T(0)} if use_td else set())) for o, f in enumerate(lin))
    H_ref, H = _quadratic([ref], values, keys), _quadratic(lin, values, keys)
    np.testing.assert_allclose(H, H_ref, rtol=1e-9, atol=1e-9 * np.abs(H_ref).max())
    if kernel[0]:     # the callback re-weighs at other values: compare at ``values`` only
        return
    # at nearby values the containers shift their linear factor to first order (b - A delta)
    delta = gtsam.VectorValues()
    delta.insert(P(0), rng.normal(size=3) * 1e-3)
    for k in body_keys:
        delta.insert(k, rng.normal(size=6) * 1e-4)
    if use_td:
        delta.insert(T(0), np.array([1e-4]))
    moved = values.retract(delta)
    e_lin, e_exact, e_before = sum(f.error(moved) for f in lin), ref.error(moved), ref.error(values)
    assert abs(e_lin - e_exact) <= 1e-2 * abs(e_exact - e_before) + 1e-9
