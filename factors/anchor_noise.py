"""Anchor-noise whitening for the inverse-depth factors (``factors.landmark``,
``factors.stereo``).

Those factors take a landmark's anchor observation as its exact ray. When the anchor pixel
is as noisy as every target observation, the stacked residual's covariance is
``sigma^2 (I + G G^T)`` to first order, ``G = dr/duv_anchor``; whitening with
``(I + G G^T)^(-1/2)``, a constant of the factor computed at the estimate when it is built,
marginalizes the anchor noise analytically and keeps one parameter per landmark.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class AnchorWhitening(NamedTuple):
    """``W = I + U diag(d) U^T`` (m, m), a rank-2 update of the identity; see
    :func:`anchor_whitening`. ``apply`` costs O(m) per column instead of O(m^2)."""

    U: np.ndarray  # (m, r), orthonormal columns, r <= 2
    d: np.ndarray  # (r,)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``W x`` for x (m,) or (m, c)."""
        if x.ndim == 1:
            return x + self.U @ (self.d * (self.U.T @ x))
        return x + self.U @ (self.d[:, None] * (self.U.T @ x))

    def matrix(self) -> np.ndarray:
        return np.eye(self.U.shape[0]) + (self.U * self.d) @ self.U.T


def anchor_whitening(G: np.ndarray) -> AnchorWhitening:
    """Whitening ``W = (I + G G^T)^(-1/2)`` (m, m) of the residuals of one anchored landmark
    whose anchor observation is noisy too.

    The inverse-depth factors take the anchor observation as the exact ray; with isotropic
    noise ``sigma`` on it as on every target observation, the stacked residual's covariance
    is ``sigma^2 (I + G G^T)`` to first order, ``G = dr/duv_anchor`` (m, 2) (the ``uvi``
    blocks of :func:`factors.projection.project_batch`, stacked). ``W r`` then has
    covariance ``sigma^2 I``:
    the anchor noise is marginalized analytically and the landmark keeps one parameter.
    With ``G = U diag(s)^(1/2) V^T``, ``W = I + U ((1 + s)^(-1/2) - 1) U^T``.
    """
    G = np.asarray(G, dtype=float)
    s, V = np.linalg.eigh(G.T @ G)
    keep = s > 1e-12 * max(1.0, float(s.max(initial=0.0)))
    U = (G @ V[:, keep]) / np.sqrt(s[keep])
    return AnchorWhitening(U, (1.0 + s[keep]) ** -0.5 - 1.0)
