"""The landmark bundle factor (``factors.landmark_schur``): its depth-eliminated information
and gradient against the full point-wise problem (inverse depths as variables, assembled
from ``factors.track_kernel``, whose Jacobians the shared suite checks numerically through
``factors.landmark`` / ``factors.stereo``), the gradient against central differences of
the depth-minimized energy, the depth refinement, and the square-root form."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_landmark_schur import E, D, X, full_problem, make_bundle
from factors.landmark_schur import bundle_factor, linearize, refine
from factors.robust import RobustKernel


def _bundle(seed, model="pinhole", robust=None, use_td=True, whiten=True, iters=2):
    return make_bundle(seed, model, robust, use_td, whiten, iters)


def _full(b, mats, Tc, td, robust):
    return full_problem(b, mats, Tc, td, robust)


@pytest.mark.parametrize("model", ["pinhole", "sphere"])
@pytest.mark.parametrize("robust", [None, RobustKernel("huber", 3.0)])
@pytest.mark.parametrize("use_td", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_schur_equals_full_problem(model, robust, use_td, seed):
    """With no refinement (iters 0), H and g are the Schur complement of the full
    problem's lambda block, and E its lambda-minimized quadratic value."""
    b, bodies, Tc, td, mats = _bundle(seed, model, robust, use_td, iters=0)
    lam0 = b.lam.copy()
    H, g, Er = linearize(b, mats, Tc.matrix(), td)
    assert np.array_equal(b.lam, lam0)
    Hf, gf, Ef = _full(b, mats, Tc, td, robust)
    Dm = b.dim
    Hll = np.diag(Hf)[Dm:]
    assert np.allclose(Hf[Dm:, Dm:], np.diag(Hll))       # landmarks do not couple
    Hs = Hf[:Dm, :Dm] - (Hf[:Dm, Dm:] / Hll) @ Hf[Dm:, :Dm]
    gs = gf[:Dm] - Hf[:Dm, Dm:] @ (gf[Dm:] / Hll)
    Es = Ef - 0.5 * gf[Dm:] @ (gf[Dm:] / Hll)
    scale = np.abs(Hs).max()
    assert np.abs(H - Hs).max() <= 1e-9 * scale
    assert np.abs(g - gs).max() <= 1e-9 * max(1.0, np.abs(gs).max())
    assert abs(Er - Es) <= 1e-9 * max(1.0, Es)


def _energy(b, bodies, Tc, td, iters=30):
    """Depth-minimized energy (no robust kernel) at the given state, lambda converged."""
    c = pack_copy(b)
    c.iters = iters
    mats = np.array([T.matrix() for T in bodies])
    return linearize(c, mats, Tc.matrix(), td)


def pack_copy(b):
    import copy
    c = copy.copy(b)
    c.lam = b.lam.copy()
    return c


@pytest.mark.parametrize("model", ["pinhole", "sphere"])
@pytest.mark.parametrize("seed", [3, 4])
def test_gradient_of_depth_minimized_energy(model, seed):
    """At converged depths g is the derivative of E*(x) = min_lambda E(x, lambda) on the
    retraction T Exp(xi) (central differences), for every body, T_b_c and td."""
    b, bodies, Tc, td, mats = _bundle(seed, model, None, True)
    b.iters = 30
    _, g, _ = linearize(b, mats, Tc.matrix(), td)
    h = 1e-6
    num = np.zeros(b.dim)
    for j in range(b.dim):
        vals = []
        for s in (h, -h):
            bb, TT, dd = list(bodies), Tc, td
            if j < 6:
                xi = np.zeros(6); xi[j] = s
                TT = Tc.retract(xi)
            elif j < 6 + 6 * b.n_bodies:
                k, e = divmod(j - 6, 6)
                xi = np.zeros(6); xi[e] = s
                bb[k] = bodies[k].retract(xi)
            else:
                dd = td + s
            vals.append(_energy(b, bb, TT, dd)[2])
        num[j] = (vals[0] - vals[1]) / (2 * h)
    assert np.abs(g - num).max() <= 1e-4 * max(1.0, np.abs(num).max())


def test_refinement_converges_and_bundle_factor_square_root():
    """Refining lambda drives the depth gradient to zero (E falls), and the factor's
    linearization is the square-root form J^T J = H (+ eps), J^T r = g, 0.5 |r|^2 = E."""
    b, bodies, Tc, td, mats = _bundle(5, iters=0)
    _, _, E0 = linearize(b, mats, Tc.matrix(), td, update=False)
    b.iters = 10
    linearize(b, mats, Tc.matrix(), td)
    b.iters = 0
    Hf, gf, _ = _full(b, mats, Tc, td, None)
    assert np.abs(gf[b.dim:]).max() <= 1e-8 * max(1.0, np.abs(gf[:b.dim]).max())
    H, g, E1 = linearize(b, mats, Tc.matrix(), td)
    assert E1 <= E0
    keys = [E(0)] + [X(i) for i in range(b.n_bodies)] + [D(0)]
    f = bundle_factor(keys, b)
    v = gtsam.Values()
    v.insert(E(0), Tc)
    for i, T in enumerate(bodies):
        v.insert(X(i), T)
    v.insert(D(0), np.array([td]))
    A, rhs = f.linearize(v).jacobian()
    assert np.abs(A.T @ A - H).max() <= 1e-6 * np.abs(H).max()
    assert np.abs(A.T @ (-rhs) - g).max() <= 1e-6 * max(1.0, np.abs(g).max())
    assert abs(f.error(v) - E1) <= 1e-6 * max(1.0, E1)


def test_refine_matches_the_elimination_and_reports_depth_information():
    """``refine`` (no elimination) reaches the depths the factor's own refinement reaches,
    its energy is the eliminated one there, and ``hll`` is the full problem's lambda
    information (with a depth prior added to one landmark)."""
    b, bodies, Tc, td, mats = _bundle(6, robust=RobustKernel("huber", 3.0), iters=0)
    b.p_lam[1], b.p_info[1] = b.lam[1] * 1.1, 50.0
    c = pack_copy(b)
    E_ref = refine(b, mats, Tc.matrix(), td, 20)
    c.iters = 20
    linearize(c, mats, Tc.matrix(), td)
    assert np.allclose(b.lam, c.lam, rtol=1e-7)
    b.iters = 0
    _, _, E_lin = linearize(b, mats, Tc.matrix(), td)
    assert abs(E_ref - E_lin) <= 1e-6 * E_lin
    Hf, _, _ = _full(b, mats, Tc, td, RobustKernel("huber", 3.0))
    hll = np.diag(Hf)[b.dim:].copy()
    hll[1] += 50.0
    assert np.allclose(b.hll, hll, rtol=1e-6)
