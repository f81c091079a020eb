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


@dataclass(frozen=True)
class ReducedCase:
    """A factor whose variables' companions (inverse depths) are eliminated inside it, so
    its residual is a square root of the reduced quadratic rather than a function whose
    derivative is its Jacobian (``factors.landmark_schur``, ``factors.photometric_host``).

    ``build(rng)`` returns the factor, the values of its keys, the key kinds, ``full(values)
    -> (H, g)`` of the full point-wise problem with the eliminated variables as the last
    columns and ``n_elim`` their number, and ``energy(values)`` the energy minimized over
    the eliminated variables (no robust kernel), for the numerical gradient. The suite
    checks ``A^T A`` and ``-A^T b`` of ``factor.linearize(values)`` against the Schur
    complement of ``full`` and that gradient against central differences of ``energy``.
    """

    name: str
    build: Callable[[np.random.Generator], tuple]
    degenerate: bool = False
