"""The protocol every factor's Jacobian cases follow.

Each ``tests/cases_*.py`` module exports ``CASES: list[JacobianCase]``; the one
parametrized suite in ``tests/test_jacobians.py`` collects them all and checks every
key of every case against ``gtsam.utils.numerical_derivative`` and
``factor.linearize(values)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np


@dataclass(frozen=True)
class JacobianCase:
    """A factor at a (random or degenerate) state.

    ``build(rng)`` returns the factor, the values of its keys, the analytic
    residual function ``residual(values) -> (r, jacobians)`` (unwhitened, in key
    order), and the key kinds (``"pose3"`` or vector length) so the suite can
    perturb each key numerically.
    """

    name: str
    build: Callable[[np.random.Generator], tuple[gtsam.NonlinearFactor, gtsam.Values,
                                                  Callable, list]]
    degenerate: bool = False
