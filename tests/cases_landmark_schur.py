"""Cases of the landmark bundle factor (``factors.landmark_schur``): N landmarks over B
bodies with their inverse depths eliminated inside, collected by ``tests/test_jacobians.py``
as ``REDUCED_CASES`` (its reduced information and gradient against the full point-wise
problem assembled from ``factors.track_kernel``, and the gradient against central
differences of the depth-minimized energy). Scenes: varying anchors, cam0 and cam1
observations (cam1 also at the anchor), td shifts, anchor-noise whitening."""

from __future__ import annotations

import copy

import gtsam
import numpy as np

from cases_projection import random_pose
from factors import track_kernel
from factors.anchor_noise import AnchorWhitening
from factors.landmark_schur import bundle_factor, pack, refine, set_whitening
from factors.bearing_model import tangent_basis
from jacobian_case import ReducedCase

SIGMA = 0.004
E, X, D = gtsam.symbol_shorthand.E, gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.D


def scene(seed, n_lm: int = 6, n_bodies: int = 4, use_td: bool = True, noise: float = 0.003):
    """Bodies, extrinsic, rig and per-landmark dicts for ``pack`` (anchors vary; cam1
    observations at the anchor and elsewhere). ``seed``: an int or a Generator."""
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
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


def make_bundle(seed, model="pinhole", robust=None, use_td=True, whiten=True, iters=2):
    bodies, Tc, rig, lms, td = scene(seed, use_td=use_td)
    b = pack(len(bodies), lms, rig[0], rig[1], model, SIGMA, robust, use_td, (1e-3, 10.0), iters)
    mats = np.array([T.matrix() for T in bodies])
    if whiten:
        set_whitening(b, mats, Tc.matrix(), td)
    return b, bodies, Tc, td, mats


def full_problem(b, mats, Tc, td, robust):
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


def _keys(b) -> list[int]:
    return [E(0)] + [X(i) for i in range(b.n_bodies)] + ([D(0)] if b.use_td else [])


def _case(name: str, model: str, use_td: bool, whiten: bool) -> ReducedCase:
    def build(rng: np.random.Generator):
        b, bodies, Tc, td, mats = make_bundle(rng, model, None, use_td, whiten, iters=0)
        refine(b, mats, Tc.matrix(), td, 40)          # depths at their optimum for the gradient
        keys = _keys(b)
        values = gtsam.Values()
        values.insert(keys[0], Tc)
        for k, T in zip(keys[1:], bodies):
            values.insert(k, T)
        if use_td:
            values.insert(keys[-1], np.array([td]))

        def unpack(v):
            B = np.array([v.atPose3(k).matrix() for k in keys[1:1 + b.n_bodies]])
            return B, v.atPose3(keys[0]), float(v.atVector(keys[-1])[0]) if use_td else 0.0

        def full(v):
            B, T, t = unpack(v)
            Hf, gf, _ = full_problem(b, B, T, t, None)
            return Hf, gf, len(b.lam)

        def energy(v):
            c = copy.copy(b)
            c.lam = b.lam.copy()
            B, T, t = unpack(v)
            return refine(c, B, T.matrix(), t, 40)

        return bundle_factor(keys, b), values, ["pose3"] * (1 + b.n_bodies) + ([1] if use_td else []), full, energy

    return ReducedCase(name, build)


REDUCED_CASES: list[ReducedCase] = [
    _case("bundle_pinhole_td_whitened", "pinhole", True, True),
    _case("bundle_sphere_td_whitened", "sphere", True, True),
    _case("bundle_pinhole_plain", "pinhole", False, False),
]
