"""Padding keys (vio.backend.padding): with them an update that touches every real key
takes iSAM2's incremental path, so the Python factors already in the graph are not
called again, and the estimate is the one without padding."""

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from factors.adapter import custom_factor
from vio.backend import padding, smoother
from vio.backend.config import SolverConfig

L = gtsam.symbol_shorthand.L


def _sum_factor(keys: list[int], target: float, calls: list[int]) -> gtsam.CustomFactor:
    """r = sum of the keys' values - target (1 row); counts its calls in calls[0]."""
    def fn(args):
        calls[0] += 1
        return np.array([sum(float(a[0]) for a in args) - target]), np.ones((1, len(args)))
    return custom_factor(gtsam.noiseModel.Isotropic.Sigma(1, 0.1), keys, [1] * len(keys), fn)


def _run(pad: bool, n_updates: int = 6) -> tuple[list[int], gtsam.Values]:
    """Each update adds a key and one factor over every key (all of them touched); returns
    the calls of the first update's factors during each later update, and the estimate."""
    cfg = SolverConfig(relinearize_skip=1000, incremental_padding=pad)
    est = SimpleNamespace(cfg=SimpleNamespace(solver=cfg), smoother=smoother.make(cfg),
                          values=gtsam.Values(), n_pad=0, k=0, kf_t={0: 0})
    first = [0]
    later = []
    for u in range(n_updates):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        calls = first if u == 0 else [0]
        g.add(gtsam.PriorFactorVector(L(u), np.array([float(u)]), gtsam.noiseModel.Isotropic.Sigma(1, 1.0)))
        g.add(_sum_factor([L(i) for i in range(u + 1)], 2.0 * u, calls))
        v.insert(L(u), np.array([0.5 * u]))
        est.k, est.kf_t[u] = u, u * 10**8
        stamps = {L(u): u * 0.1}
        padding.pad(est, g, v, stamps)
        before = first[0]
        est.smoother.update(g, v, stamps)
        est.values = est.smoother.calculateEstimate()
        if u:
            later.append(first[0] - before)
    return later, est.values


def test_padding_keeps_old_factors_out_of_later_updates():
    plain, v_plain = _run(False)
    padded, v_pad = _run(True)
    assert sum(plain) >= 4          # without padding: batch steps call the old factor again
    assert sum(padded) == 0         # with padding: iSAM2's cached linearization is used
    for i in range(6):
        assert v_pad.atVector(L(i))[0] == pytest.approx(v_plain.atVector(L(i))[0], abs=1e-9)


@pytest.mark.parametrize("n_real", [0, 1, 10, 155, 1000])
def test_needed_keeps_every_touch_below_the_batch_threshold(n_real):
    n_pad = padding.needed(n_real)
    assert n_real < 0.65 * (n_real + n_pad)
    assert n_pad <= 0.56 * n_real + 5


def test_padding_keys_stay_in_the_window():
    """Their timestamps follow the newest keyframe: a long run never marginalizes them."""
    cfg = SolverConfig(lag_s=0.5)
    est = SimpleNamespace(cfg=SimpleNamespace(solver=cfg), smoother=smoother.make(cfg),
                          values=gtsam.Values(), n_pad=0, k=0, kf_t={})
    for u in range(12):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        g.add(gtsam.PriorFactorVector(L(u), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 1.0)))
        v.insert(L(u), np.zeros(1))
        est.k, est.kf_t[u] = u, u * 2 * 10**8
        stamps = {L(u): u * 0.2}
        padding.pad(est, g, v, stamps)
        est.smoother.update(g, v, stamps)
        est.values = est.smoother.calculateEstimate()
    assert est.n_pad == padding.needed(4)     # at most 3 keys of the window plus the new one
    assert all(est.values.exists(padding.Z(i)) for i in range(est.n_pad))
    assert not est.values.exists(L(0))
