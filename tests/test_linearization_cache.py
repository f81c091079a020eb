"""The adapter's linearization cache (``factors.adapter.custom_factor(cache=True)``): a
factor is evaluated again only when the values of its keys or its declared state change,
and inside iSAM2 it saves the relinearizations of ``ISAM2::recalculateBatch``."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.adapter import custom_factor

X, S = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.S


def _counting_factor(cache: bool, state=None, scale: list | None = None):
    """A prior-like factor on X(0) (pose3) and S(0) (2-vector); counts its calls."""
    calls = []
    scale = [1.0] if scale is None else scale

    def fn(args):
        calls.append(1)
        T, s = args
        r = np.concatenate([gtsam.Pose3.Logmap(T), s]) * scale[0]
        return r, [np.vstack([np.eye(6), np.zeros((2, 6))]) * scale[0],
                   np.vstack([np.zeros((6, 2)), np.eye(2)]) * scale[0]]

    f = custom_factor(gtsam.noiseModel.Unit.Create(8), [X(0), S(0)], ["pose3", 2], fn,
                      cache=cache, state=state)
    return f, calls


def _values(t: float, s: float) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(gtsam.Rot3.Rz(0.1), np.array([t, 0.0, 1.0])))
    v.insert(S(0), np.array([s, -s]))
    return v


def test_same_values_reuse_the_linearization_bitwise() -> None:
    f, calls = _counting_factor(cache=True)
    a = f.linearize(_values(0.3, 0.2))
    b = f.linearize(_values(0.3, 0.2))   # a fresh Values with the same numbers
    assert len(calls) == 1
    assert np.array_equal(a.jacobian()[0], b.jacobian()[0])
    assert np.array_equal(a.jacobian()[1], b.jacobian()[1])
    e = f.error(_values(0.3, 0.2))       # error() at the cached point: no call either
    assert len(calls) == 1
    assert e == 0.5 * float(np.sum(b.getb() ** 2))


def test_changed_values_or_state_are_evaluated_again() -> None:
    scale = [1.0]
    f, calls = _counting_factor(cache=True, state=lambda: scale[0], scale=scale)
    f.linearize(_values(0.3, 0.2))
    f.linearize(_values(0.3 + 1e-15, 0.2))   # one ulp-scale change of one key
    assert len(calls) == 2
    f.linearize(_values(0.3 + 1e-15, 0.2 + 1e-16))
    assert len(calls) == 3
    scale[0] = 2.0                           # state changed outside the factor
    lin = f.linearize(_values(0.3 + 1e-15, 0.2 + 1e-16))
    assert len(calls) == 4
    assert np.allclose(lin.jacobian()[0][:6, :6], 2.0 * np.eye(6))


def test_error_only_calls_do_not_replace_the_cached_linearization() -> None:
    f, calls = _counting_factor(cache=True)
    f.linearize(_values(0.3, 0.2))
    f.error(_values(0.5, 0.2))          # somewhere else: evaluated, not cached
    f.linearize(_values(0.3, 0.2))      # back at the linearization point: cached
    assert len(calls) == 2


def test_without_cache_every_call_evaluates() -> None:
    f, calls = _counting_factor(cache=False)
    for _ in range(3):
        f.linearize(_values(0.3, 0.2))
    assert len(calls) == 3


def test_isam2_batch_steps_hit_the_cache_and_give_the_same_estimate() -> None:
    """A chain of poses with between factors; every step adds a pose and touches most of
    the variables, so iSAM2 re-eliminates in batch and relinearizes every factor at its
    unchanged linearization point. Cached and uncached factors give the same bits."""
    def run(cache: bool):
        p = gtsam.ISAM2Params()
        p.relinearizeSkip = 10
        isam = gtsam.ISAM2(p)
        calls = []
        noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
        step = gtsam.Pose3(gtsam.Rot3.Rz(0.05), np.array([1.0, 0.0, 0.0]))

        def between(i):
            def fn(args):
                calls.append(i)
                f = gtsam.BetweenFactorPose3(X(i), X(i + 1), step, noise)
                v = gtsam.Values()
                v.insert(X(i), args[0])
                v.insert(X(i + 1), args[1])
                J = f.linearize(v)
                A, b = J.jacobian()
                sig = 0.1   # unwhiten: the adapter's noise model whitens again
                return -b * sig, [A[:, :6] * sig, A[:, 6:] * sig]
            return custom_factor(noise, [X(i), X(i + 1)], ["pose3", "pose3"], fn, cache=cache)

        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        g.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
        v.insert(X(0), gtsam.Pose3())
        isam.update(g, v)
        for i in range(8):
            g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
            g.add(between(i))
            v.insert(X(i + 1), gtsam.Pose3(gtsam.Rot3.Rz(0.04 * (i + 1)), np.array([0.9 * (i + 1), 0.1, 0.0])))
            isam.update(g, v)
        est = isam.calculateEstimate()
        return np.array([est.atPose3(X(i)).matrix() for i in range(9)]), len(calls)

    with_cache, n_cached = run(True)
    without, n_plain = run(False)
    assert np.array_equal(with_cache, without)
    assert n_cached < n_plain
