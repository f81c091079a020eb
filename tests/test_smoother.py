"""The QR re-solve after a Cholesky refusal (vio.backend.smoother): the update that GTSAM's
Cholesky refuses is solved as a QR smoother would have solved it, every recorded factor
slot still names the same factor, and Cholesky comes back once the window has moved on."""

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from vio.backend import smoother


class _Slots:
    """A factor-slot holder like the landmark manager: names -> smoother slots."""

    def __init__(self) -> None:
        self.slots: dict[str, int] = {}

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        self.slots = {n: remap[i] for n, i in self.slots.items() if i in remap}


class _Est(SimpleNamespace):
    @property
    def home_factorization(self):
        return self.cfg.solver.factorization

    def remap_factor_indices(self, remap):
        self.lm.remap_factor_indices(remap)

    def _new_smoother(self, factorization=None):
        p = gtsam.ISAM2Params()
        p.setFactorization(factorization or self.cfg.solver.factorization)
        return gtsam.IncrementalFixedLagSmoother(10.0, p)


def _est(factorization: str) -> _Est:
    est = _Est(cfg=SimpleNamespace(solver=SimpleNamespace(factorization=factorization)),
               smoother_factorization=factorization, qr_since=None, qr_resolves=0,
               lm=_Slots(), values=gtsam.Values(), k=0, kf_t={0: 0})
    est.smoother = est._new_smoother()
    return est


def _prior(key: int, mean, sigmas) -> gtsam.PriorFactorVector:
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float))
    return gtsam.PriorFactorVector(key, np.asarray(mean, float), noise)


def _between(k0: int, k1: int) -> gtsam.BetweenFactorVector:
    return gtsam.BetweenFactorVector(k0, k1, np.array([1.0, 0.5, -0.2]), gtsam.noiseModel.Isotropic.Sigma(3, 0.1))


def _run(est, g, v, stamps, removals=()):
    """The estimator's update step (``Estimator._update``)."""
    try:
        est.smoother.update(g, v, stamps, list(removals))
        return list(est.smoother.getISAM2Result().getNewFactorsIndices())
    except RuntimeError as exc:
        return smoother.qr_resolve(est, g, exc)


def _first(est):
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(_prior(0, [0, 0, 0], [0.1] * 3))
    g.add(_prior(1, [1, 1, 1], [10.0] * 3))
    g.add(_between(0, 1))
    for k in (0, 1):
        v.insert(k, np.zeros(3))
    idx = _run(est, g, v, {0: 0.0, 1: 1.0})
    est.lm.slots = {"p0": idx[0], "weak": idx[1], "b01": idx[2]}


def _ill(key: int) -> gtsam.PriorFactorVector:
    """A prior whose information spans 1e-5 .. 1e5 in oblique directions: GTSAM's
    Cholesky refuses it as indeterminate, QR solves it."""
    Q = gtsam.Rot3.RzRyRx(0.3, -0.5, 0.7).matrix()
    return gtsam.PriorFactorVector(key, np.array([2, 1.5, -0.4]),
                                   gtsam.noiseModel.Gaussian.Covariance(Q @ np.diag([1e-5, 1.0, 1e5]) @ Q.T))


def _second(est):
    """Adds a prior on 1 and variable 2 with the ill-conditioned prior; removes the weak
    prior on 1."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(_prior(1, [1.2, 0.4, 0.1], [0.5] * 3))
    g.add(_ill(2))
    v.insert(2, np.zeros(3))
    est.kf_t[2], est.k = 2, 2
    idx = _run(est, g, v, {2: 2.0}, [est.lm.slots.pop("weak")])
    est.lm.slots.update(p1=idx[0], p2=idx[1])
    est.values = est.smoother.calculateEstimate()


def test_cholesky_refuses_this_update():
    est = _est("CHOLESKY")
    _first(est)
    g = gtsam.NonlinearFactorGraph()
    g.add(_ill(2))
    v = gtsam.Values()
    v.insert(2, np.zeros(3))
    with pytest.raises(RuntimeError, match="Indeterminate"):
        est.smoother.update(g, v, {2: 2.0}, [])


def test_qr_resolve_matches_a_qr_smoother_and_keeps_slots():
    chol, qr = _est("CHOLESKY"), _est("QR")
    for est in (chol, qr):
        _first(est)
        _second(est)
    assert chol.qr_resolves == 1 and chol.smoother_factorization == "QR" and chol.qr_since == 2
    assert qr.qr_resolves == 0
    for k in (0, 1, 2):
        np.testing.assert_allclose(chol.values.atVector(k), qr.values.atVector(k), atol=1e-9)
    fg_c, fg_q = chol.smoother.getFactors(), qr.smoother.getFactors()
    assert set(chol.lm.slots) == {"p0", "b01", "p1", "p2"}
    for name, slot in chol.lm.slots.items():   # each recorded slot names the same factor
        fc, fq = fg_c.at(slot), fg_q.at(qr.lm.slots[name])
        assert fc is not None and fc.keys() == fq.keys()
        assert fc.error(chol.values) == pytest.approx(fq.error(qr.values), rel=1e-9, abs=1e-12)
    assert sum(fg_c.at(j) is not None for j in range(fg_c.size())) == 4   # the removed prior stays removed


def test_back_to_cholesky_once_the_window_moved_on():
    est = _est("CHOLESKY")
    _first(est)
    _second(est)
    smoother.maybe_back_to_cholesky(est)            # keyframe 2 of the refusal still in the window
    assert est.smoother_factorization == "QR"
    est.kf_t = {3: 3}
    g = gtsam.NonlinearFactorGraph()
    g.add(_prior(2, [2, 1.5, -0.4], [0.1] * 3))
    est.smoother.update(g, gtsam.Values(), {}, [est.lm.slots.pop("p2")])
    est.lm.slots["q2"] = list(est.smoother.getISAM2Result().getNewFactorsIndices())[0]
    before = est.smoother.calculateEstimate()
    smoother.maybe_back_to_cholesky(est)
    assert est.smoother_factorization == "CHOLESKY" and est.qr_since is None
    for k in (0, 1, 2):
        np.testing.assert_allclose(est.values.atVector(k), before.atVector(k), atol=1e-9)
    fg = est.smoother.getFactors()
    assert [fg.at(est.lm.slots[n]).keys() for n in ("p0", "b01", "p1", "q2")] == [[0], [0, 1], [1], [2]]


def test_back_to_cholesky_once_the_refused_variable_left():
    """The refusal's variable gone from the window ends the QR window early (real MH_01
    mono: the refused world point had left by the next keyframe, 18 keyframes on QR -> 0);
    while it is there, or when the refusal named none, the window rule holds."""
    assert smoother._refused_key("p187") == gtsam.Symbol("p", 187).key()
    assert smoother._refused_key("?") is None and smoother._refused_key("2") is None
    est = _est("CHOLESKY")
    _first(est)
    _second(est)
    est.qr_key = 2                                   # still in the window
    smoother.maybe_back_to_cholesky(est)
    assert est.smoother_factorization == "QR"
    g = gtsam.NonlinearFactorGraph()                 # the ill-conditioned prior replaced
    g.add(_prior(2, [2, 1.5, -0.4], [0.1] * 3))
    est.smoother.update(g, gtsam.Values(), {}, [est.lm.slots.pop("p2")])
    smoother.maybe_back_to_cholesky(est)
    assert est.smoother_factorization == "QR"         # keyframe 2 of the refusal still there
    est.qr_key = gtsam.Symbol("p", 187).key()        # not in the window (any more)
    smoother.maybe_back_to_cholesky(est)
    assert est.smoother_factorization == "CHOLESKY" and est.qr_since is None


def test_not_a_refusal_is_reraised():
    est = _est("QR")
    with pytest.raises(RuntimeError, match="boom"):
        smoother.qr_resolve(est, gtsam.NonlinearFactorGraph(), RuntimeError("boom"))


def test_update_hands_callbacks_the_linearization_point_uncopied():
    """smoother.update holds a wrapper of iSAM2's theta_, so pybind11 passes it to every
    Python factor callback instead of a copy of the whole Values; same estimate."""
    from factors.adapter import custom_factor
    L = gtsam.symbol_shorthand.L

    def run(held: bool):
        sm = gtsam.IncrementalFixedLagSmoother(10.0, gtsam.ISAM2Params())
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i in range(50):
            g.add(_prior(L(i), [float(i)], [1.0]))
            v.insert(L(i), np.array([0.5 * i]))
        seen = []

        def fn(args):
            return np.array([args[0][0] - args[1][0] - 1.0]), np.array([[1.0, -1.0]])
        for i in range(1, 50):
            g.add(custom_factor(gtsam.noiseModel.Isotropic.Sigma(1, 0.1), [L(i), L(i - 1)], [1, 1], fn))

        def spy(this, values, H):
            seen.append(values)
            if H is not None:
                H[0] = np.zeros((1, 1))
            return np.zeros(1)
        g.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), gtsam.KeyVector([L(0)]), spy))
        stamps = {L(i): 0.0 for i in range(50)}
        (smoother.update(sm, g, v, stamps) if held else sm.update(g, v, stamps))
        theta = sm.getLinearizationPoint()
        return sm.calculateEstimate(), seen, theta

    est_h, seen_h, theta_h = run(True)
    est_p, seen_p, theta_p = run(False)
    assert seen_h and all(s is theta_h for s in seen_h)
    assert seen_p and not any(s is theta_p for s in seen_p)
    L = gtsam.symbol_shorthand.L
    assert all(est_h.atVector(L(i))[0] == est_p.atVector(L(i))[0] for i in range(50))


def _chain_step(k: int, rng: np.random.Generator):
    """Keyframe ``k`` of a turning Pose3 chain: odometry (a 0.4-rad turn and a 1-m step a
    keyframe, noisy), a loose position fix, and a dead-reckoned initial guess 0.3 m off:
    iSAM2 relinearizes keys of the marginal factors after they are made."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.4), np.array([1.0, 0.0, 0.1]))
    truth = [gtsam.Pose3()]
    for _ in range(k):
        truth.append(truth[-1].compose(step))
    if k == 0:
        g.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
        v.insert(0, gtsam.Pose3())
        return g, v
    meas = step.retract(rng.normal(0, 0.02, 6))
    g.add(gtsam.BetweenFactorPose3(k - 1, k, meas, gtsam.noiseModel.Isotropic.Sigma(6, 0.02)))
    g.add(gtsam.GPSFactor(k, truth[k].translation() + rng.normal(0, 0.3, 3),
                          gtsam.noiseModel.Isotropic.Sigma(3, 0.3)))
    v.insert(k, truth[k].retract(np.r_[0.0, 0.0, 0.3, 0.3, -0.2, 0.1]))
    return g, v


def _chain(rebuild_at: tuple[int, ...] = (), n: int = 14, factorization: str = "QR",
           fixed: list | None = None) -> gtsam.Values:
    """The chain's estimate after ``n`` keyframes, rebuilt after each keyframe in
    ``rebuild_at``; ``fixed`` collects (old, new) fixed keys of each rebuild."""
    est = _est(factorization)
    p = gtsam.ISAM2Params()
    p.setFactorization(factorization)
    p.relinearizeSkip = 1
    p.setRelinearizeThreshold(1e-3)
    est._new_smoother = lambda factorization=None: gtsam.IncrementalFixedLagSmoother(3.0, p)
    est.smoother = est._new_smoother()
    rng = np.random.default_rng(7)
    for k in range(n):
        g, v = _chain_step(k, rng)
        est.smoother.update(g, v, {k: float(k)}, [])
        if k in rebuild_at:
            before = sorted(est.smoother.getISAM2().getFixedVariables())
            new, remap, _ = smoother.rebuilt(est)
            smoother.install(est, new, remap)
            if fixed is not None:
                fixed.append((before, sorted(new.getISAM2().getFixedVariables())))
    for _ in range(3):
        est.smoother.update()
    return est.smoother.calculateEstimate()


@pytest.mark.parametrize("factorization", ["QR", "CHOLESKY"])
def test_rebuilt_smoother_is_the_smoother_it_replaces(factorization):
    """A rebuild changes nothing that follows: its marginal factors carry their
    linearization point (``smoother.anchored``), and the keys iSAM2 held fixed (every
    key of a marginal it made) stay fixed (``smoother._fixing_factors``); relinearized,
    they let real MH_05 mono drift (module docstring). Rebuilt once the first marginals
    exist and again three keyframes later, the chain ends where the smoother that was
    never rebuilt does (before the fixed keys were carried over: 1.7e-4 apart), with
    the same fixed keys and no stand-in variable left."""
    fixed: list = []
    ref, got = _chain(factorization=factorization), _chain((6, 9), factorization=factorization, fixed=fixed)
    for k in range(11, 14):
        d = ref.atPose3(k).localCoordinates(got.atPose3(k))
        assert np.linalg.norm(d) < 1e-9, (k, d)
    assert [len(b) for b, _ in fixed] == [1, 1]     # a marginal exists at both rebuilds
    assert all(b == a for b, a in fixed)
    assert sorted(got.keys()) == sorted(ref.keys())   # no stand-in left


@pytest.mark.parametrize("form", ["jacobian", "hessian"])   # QR / Cholesky smoothers' marginals
def test_anchored_marginal_shifts_with_the_estimate(form):
    """``anchored(f, lin)`` evaluated at ``lin`` + dx is the marginal's linear error at dx."""
    lin = gtsam.Values()
    lin.insert(1, gtsam.Pose3(gtsam.Rot3.Rx(0.3), np.array([1.0, 2.0, 3.0])))
    A = np.random.default_rng(3).normal(size=(6, 6))
    b = np.arange(6.0)
    jf = gtsam.JacobianFactor(1, A, b, gtsam.noiseModel.Unit.Create(6))
    raw = gtsam.LinearContainerFactor(jf if form == "jacobian" else gtsam.HessianFactor(jf))
    assert raw.error(lin) == 0.0    # no point: iSAM2's marginal, counted as 0
    f = smoother.anchored(raw, lin)
    dx = np.array([0.01, -0.02, 0.03, 0.1, 0.0, -0.1])
    c = gtsam.Values()
    c.insert(1, lin.atPose3(1).retract(dx))
    assert f.error(c) == pytest.approx(0.5 * np.sum((A @ dx - b) ** 2), rel=1e-9)
    other = _prior(0, [0, 0, 0], [1, 1, 1])
    assert smoother.anchored(other, lin) is other


def test_refusal_at_a_world_point_holds_that_point_and_keeps_cholesky():
    """Refused at a world point (``p<i>``): rebuilt with Cholesky and a prior holding that
    point where it is (``SolverConfig.refusal_point_sigma`` times its distance from the
    newest keyframe), so no QR window follows; the slots still name the same factors and
    the well-determined directions are solved as QR solves them."""
    P, X = gtsam.symbol_shorthand.P, gtsam.symbol_shorthand.X
    ests = []
    for fact, rel in (("CHOLESKY", 1.0), ("QR", 0.0)):
        est = _est(fact)
        est.cfg.solver.refusal_point_sigma = rel
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        g.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
        g.add(_prior(P(1), [1, 1, 1], [0.5] * 3))
        v.insert(X(0), gtsam.Pose3())
        v.insert(P(1), np.ones(3))
        idx = _run(est, g, v, {X(0): 0.0, P(1): 0.0})
        est.lm.slots = {"x0": idx[0], "p1": idx[1]}
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        g.add(_ill(P(2)))
        v.insert(P(2), np.array([2.0, 1.0, 0.0]))
        est.kf_t[1], est.k = 1, 0
        idx = _run(est, g, v, {P(2): 1.0})
        est.lm.slots["p2"] = idx[0]
        est.values = est.smoother.calculateEstimate()
        ests.append(est)
    chol, qr = ests
    assert chol.smoother_factorization == "CHOLESKY" and chol.qr_resolves == 0 and chol.point_holds == 1
    assert qr.qr_resolves == 0 and not hasattr(qr, "point_holds")
    fg = chol.smoother.getFactors()
    assert [list(fg.at(chol.lm.slots[n]).keys()) for n in ("x0", "p1", "p2")] == [[X(0)], [P(1)], [P(2)]]
    # the ill prior's information is 1e5 / 1 / 1e-5 along Q's columns; the hold (sigma:
    # 1.0 x the point's distance sqrt(5) m from keyframe 0, information 0.2) leaves the
    # first as QR solves it, pulls the second by 0.2 / 1.2 and keeps the third in place
    Q = gtsam.Rot3.RzRyRx(0.3, -0.5, 0.7).matrix()
    dc, dq = Q.T @ chol.values.atVector(P(2)), Q.T @ qr.values.atVector(P(2))
    lin = Q.T @ np.array([2.0, 1.0, 0.0])
    assert abs(dc[0] - dq[0]) < 1e-4
    assert dc[1] == pytest.approx((dq[1] + 0.2 * lin[1]) / 1.2, abs=1e-3)
    assert abs(dc[2] - lin[2]) < 1e-3 and abs(dq[2] - lin[2]) > 0.5


def _recording_factor(key: int, points: list) -> gtsam.CustomFactor:
    """A 2-vector identity factor towards 0 that records where it is linearized."""
    def fn(this, values, H):
        if H is not None:
            points.append(np.array(values.atVector(key)))
            H[0] = np.eye(2)
        return values.atVector(key)
    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(2, 1.0), [key], fn)


@pytest.mark.parametrize("own, relinearized", [(None, True), ({"a": (0.05, 2.0)}, False)])
def test_source_keys_relinearize_at_their_own_thresholds(own, relinearized):
    """A factor source's key character with thresholds of its own (``key_thresholds``,
    e.g. a photometric keyframe's [a, b] brightness, b in intensity units) is relinearized
    only when it moves beyond them, not at the general 0.005; a wrong count is refused."""
    from vio.backend.config import SolverConfig
    A = gtsam.symbol_shorthand.A
    s = SolverConfig(relinearize_threshold=0.005, relinearize_skip=1, lag_s=100.0)
    sm = smoother.make(s, {"a": 2}, "QR", own)
    points: list = []
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(_recording_factor(A(0), points))
    v.insert(A(0), np.array([0.0, 0.5]))
    sm.update(g, v, {A(0): 0.0})
    for k in range(1, 4):   # priors at 0.8, 1.1, 1.4: the offset moves to their mean
        g = gtsam.NonlinearFactorGraph()
        g.add(_prior(A(0), [0.0, 0.5 + 0.3 * k], [1e-3, 1e-3]))
        sm.update(g, gtsam.Values(), {A(0): float(k)})
    assert sm.calculateEstimate().atVector(A(0))[1] == pytest.approx(1.1, abs=0.01)
    moved = max(abs(p[1] - 0.5) for p in points)
    assert (moved > 0.2) == relinearized
    with pytest.raises(ValueError, match="relinearization thresholds of key 'a'"):
        smoother.make(s, {"a": 2}, "QR", {"a": (0.05,)})
