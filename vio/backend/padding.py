"""Padding keys that keep iSAM2 on its incremental path.

GTSAM's ``ISAM2::recalculate`` takes a batch step whenever the keys an update touches
(those of new and removed factors, relinearized keys, and every key in the cliques above
them) are at least 65 % of all keys (``kBatchThreshold``, hard-coded in ``ISAM2.cpp``).
The batch step (``recalculateBatch``) relinearizes EVERY factor of the graph at the
unchanged linearization point. In a sliding window each keyframe brings observations of
nearly every live landmark, so nearly every keyframe update was a batch step: every
Python factor was called again (the adapter's cache answers, but a call still costs the
Values copy pybind11 makes for it, the argument reads and the Jacobian hand-back), about
15,000 of the ~25,700 callbacks of real MH_05 mono. The incremental path
(``recalculateIncremental``) re-eliminates the same affected keys but takes iSAM2's cached
linear factor (``cacheLinearizedFactors``) for every factor none of whose keys was
relinearized: the same linear system, so the same estimate up to elimination order.

So the window carries inert padding keys (``Z(i)``, 1-vectors), each held by its own unit
prior: a separate tree of the Bayes forest that no update touches, only counted in
``theta_.size()``. There are enough of them that the touched fraction stays below the
threshold even when every real key is touched: ``n_pad >= 0.54 n_real`` (1 / 0.65 - 1),
with a margin. They never leave the window (their timestamps follow the newest
keyframe) and are never read; each costs ~0.1 us in the Values copy pybind11 makes for
every Python callback (real MH_05 mono: ~90-100 padding keys for 155-170 real ones).
``SolverConfig.incremental_padding`` turns this off.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import gtsam
import numpy as np

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

Z = gtsam.symbol_shorthand.Z
KEY_CHAR = "z"
_BATCH_FRACTION = 0.65      # GTSAM ISAM2.cpp kBatchThreshold
_MARGIN = 1.02              # above the bare ratio; plus a few keys for small windows
_NOISE = gtsam.noiseModel.Unit.Create(1)


def needed(n_real: int) -> int:
    """Padding keys that keep ``n_real`` touched keys under the batch threshold."""
    return int(math.ceil(n_real * (1.0 / _BATCH_FRACTION - 1.0) * _MARGIN)) + 4


def pad(est: "Estimator", g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict) -> None:
    """Before ``est.smoother.update(g, v, stamps, ...)``: add the padding keys the window
    now needs (priors appended at the end of ``g``, so the managers' recorded factor
    positions hold) and keep every padding key in the window (``stamps``).

    ``est.n_pad``: padding keys in ``est.smoother`` (0 after a restart; a rebuilt
    smoother takes them over with the old factors and values)."""
    if not est.cfg.solver.incremental_padding:
        return
    n_real = int(est.values.size()) - est.n_pad + int(v.size())
    want = needed(n_real)
    zero = np.zeros(1)
    for i in range(est.n_pad, want):
        g.add(gtsam.PriorFactorVector(Z(i), zero, _NOISE))
        v.insert(Z(i), zero)
    est.n_pad = max(est.n_pad, want)
    t = est.kf_t[est.k] * 1e-9
    for i in range(est.n_pad):
        stamps[Z(i)] = t
