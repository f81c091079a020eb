"""Robust kernels and scale estimation (seed 003: Huber, Cauchy, MAD scale).

Two ways to use a kernel:

* per factor, through GTSAM: :func:`robust_noise` wraps a Gaussian noise model in
  ``gtsam.noiseModel.Robust`` (the whole factor's whitened residual norm is reweighted);
* per 2-row block inside a stacked factor (``factors.landmark``): :func:`block_sqrt_weights`
  gives the IRLS square-root weights ``sqrt(w(|r_k| / sigma))`` computed with the same
  formulas as GTSAM's ``mEstimator`` (tests compare them).

``s`` below is always a *whitened* residual norm (unitless).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors.jit import njit as _njit

HUBER_K = 1.345
"""Huber threshold for 95% efficiency under Gaussian noise (seed 003)."""
CAUCHY_C = 2.3849
"""Cauchy scale for 95% efficiency under Gaussian noise (seed 003)."""
MAD_SCALE = 1.4826
"""``1 / Phi^-1(3/4)``: sigma = MAD_SCALE * median|r| for Gaussian r (seed 003)."""
KERNELS = ("none", "huber", "cauchy")


def huber_weight(s: np.ndarray, k: float = HUBER_K) -> np.ndarray:
    """IRLS weight ``w(s) = 1`` for ``|s| <= k`` else ``k / |s|`` (GTSAM ``mEstimator.Huber``)."""
    a = np.abs(np.asarray(s, dtype=float))
    return np.where(a <= k, 1.0, k / np.maximum(a, k))


def huber_loss(s: np.ndarray, k: float = HUBER_K) -> np.ndarray:
    """``rho(s) = s^2/2`` for ``|s| <= k`` else ``k |s| - k^2/2``."""
    a = np.abs(np.asarray(s, dtype=float))
    return np.where(a <= k, 0.5 * a * a, k * a - 0.5 * k * k)


def cauchy_weight(s: np.ndarray, c: float = CAUCHY_C) -> np.ndarray:
    """IRLS weight ``w(s) = 1 / (1 + s^2 / c^2)`` (GTSAM ``mEstimator.Cauchy``)."""
    s = np.asarray(s, dtype=float)
    return 1.0 / (1.0 + (s / c) ** 2)


def cauchy_loss(s: np.ndarray, c: float = CAUCHY_C) -> np.ndarray:
    """``rho(s) = c^2/2 log(1 + s^2 / c^2)``."""
    s = np.asarray(s, dtype=float)
    return 0.5 * c * c * np.log1p((s / c) ** 2)


@dataclass(frozen=True)
class RobustKernel:
    """A robust kernel by name; ``param`` defaults to the seed-003 95%-efficiency value."""

    kind: str = "huber"
    param: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KERNELS:
            raise ValueError(f"unknown robust kernel {self.kind!r}; use one of {KERNELS}")
        if self.param is not None and not self.param > 0:
            raise ValueError(f"robust kernel parameter must be > 0, got {self.param}")

    @property
    def k(self) -> float:
        """The kernel threshold/scale actually used (whitened units)."""
        if self.param is not None:
            return float(self.param)
        return CAUCHY_C if self.kind == "cauchy" else HUBER_K

    def weight(self, s: np.ndarray) -> np.ndarray:
        """IRLS weight of whitened norms ``s`` (any shape)."""
        if self.kind == "huber":
            return huber_weight(s, self.k)
        if self.kind == "cauchy":
            return cauchy_weight(s, self.k)
        return np.ones_like(np.asarray(s, dtype=float))

    def loss(self, s: np.ndarray) -> np.ndarray:
        """Robust loss ``rho(s)`` of whitened norms ``s``."""
        if self.kind == "huber":
            return huber_loss(s, self.k)
        if self.kind == "cauchy":
            return cauchy_loss(s, self.k)
        return 0.5 * np.asarray(s, dtype=float) ** 2

    def estimator(self) -> gtsam.noiseModel.mEstimator.Base:
        """The equivalent GTSAM ``mEstimator`` (``Null`` for ``"none"``)."""
        if self.kind == "huber":
            return gtsam.noiseModel.mEstimator.Huber.Create(self.k)
        if self.kind == "cauchy":
            return gtsam.noiseModel.mEstimator.Cauchy.Create(self.k)
        return gtsam.noiseModel.mEstimator.Null.Create()


def robust_noise(base: gtsam.noiseModel.Base, kernel: RobustKernel) -> gtsam.noiseModel.Base:
    """``gtsam.noiseModel.Robust`` of ``base`` with ``kernel`` (``base`` itself for ``"none"``)."""
    if kernel.kind == "none":
        return base
    return gtsam.noiseModel.Robust.Create(kernel.estimator(), base)


def mad_sigma(r: np.ndarray, center: bool = False) -> float:
    """Robust scale ``sigma = 1.4826 * median|r|`` (seed 003) over all entries of ``r``.

    Pass residual *components* (e.g. both rows of every 2-vector), not block norms: the
    constant assumes each entry is zero-mean Gaussian. ``center=True`` subtracts the
    median first (classical MAD). Raises ``ValueError`` on empty input.
    """
    a = np.asarray(r, dtype=float).reshape(-1)
    a = a[np.isfinite(a)]
    if a.size == 0:
        raise ValueError("mad_sigma needs at least one finite residual")
    if center:
        a = a - np.median(a)
    return float(MAD_SCALE * np.median(np.abs(a)))


def block_sqrt_weights(r: np.ndarray, sigma: float, kernel: RobustKernel | None) -> np.ndarray:
    """IRLS square-root weights (n,) for residual blocks ``r`` (n, d) with noise ``sigma``.

    ``w_k = kernel.weight(|r_k| / sigma)``; multiplying block k of the residual and of the
    Jacobian by ``sqrt(w_k)`` reproduces what ``gtsam.noiseModel.Robust`` does to a factor
    that holds only block k.
    """
    if kernel is None or kernel.kind == "none":
        return np.ones(r.shape[0])
    s = np.sqrt(np.einsum("nd,nd->n", r, r)) / sigma
    return np.sqrt(kernel.weight(s))


@_njit
def _reweight_rows(r: np.ndarray, J: np.ndarray, sigma: float, kind: int, k: float) -> None:
    n = r.shape[0]
    for o in range(n):
        s = np.sqrt(r[o, 0] * r[o, 0] + r[o, 1] * r[o, 1]) / sigma
        if kind == 1:
            w = 1.0 if s <= k else k / s
        elif kind == 2:
            w = 1.0 / (1.0 + (s / k) ** 2)
        else:
            w = 1.0
        sw = np.sqrt(w)
        r[o, 0] *= sw
        r[o, 1] *= sw
        for c in range(J.shape[1]):
            J[2 * o, c] *= sw
            J[2 * o + 1, c] *= sw


def reweight_blocks(r: np.ndarray, J: np.ndarray, sigma: float, kernel: RobustKernel) -> None:
    """In place: scale residual block k of ``r`` (n, 2) and rows ``2k, 2k+1`` of ``J`` (2n, D)
    by ``sqrt(w(|r_k| / sigma))`` -- :func:`block_sqrt_weights` fused for the landmark factor."""
    _reweight_rows(r, J, float(sigma), KERNELS.index(kernel.kind), kernel.k)

