"""A small dense Levenberg-Marquardt solver (seed 003: Madsen/Nielsen).

Minimizes F(x) = sum_i rho(r_i(x)) with rho(r) = r^2 / 2 (least squares) or Huber
with threshold k (rho = k |r| - k^2 / 2 beyond k), on a vector space or a manifold
(``retract(x, h)``). Robust costs use IRLS normal equations: A = J^T W J,
g = J^T W r with W = rho'(r) / r, which is the exact gradient of F and the usual
Gauss-Newton Hessian model, so the gain ratio stays meaningful.

Seed 003 algorithm, with our sign convention (g is the gradient, not J^T eps):
    mu = tau * max diag(A)          [Marquardt scaling: mu = tau, D = diag(A)]
    solve (A + mu D) h = -g;  stop if ||h|| <= eps2 (||x|| + eps2)
    rho = (F(x) - F(x + h)) / (h^T (mu D h - g) / 2)
    rho > 0: accept, mu *= max(1/3, 1 - (2 rho - 1)^3), nu = 2
    else:    mu *= nu, nu *= 2
Stops: ||g||_inf <= eps1, ||r|| <= eps3, relative decrease of ||r|| < eps4, small
step, ``max_iters`` iterations or ``max_rejects`` consecutive rejections.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from vio.direct.config import LMConfig

ResidualFn = Callable[[Any], tuple[np.ndarray, np.ndarray]]
"""x -> (r (m,), J (m, n)); J is the derivative along ``retract``'s tangent."""


@dataclass(frozen=True)
class LMResult:
    """Outcome of ``levenberg_marquardt``; costs are F = sum rho(r_i)."""

    x: Any
    cost: float
    initial_cost: float
    iterations: int
    evaluations: int
    mu: float
    stop_reason: str
    converged: bool


def robust_cost(r: np.ndarray, huber_k: float | None, n_plain: int = 0) -> tuple[float, np.ndarray]:
    """F = sum rho(r_i) and the IRLS weights W_i = rho'(r_i) / r_i; the last ``n_plain``
    residuals (a Gaussian prior) stay least squares."""
    a = np.abs(r)
    if huber_k is None:
        return 0.5 * float(r @ r), np.ones_like(r)
    inl = a <= huber_k
    if n_plain:
        inl[len(r) - n_plain:] = True
    F = float(np.sum(np.where(inl, 0.5 * r * r, huber_k * a - 0.5 * huber_k ** 2)))
    return F, np.where(inl, 1.0, huber_k / np.maximum(a, 1e-300))


def _vector_norm(x: Any) -> float:
    return float(np.linalg.norm(x)) if isinstance(x, np.ndarray) else 1.0


def _normal_equations(r: np.ndarray, J: np.ndarray, huber_k: float | None, n_plain: int = 0):
    F, w = robust_cost(r, huber_k, n_plain)
    Jw = J * w[:, None]
    return F, Jw.T @ J, Jw.T @ r


def _solve(A: np.ndarray, g: np.ndarray, mu: float, D: np.ndarray) -> np.ndarray | None:
    M = A + mu * np.diag(D)
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return None
    return -np.linalg.solve(L.T, np.linalg.solve(L, g))


def levenberg_marquardt(fun: ResidualFn, x0: Any, config: LMConfig = LMConfig(),
                        retract: Callable[[Any, np.ndarray], Any] | None = None,
                        norm: Callable[[Any], float] = _vector_norm, n_plain: int = 0) -> LMResult:
    """Minimize sum rho(r(x)) from ``x0``; see the module docstring.

    ``retract(x, h)`` defaults to ``x + h``; ``norm(x)`` scales the eps2 step test
    (default: the Euclidean norm for arrays, 1 otherwise); the last ``n_plain``
    residuals are least squares whatever ``config.huber_k``.
    """
    retract = retract or (lambda x, h: x + h)
    c = config
    x = x0
    r, J = fun(x)
    F, A, g = _normal_equations(r, J, c.huber_k, n_plain)
    F0, evals, k, nu = F, 1, 0, 2.0
    diag_mode = c.damping == "diagonal"
    D = np.maximum(np.diag(A), 1e-12 * max(np.max(np.diag(A)), 1e-300)) if diag_mode else np.ones(len(g))
    mu = c.tau if diag_mode else c.tau * max(float(np.max(np.diag(A))), 1e-300)
    reason = "gradient" if np.max(np.abs(g)) <= c.eps1 else ""
    while not reason and k < c.max_iters:
        k += 1
        rejects = 0
        while True:
            h = _solve(A, g, mu, D)
            if h is None:
                mu, nu, rejects = mu * nu, nu * 2.0, rejects + 1
            elif np.linalg.norm(h) <= c.eps2 * (norm(x) + c.eps2):
                reason = "small_step"
                break
            else:
                x_new = retract(x, h)
                r_new, J_new = fun(x_new)
                evals += 1
                F_new, _ = robust_cost(r_new, c.huber_k, n_plain)
                denom = 0.5 * float(h @ (mu * D * h - g))
                gain = (F - F_new) / denom if denom > 0 else -1.0
                if gain > 0 and np.isfinite(F_new):
                    if np.sqrt(F) - np.sqrt(F_new) < c.eps4 * np.sqrt(F):
                        reason = "small_decrease"
                    x, r, J = x_new, r_new, J_new
                    F, A, g = _normal_equations(r, J, c.huber_k, n_plain)
                    if diag_mode:
                        D = np.maximum(D, np.diag(A))
                    if np.max(np.abs(g)) <= c.eps1:
                        reason = reason or "gradient"
                    mu *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                    nu = 2.0
                    break
                mu, nu, rejects = mu * nu, nu * 2.0, rejects + 1
            if rejects >= c.max_rejects:
                reason = "rejected"
                break
        if not reason and np.sqrt(2.0 * F) <= c.eps3:
            reason = "small_residual"
    reason = reason or "max_iters"
    converged = reason in ("gradient", "small_step", "small_decrease", "small_residual")
    return LMResult(x, F, F0, k, evals, mu, reason, converged)
