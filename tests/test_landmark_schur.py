"""The landmark bundle factor (``factors.landmark_schur``): its depth-eliminated information
and gradient against the full point-wise problem (inverse depths as variables, assembled
from ``factors.track_kernel``, whose Jacobians the shared suite checks numerically through
``factors.landmark`` / ``factors.stereo``), the gradient against central differences of
the depth-minimized energy, the depth refinement, and the square-root form."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_projection import random_pose
from factors import track_kernel
from factors.anchor_noise import AnchorWhitening
from factors.landmark_schur import bundle_factor, linearize, pack, refine, set_whitening
from factors.projection import tangent_basis
from factors.robust import RobustKernel

SIGMA = 0.004
E, X, D = gtsam.symbol_shorthand.E, gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.D


def _scene(seed: int, n_lm: int = 6, n_bodies: int = 4, use_td: bool = True, noise: float = 0.003):
    """Bodies, extrinsic, rig and per-landmark dicts for ``pack`` (anchors vary; cam1
    observations at the anchor and elsewhere)."""
    rng = np.random.default_rng(seed)
    Tc = random_pose(rng, 0.2, 0.05)
    T0 = random_pose(rng, 0.3, 1.0)
    bodies = [T0] + [T0.compose(random_pose(rng, 0.05, 0.3)) for _ in range(n_bodies - 1)]
    C = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.01), np.array([0.11, 0.0, 0.0]))
    T_b_c1 = C.compose(Tc)       # C = T_b_c1 T_b_c0^-1
    lms = []
    while len(lms) < n_lm:
        a = int(rng.integers(0, n_bodies))
        others = [b for b in range(n_bodies) if b != a]
        chosen = sorted(rng.choice(others, size=int(rng.integers(1, len(others) + 1)), replace=False).tolist())
        Ta = bodies[a].compose(Tc)
        uva = rng.uniform(-0.4, 0.4, 2)
        lam = rng.uniform(0.2, 1.0)
        p_w = Ta.transformFrom(np.append(uva, 1.0) / lam)
        lb = [a] + chosen
        target, right, uv = [], [], []
        ok = True
        for t, b in enumerate(lb):
            for cam, Tbc in ((0, Tc), (1, T_b_c1)):
                if t == 0 and cam == 0:
                    continue
                if cam == 1 and rng.uniform() < 0.4:
                    continue
                p = bodies[b].compose(Tbc).transformTo(p_w)
                if p[2] < 0.3:
                    ok = False
                target.append(t), right.append(cam == 1), uv.append(p[:2] / p[2] + rng.normal(size=2) * noise)
        if not ok or not uv:
            continue
        uv = np.array(uv)
        n = len(uv)
        lms.append(dict(bodies=lb, target=np.array(target), right=np.array(right), uv=uv,
                        vel=rng.normal(size=(n, 2)) * 0.5, off=rng.normal(size=n) * 1e-3,
                        basis=tangent_basis(uv), a_uv=uva + rng.normal(size=2) * noise,
                        a_vel=rng.normal(size=2) * 0.5, a_off=0.0, lam=lam * rng.uniform(0.8, 1.25)))
    rig = (C.matrix(), C.inverse().AdjointMap())
    td = 0.002 if use_td else 0.0
    return bodies, Tc, rig, lms, td


def _bundle(seed, model="pinhole", robust=None, use_td=True, whiten=True, iters=2):
    bodies, Tc, rig, lms, td = _scene(seed, use_td=use_td)
    b = pack(len(bodies), lms, rig[0], rig[1], model, SIGMA, robust, use_td, (1e-3, 10.0), iters)
    mats = np.array([T.matrix() for T in bodies])
    if whiten:
        set_whitening(b, mats, Tc.matrix(), td)
    return b, bodies, Tc, td, mats


def _full(b, mats, Tc, td, robust):
    """(H_full, g_full, E_full) over [reduced columns, lambda_1..N] at ``b.lam``."""
    Dm, N = b.dim, len(b.lam)
    Hf, gf, Ef = np.zeros((Dm + N, Dm + N)), np.zeros(Dm + N), 0.0
    for i in range(N):
        s0, s1 = b.start[i], b.start[i + 1]
        lb = b.lbodies[b.lb_start[i]:b.lb_start[i + 1]]
        W = AnchorWhitening(b.U[2 * s0:2 * s1], b.d[i])
        r, J, _ = track_kernel.evaluate(mats[lb], b.target[s0:s1], b.right[s0:s1], b.C, b.ad_inv,
                                        Tc.matrix(), b.lam[i], td if b.use_td else None, b.a_uv[i],
                                        b.a_vel[i], b.a_off[i], b.uv[s0:s1], b.vel[s0:s1], b.off[s0:s1],
                                        b.basis[s0:s1], "sphere" if b.sphere else "pinhole", SIGMA,
                                        robust, W)
        r, J = r / SIGMA, J / SIGMA
        cols = [Dm + i] + list(range(6)) + [6 + 6 * t + e for t in lb for e in range(6)] + ([Dm - 1] if b.use_td else [])
        Jg = np.zeros((len(r), Dm + N))
        Jg[:, cols] = J
        Hf += Jg.T @ Jg
        gf += Jg.T @ r
        Ef += 0.5 * r @ r
    return Hf, gf, Ef


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
