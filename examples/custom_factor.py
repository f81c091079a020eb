"""Add your own factor: a pure residual with analytic Jacobians in GTSAM conventions.

Example: a range measurement from a body pose ``T_w_b`` to a known beacon ``p_w``:
``r = |t - p_w| - d``. With GTSAM's retraction ``T * Exp([omega, v])`` the translation
moves by ``R v``, so ``dr/d[omega, v] = [0, u^T R]`` with ``u`` the unit direction.
The numeric check below is the same judge the project's Jacobian suite uses.

    python examples/custom_factor.py
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.utils.numerical_derivative import numericalDerivative11

from factors.adapter import custom_factor

P_W = np.array([2.0, -1.0, 0.5])


def range_residual(args: list, d: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """``args = [T_w_b]``; returns r (1,) and [J (1, 6)]."""
    T = args[0]
    delta = T.translation() - P_W
    rng = float(np.linalg.norm(delta))
    u = delta / rng
    J = np.zeros((1, 6))
    J[0, 3:] = u @ T.rotation().matrix()
    return np.array([rng - d]), [J]


def main() -> None:
    X0 = gtsam.symbol_shorthand.X(0)
    T = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([0.5, 0.4, 1.0]))
    factor = custom_factor(gtsam.noiseModel.Isotropic.Sigma(1, 0.05), [X0], ["pose3"],
                           lambda a: range_residual(a, 2.5))
    values = gtsam.Values()
    values.insert(X0, T)
    _, (J,) = range_residual([T], 2.5)
    numeric = numericalDerivative11(lambda pose: range_residual([pose], 2.5)[0], T)
    print("analytic", J.round(6))
    print("numeric ", numeric.round(6))
    assert np.allclose(J, numeric, atol=1e-7), "Jacobian mismatch"
    lin = factor.linearize(values)
    print("whitened block from linearize():", lin.jacobian()[0].round(4))


if __name__ == "__main__":
    main()
