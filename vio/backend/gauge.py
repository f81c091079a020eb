"""The window's gauge: position and yaw held on the oldest keyframe of the fixed-lag window.

Visual-inertial odometry observes neither the position nor the yaw of the world frame
(four directions: the trajectory moved rigidly by ``[x, y, z]`` and turned about gravity
fits every IMU and visual factor alike). The start's priors fix them; once their
keyframe leaves the window, only the marginal factors carry them, through chains of
relative constraints whose uncertainty grows like odometry drift, and linearized at
points the estimate has since left. Nearly free directions with spurious gradients from
those stale linearizations: on generated MH_05 tracks from 12 s (td 5 ms), 49 s in, one
keyframe update turned and moved the whole window by 2.6 deg about gravity and 0.9 m
(the graph's error 430 -> 4454, the output jumping 3.4 m in the next frames), and the
run ended at ATE 1.09 m (0.073 m with this prior). Sliding-window estimators hold these directions on a window
pose (VINS-Mono fixes the first window pose's position and yaw); here a prior on the
oldest in-window keyframe at its current estimate, sigmas ``GaugeConfig.position_m`` and
``yaw_rad``, moved to the next oldest when that keyframe leaves (removed before its
keyframe is marginalized, so anchors do not pile up in the marginals). Roll and pitch
(gravity) are left to the IMU. Sigmas 0.1 m / 0.01 rad: 0.01 m / 0.001 rad moved the
real V1_01 tracks from 0.030 to 0.041 m (a tight anchor fights the position and yaw the
marginals still hold, linearized at other attitudes), 1 m / 0.1 rad left generated
MH_05@30 at 0.256 m (0.052 m at 0.1 / 0.01; figures in ``benchmarks/README.md``). Mono
mode holds the position at 0.05 m (``vio.modes``): there a keyframe update that took in
drifting KLT mistracks slid the whole window by up to 45 mm (stop 53).

The prior is a ``PriorFactorPose3`` with a full information matrix in the pose's
tangent ``[omega, v]`` (GTSAM: ``T Exp(xi)``, body frame): yaw about the world's z is
the body axis ``u = R_w_b^T e_z``, information ``u u^T / yaw_rad^2``; a body-frame
translation step ``v`` moves the position by ``R_w_b v``, so isotropic position
information is ``I / position_m^2`` in either frame. Roll and pitch get ``free_rad``
(an information floor that keeps the matrix positive definite).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

from vio.config import check_ranges


@dataclass(frozen=True)
class GaugeConfig:
    """``enabled``: hold the gauge on the oldest window keyframe (module docstring);
    ``position_m`` (m) and ``yaw_rad`` (rad): the prior's sigmas; ``free_rad``: the
    sigma of the roll / pitch floor."""

    enabled: bool = True
    position_m: float = 0.1
    yaw_rad: float = 0.01
    free_rad: float = 1e3

    def __post_init__(self) -> None:
        check_ranges(self, positive=("position_m", "yaw_rad", "free_rad"))


def gauge_prior(key: int, T_w_b: gtsam.Pose3, cfg: GaugeConfig) -> gtsam.PriorFactorPose3:
    """Prior on the position and the yaw (about world z) of pose ``key`` at ``T_w_b``."""
    u = T_w_b.rotation().matrix()[2, :]        # R^T e_z: world z in the body frame
    info = np.zeros((6, 6))
    info[:3, :3] = np.outer(u, u) / cfg.yaw_rad ** 2 + np.eye(3) / cfg.free_rad ** 2
    info[3:, 3:] = np.eye(3) / cfg.position_m ** 2
    return gtsam.PriorFactorPose3(key, T_w_b, gtsam.noiseModel.Gaussian.Information(info))


class GaugeAnchor:
    """The estimator's gauge prior: which keyframe holds it and its smoother slot."""

    def __init__(self, cfg: GaugeConfig) -> None:
        self.cfg = cfg
        self.k: int | None = None        # the anchored keyframe (None before the start)
        self.slot: int | None = None     # its prior's smoother slot (None: the start's priors)
        self._pos: int | None = None     # position of a new prior in this update's graph
        self.moves = 0

    def reset(self, k: int) -> None:
        """A (re)start at keyframe ``k``: its own priors hold the gauge."""
        self.k, self.slot, self._pos = k, None, None

    def prepare_update(self, keyframes: list[int], leaving: list[int],
                       pose_of: Callable[[int], gtsam.Pose3], key_of: Callable[[int], int],
                       g: gtsam.NonlinearFactorGraph) -> list[int]:
        """Before an update that marginalizes ``leaving`` (``keyframes``: all in the window,
        the new one included; ``pose_of(k)``: keyframe ``k``'s ``T_w_b`` estimate or
        prediction; ``key_of(k)``: its pose key): when the anchored keyframe leaves, its
        prior is removed (the returned slots) and a new one goes on the oldest remaining
        keyframe (the new keyframe never leaves, so one remains)."""
        self._pos = None
        if not self.cfg.enabled or self.k not in leaving:
            return []
        removals = [] if self.slot is None else [self.slot]
        self.k, self.slot = min(k for k in keyframes if k not in leaving), None
        self._pos = int(g.size())
        g.add(gauge_prior(key_of(self.k), pose_of(self.k), self.cfg))
        self.moves += 1
        return removals

    def record_factor_indices(self, indices: list[int]) -> None:
        if self._pos is not None:
            self.slot = int(indices[self._pos])
            self._pos = None

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        if self.slot is not None:
            self.slot = remap.get(self.slot)
