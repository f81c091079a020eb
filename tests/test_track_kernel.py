"""factors.track_kernel (one compiled pass per landmark factor) equals the numpy
reference path it replaced: projection, cam1 scatter through Ad(C^-1), robust weights,
anchor-noise whitening; and its closed-form 2x2 whitening equals the eigh one."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors import landmark, stereo
from factors.anchor_noise import anchor_whitening
from factors.robust import RobustKernel, reweight_blocks
from factors.track_kernel import whitening


def _pose(rng: np.random.Generator, scale: float = 0.2) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, scale, 3)), rng.normal(0, scale, 3))


def _reference(p, n: int, sigma: float, robust, W, J: np.ndarray | None = None):
    """The numpy path: reweight per 2-row block, then the whitening."""
    r, J = p.r.copy(), (p.J if J is None else J).copy(order="F")
    if robust is not None:
        reweight_blocks(r, J, sigma, robust)
    r = r.reshape(2 * n)
    return (W.apply(r), W.apply(J)) if W is not None else (r, J)


def _stereo_reference_J(p, st) -> np.ndarray:
    """Scatter of the batch Jacobian onto the stereo keys (the former stereo_residual)."""
    n, k = st.n, len(st.keys)
    J = np.zeros((2 * n, 13 + 6 * k + (p.J.shape[1] - 13 - 6 * n)), order="F")
    J[:, :13] = p.J[:, :13]
    if J.shape[1] > 13 + 6 * k:
        J[:, -1] = p.J[:, -1]
    i = np.arange(n)
    blocks = p.J[:, 13:13 + 6 * n].reshape(n, 2, n, 6)[i, :, i, :]
    blocks[st.right] = blocks[st.right] @ st.ad_inv
    c0 = np.where(st.target == 0, 7, 13 + 6 * (st.target - 1))
    J[(2 * i[:, None] + np.arange(2))[:, :, None], (c0[:, None] + np.arange(6))[:, None, :]] += blocks
    return J


@pytest.mark.parametrize("use_td", [False, True])
@pytest.mark.parametrize("model", ["pinhole", "sphere"])
@pytest.mark.parametrize("kernel", ["none", "huber", "cauchy"])
def test_kernel_matches_the_numpy_path(use_td, model, kernel):
    rng = np.random.default_rng(7)
    sigma = 2e-3
    robust = None if kernel == "none" else RobustKernel(kernel, 1.0)
    poses = [_pose(rng) for _ in range(4)]
    keys = [gtsam.symbol("x", i) for i in range(4)]
    lm = landmark.make_track(keys[0], rng.normal(0, 0.2, 2), keys[1:], rng.normal(0, 0.2, (3, 2)),
                             anchor_vel=rng.normal(0, 1, 2), vel=rng.normal(0, 1, (3, 2)),
                             anchor_offset=0.001, offset=rng.normal(0, 0.002, 3))
    args = [np.array([0.3]), _pose(rng, 0.05), *poses] + ([np.array([0.004])] if use_td else [])
    W = anchor_whitening(landmark.landmark_anchor_jacobian(args, lm, model, use_td))
    for w in (None, W):
        r, J = landmark._evaluate(args, lm, model, sigma, robust, use_td, None, w)
        r0, J0 = _reference(landmark._project(args, lm, model, use_td), 3, sigma, robust, w)
        assert np.allclose(r, r0, rtol=1e-12, atol=1e-14) and np.allclose(J, J0, rtol=1e-12, atol=1e-12)
    C = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.01, -0.02, 0.005])), np.array([0.11, 0.002, 0.0]))
    st = stereo.make_stereo_track(keys[0], rng.normal(0, 0.2, 2), [keys[1], keys[2], keys[0], keys[2]],
                                  rng.normal(0, 0.2, (4, 2)), stereo.stereo_rig(C),
                                  anchor_vel=rng.normal(0, 1, 2), vel=rng.normal(0, 1, (4, 2)),
                                  right=[False, False, True, True])
    args = [np.array([0.3]), _pose(rng, 0.05), *poses[:3]] + ([np.array([0.004])] if use_td else [])
    W = anchor_whitening(stereo.stereo_anchor_jacobian(args, st, model, use_td))
    for w in (None, W):
        r, J = stereo.stereo_residual(args, st, model, sigma, robust, use_td, w)
        p = stereo._project(args, st, model, use_td)
        r0, J0 = _reference(p, 4, sigma, robust, w, _stereo_reference_J(p, st))
        assert np.allclose(r, r0, rtol=1e-12, atol=1e-14) and np.allclose(J, J0, rtol=1e-12, atol=1e-12)


def test_cheirality_rows_are_constant_and_zero():
    """A target camera facing away: the constant residual, zero Jacobian rows (and no
    td column entry), as in factors.projection."""
    rng = np.random.default_rng(1)
    Ti, Tc = _pose(rng), _pose(rng, 0.05)
    flip = gtsam.Pose3(gtsam.Rot3.Ry(np.pi), np.zeros(3))
    Tj = Ti * Tc * flip * Tc.inverse()
    lm = landmark.make_track(0, np.zeros(2), [1, 2], rng.normal(0, 0.1, (2, 2)), vel=np.ones((2, 2)))
    args = [np.array([0.5]), Tc, Ti, Tj, _pose(rng), np.array([0.002])]
    r, J = landmark._evaluate(args, lm, "pinhole", 1e-3, RobustKernel("huber", 3.0), True, None)
    assert np.all(r[:2] == 2.0 * np.sqrt(RobustKernel("huber", 3.0).weight(np.array([2.0 * np.sqrt(2) / 1e-3]))[0]))
    assert not J[:2].any() and J[2:].any()


@pytest.mark.parametrize("use_td", [False, True])
@pytest.mark.parametrize("model", ["pinhole", "sphere"])
@pytest.mark.parametrize("kernel", ["none", "huber", "cauchy"])
def test_depth_kernel_equals_the_full_pass(use_td, model, kernel):
    """``track_eval_depth`` (r, the inverse-depth column and dr/duv of the anchor) gives
    ``track_eval``'s values to the bit, cam1 rows, td shifts, robust
    weights and a camera facing away (pinhole: the constant residual, zero rows) included."""
    from factors.bearing_model import tangent_basis
    from factors.robust import KERNELS
    from factors.track_kernel import evaluate, track_eval_depth
    rng = np.random.default_rng(11)
    Ti, Tc = _pose(rng), _pose(rng, 0.05)
    flip = gtsam.Pose3(gtsam.Rot3.Ry(np.pi), np.zeros(3))
    bodies = np.array([Ti.matrix(), _pose(rng).matrix(), _pose(rng).matrix(),
                       (Ti * Tc * flip * Tc.inverse()).matrix()])
    target = np.array([1, 2, 0, 2, 3], np.int64)
    right = np.array([False, False, True, True, False])
    C = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.01, -0.02, 0.005])), np.array([0.11, 0.002, 0.0]))
    rig = stereo.stereo_rig(C)
    uv, vel, off = rng.normal(0, 0.2, (5, 2)), rng.normal(0, 1, (5, 2)), rng.normal(0, 0.002, 5)
    a_uv, a_vel, basis = rng.normal(0, 0.2, 2), rng.normal(0, 1, 2), tangent_basis(uv)
    robust = None if kernel == "none" else RobustKernel(kernel, 1.0)
    lam, td, sigma = 0.3, (0.004 if use_td else None), 2e-3
    r, J, G = evaluate(bodies, target, right, rig.C, rig.ad_inv, Tc.matrix(), lam, td, a_uv, a_vel,
                       0.001, uv, vel, off, basis, model, sigma, robust, None)
    if model == "pinhole":   # the far side (a sphere sees it)
        assert np.all(r[-2:] == r[-2]) and not J[-2:].any() and J[:-2, 0].any()
    kind, kk = (0, 1.0) if robust is None else (KERNELS.index(kernel), 1.0)
    r2, jl, G2 = np.empty_like(r), np.empty((1, len(r))).T, np.full_like(G, np.nan)
    track_eval_depth(bodies, target, right, rig.C, Tc.matrix(), lam, td or 0.0, use_td, a_uv, a_vel,
                     0.001, uv, vel, off, basis, model == "sphere", sigma, kind, kk, r2, jl, G2)
    assert np.array_equal(r2, r) and np.array_equal(jl[:, 0], J[:, 0]) and np.array_equal(G2, G)


@pytest.mark.parametrize("m", [2, 6, 20])
def test_closed_form_whitening_equals_eigh(m):
    rng = np.random.default_rng(m)
    for i, G in enumerate((rng.normal(0, 1, (m, 2)), np.outer(rng.normal(0, 1, m), [1.0, 2.0]),
                           np.zeros((m, 2)), rng.normal(0, 1, (m, 2)) * [1e3, 1e-3])):
        a, b = anchor_whitening(G), whitening(G)
        assert a.U.shape == b.U.shape
        assert np.allclose(a.matrix(), b.matrix(), rtol=1e-12, atol=1e-12)
        if i == 0:   # W (I + G G^T) W = I
            W = b.matrix()
            assert np.allclose(W @ (np.eye(m) + G @ G.T) @ W, np.eye(m), atol=1e-12)


def test_cache_is_warm_after_compiling():
    """``vio run`` tells the user a first run compiles: the check sees a compiled kernel
    in Numba's disk cache and never reports a plain function as compiled."""
    from factors.jit import cache_is_warm
    from factors.track_kernel import track_eval
    from vio.backend.kernels import compile_kernels
    compile_kernels()
    assert cache_is_warm(track_eval)
    assert not cache_is_warm(lambda: 0)


def test_kernel_start_up_skips_numba_blas_probe_and_blas_still_works():
    """``factors.jit`` imports Numba's array-math module without ``scipy.linalg`` (its BLAS
    probe costs 0.15-0.25 s a process); a compiled kernel calling BLAS still gets it."""
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys\n"
        "import numpy as np\n"
        "import factors.jit\n"
        "import numba.np.arraymath\n"
        "assert 'scipy.linalg' not in sys.modules, 'the BLAS probe imported scipy.linalg'\n"
        "from numba import njit\n"
        "mm = njit(lambda a, b: a @ b)\n"
        "inv = njit(lambda a: np.linalg.inv(a))\n"
        "a = np.array([[2.0, 1.0], [0.5, 3.0]])\n"
        "assert np.allclose(mm(a, a), a @ a) and np.allclose(inv(a), np.linalg.inv(a))\n"
        "print('ok')\n")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
