"""The stacked factor (factors.stack): the quadratic of the members summed, one failing
member dropped alone, inconsistent members refused."""

import gtsam
import numpy as np
import pytest

import cases_stack
from cases_stack import CASES
from factors.adapter import FactorHealth, custom_factor
from factors.stack import Member, stacked_factor

L = gtsam.symbol_shorthand.L


def _hessian(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: list[int]):
    """(A^T A, A^T b) of the linearized graph in the column order of ``keys``."""
    lin = graph.linearize(values)
    order = gtsam.Ordering()
    for k in keys:
        order.push_back(k)
    A, b = lin.jacobian(order)
    return A.T @ A, A.T @ b


@pytest.mark.parametrize("case", CASES[:2], ids=lambda c: c.name)
def test_stack_is_the_sum_of_its_members(case, monkeypatch):
    captured = []   # the case's members, to build them as separate factors too
    orig = cases_stack.stacked_factor
    monkeypatch.setattr(cases_stack, "stacked_factor", lambda mems: captured.extend(mems) or orig(mems))
    stacked, values, _, _ = case.build(np.random.default_rng(3))
    keys = [int(k) for k in stacked.keys()]
    single = gtsam.NonlinearFactorGraph()
    for mem in captured:
        single.add(custom_factor(gtsam.noiseModel.Isotropic.Sigma(mem.m, mem.sigma), mem.keys, mem.kinds, mem.fn))
    one = gtsam.NonlinearFactorGraph()
    one.add(stacked)
    H1, g1 = _hessian(one, values, keys)
    H2, g2 = _hessian(single, values, keys)
    assert len(captured) == 3
    assert np.allclose(H1, H2, rtol=1e-10, atol=1e-6 * np.abs(H2).max())
    assert np.allclose(g1, g2, rtol=1e-10, atol=1e-6 * np.abs(g2).max())
    assert stacked.error(values) == pytest.approx(single.error(values), rel=1e-10)


def _member(key_a: int, key_b: int, target: float, sigma: float, fail: bool = False) -> Member:
    def fn(args):
        if fail:
            raise ZeroDivisionError("planted")
        return np.array([args[0][0] - args[1][0] - target]), np.array([[1.0, -1.0]])
    return Member((key_a, key_b), (1, 1), fn, 1, sigma)


def test_a_failing_member_drops_out_alone():
    health = FactorHealth()
    f = stacked_factor([_member(L(0), L(1), 1.0, 0.5), _member(L(1), L(2), 2.0, 0.1, fail=True)], health)
    v = gtsam.Values()
    for i, x in enumerate([3.0, 1.0, 0.0]):
        v.insert(L(i), np.array([x]))
    r = f.unwhitenedError(v)
    assert r == pytest.approx([(3.0 - 1.0 - 1.0) / 0.5, 0.0])
    assert health.failures == 1 and "planted" in health.last_error


def test_inconsistent_members_are_refused():
    good = _member(L(0), L(1), 0.0, 1.0)
    with pytest.raises(ValueError, match="is 1 in one member"):
        stacked_factor([good, Member((L(1), L(2)), ("pose3", 1), good.fn, 1, 1.0)])
    with pytest.raises(ValueError, match="sigma > 0"):
        stacked_factor([Member((L(0), L(1)), (1, 1), good.fn, 1, 0.0)])
    with pytest.raises(ValueError, match="at least one"):
        stacked_factor([])
