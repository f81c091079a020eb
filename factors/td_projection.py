"""Time-offset projection factor (seed 004, ``projection_td_factor``), GTSAM conventions.

Adds the camera-IMU time offset ``td`` (1-vector, seconds; image stamp + td = IMU time
of exposure) to :mod:`factors.projection`. Each observation is moved along its image
velocity ``vel`` (normalized-plane units per second) to the time of the state (seed 004)::

    uv_td = uv - (td - td_obs + row / ROWS * t_readout) * vel

separately for the anchor observation i and the target observation j, each with its own
``vel``, ``row`` and ``td_obs`` (the td used when the velocity/observation was recorded).
The shifted observations are then fed to the projection code unchanged
(:func:`factors.projection.project_batch`), and the td Jacobian is the exact chain rule::

    dr/dtd = dr/duv_i * (-vel_i) + dr/duv_j * (-vel_j)

For the ``"sphere"`` model the tangent basis ``B`` is built from the *raw* observation
``uv_j`` (a constant of the measurement), while the bearing it is compared with is the
*shifted* one; ``dr/duv_j = -B (I - b b^T) / |m_j|`` then includes the derivative of the
normalization. VINS-Mono instead uses ``+sqrt_info * vel_j.head(2)``, which holds only if
``|m_j| = 1`` and ``B`` is aligned with the image axes; it is not used here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.bearing_model import check_model, tangent_basis
from factors.projection import Projected, project_batch, single_blocks


@dataclass(frozen=True)
class TdObservation:
    """One observation with its image velocity for the td factor.

    ``uv`` (2,) normalized-plane point at the image stamp; ``vel`` (2,) its velocity in
    normalized units per second; ``row_time = row / ROWS * t_readout`` (s) the rolling-shutter
    delay of its row (0 for a global shutter); ``td_obs`` (s) the td in use when it was recorded.
    """

    uv: np.ndarray
    vel: np.ndarray
    row_time: float = 0.0
    td_obs: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "uv", np.asarray(self.uv, dtype=float).reshape(2))
        object.__setattr__(self, "vel", np.asarray(self.vel, dtype=float).reshape(2))

    @staticmethod
    def create(uv: np.ndarray, vel: np.ndarray, row: float = 0.0, rows: int = 1,
               t_readout: float = 0.0, td_obs: float = 0.0) -> "TdObservation":
        """Build from the pixel ``row`` of ``rows`` and the frame readout time (s)."""
        if rows <= 0:
            raise ValueError(f"rows must be positive, got {rows}")
        return TdObservation(np.asarray(uv, dtype=float).reshape(2),
                             np.asarray(vel, dtype=float).reshape(2),
                             float(row) / rows * float(t_readout), float(td_obs))

    @property
    def offset(self) -> float:
        """``row_time - td_obs`` (s): the shift is ``(td + offset) * vel``."""
        return self.row_time - self.td_obs


def shift_uv(uv: np.ndarray, vel: np.ndarray, offset: np.ndarray, td: float) -> np.ndarray:
    """``uv - (td + offset) * vel`` (seed 004); ``uv``, ``vel`` (..., 2), ``offset`` (...)."""
    return uv - (td + np.asarray(offset, dtype=float))[..., None] * vel


def td_project_batch(Ti: np.ndarray, Tjs: np.ndarray, Tc: np.ndarray, lam: float, td: float,
                     uv_i: np.ndarray, vel_i: np.ndarray, offset_i: float,
                     uv_j: np.ndarray, vel_j: np.ndarray, offset_j: np.ndarray, model: str,
                     basis: np.ndarray) -> Projected:
    """Batched td residuals for n targets of one anchor (seed 004 chain rule).

    As :func:`factors.projection.project_batch` (``Ti``, ``Tjs``, ``Tc`` homogeneous
    matrices, ``basis`` (n, 2, 3) from the *raw* ``uv_j``) with the anchor ``uv_i, vel_i``
    (2,), targets ``uv_j, vel_j`` (n, 2), ``offset_j`` (n,); the last column of ``J`` is
    ``dr/dtd``.
    """
    return project_batch(Ti, Tjs, Tc, lam, shift_uv(uv_i, vel_i, offset_i, td),
                         shift_uv(uv_j, vel_j, offset_j, td), model, basis, vel_i, vel_j)


def td_projection_residual(T_w_bi: gtsam.Pose3, T_w_bj: gtsam.Pose3, T_b_c: gtsam.Pose3,
                           inv_depth: float, td: float, obs_i: TdObservation,
                           obs_j: TdObservation, model: str = "pinhole"
                           ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual (2,) and ``[J_Ti (2,6), J_Tj (2,6), J_Tbc (2,6), J_lam (2,1), J_td (2,1)]``.

    ``td`` in seconds; other arguments as :func:`factors.projection.projection_residual`.
    """
    check_model(model)
    uv_j = obs_j.uv.reshape(1, 2)
    p = td_project_batch(T_w_bi.matrix(), T_w_bj.matrix()[None], T_b_c.matrix(),
                         float(inv_depth), float(td), obs_i.uv, obs_i.vel, obs_i.offset, uv_j,
                         obs_j.vel.reshape(1, 2), np.array([obs_j.offset]), model,
                         tangent_basis(uv_j))
    return p.r[0], single_blocks(p.J) + [p.J[:, -1:]]


def td_projection_factor(noise: gtsam.noiseModel.Base, keys: Sequence[int],
                         obs_i: TdObservation, obs_j: TdObservation, model: str = "pinhole",
                         health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """``gtsam.CustomFactor`` on keys ``(T_w_bi, T_w_bj, T_b_c, lambda, td)``."""
    check_model(model)
    keys = [int(k) for k in keys]
    if len(keys) != 5 or len(set(keys)) != 5:
        raise ValueError(f"td_projection_factor needs 5 distinct keys (Ti, Tj, Tbc, lambda, td), "
                         f"got {keys}")
    uv_j, vel_j = obs_j.uv.reshape(1, 2), obs_j.vel.reshape(1, 2)
    off_j = np.array([obs_j.offset])
    basis = tangent_basis(uv_j)

    def fn(args: list) -> tuple[np.ndarray, list[np.ndarray]]:
        Ti, Tj, Tc, lam, td = args
        p = td_project_batch(Ti.matrix(), Tj.matrix()[None], Tc.matrix(), lam[0], td[0],
                             obs_i.uv, obs_i.vel, obs_i.offset, uv_j, vel_j, off_j, model, basis)
        return p.r[0], single_blocks(p.J) + [p.J[:, -1:]]

    return custom_factor(noise, keys, ["pose3", "pose3", "pose3", 1, 1], fn, health)
