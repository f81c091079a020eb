"""``vio.backend.outlier_carry``: a held outlier update keeps its slots through a rebuild's
remapping and never asks iSAM2 to remove an empty slot."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from vio.backend.outlier_carry import OutlierCarry

X = gtsam.symbol_shorthand.X
NOISE = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)


def _smoother(n: int = 4) -> gtsam.IncrementalFixedLagSmoother:
    """n Point3 keys, a prior on each (slots 0..n-1), a between factor per pair (n..2n-2)."""
    sm = gtsam.IncrementalFixedLagSmoother(100.0, gtsam.ISAM2Params())
    g, v, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    for i in range(n):
        g.add(gtsam.PriorFactorPoint3(X(i), np.full(3, float(i)), NOISE))
        v.insert(X(i), np.full(3, float(i)))
        stamps[X(i)] = float(i)
    for i in range(n - 1):
        g.add(gtsam.BetweenFactorPoint3(X(i), X(i + 1), np.ones(3), NOISE))
    sm.update(g, v, stamps)
    return sm


def test_take_returns_the_held_update_once_without_empty_slots():
    sm = _smoother()
    carry = OutlierCarry()
    assert carry.take(sm) is None
    prior = gtsam.NonlinearFactorGraph()
    prior.add(gtsam.PriorFactorPoint3(X(3), np.full(3, 3.0), NOISE))
    assert carry.hold(prior, {X(3): 0.0}, [5, 5, 1], 0) == 0        # nothing rejected: nothing held
    assert carry.take(sm) is None
    assert carry.hold(prior, {X(3): 0.0}, [5, 5, 1], 2) == 2
    with pytest.raises(RuntimeError, match="already held"):
        carry.hold(prior, {}, [], 1)
    sm.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, [1])   # slot 1 emptied meanwhile
    g, stamps, removals = carry.take(sm)
    assert removals == [5] and stamps == {X(3): 0.0} and g.size() == 1
    sm.update(g, gtsam.Values(), stamps, removals)                    # accepted by iSAM2
    assert sm.getFactors().at(5) is None
    assert carry.take(sm) is None


def test_remap_and_clear():
    carry = OutlierCarry()
    carry.remap({0: 1})                                               # nothing held: no-op
    carry.hold(gtsam.NonlinearFactorGraph(), {}, [2, 7], 1)
    carry.remap({2: 0, 5: 1})
    assert carry.take(_smoother())[2] == [0]
    carry.hold(gtsam.NonlinearFactorGraph(), {}, [2], 1)
    carry.clear()
    assert carry.take(_smoother()) is None
