"""What the estimator exchanges at each keyframe (``vio.backend.estimator.Estimator``):
its result, and the interface of the extra factor sources it drives."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import gtsam
import numpy as np


@dataclass(frozen=True)
class KeyframeResult:
    """Outcome of one keyframe update: the new state and some health figures."""

    k: int
    t_ns: int
    T_w_b: gtsam.Pose3
    v_w: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    n_landmarks: int
    n_removed: int
    recovered: bool


class FactorSource(Protocol):
    """Extra factors an ``Estimator`` adds at every keyframe next to its own landmark
    factors (e.g. the photometric points of ``vio.direct``), registered in
    ``Estimator.sources``. Each keyframe: ``observe`` gets the keyframe index and the
    pipeline's packet, then ``prepare_update`` appends factors/values/timestamps for
    keyframe ``k`` to ``g``/``v``/``stamps`` (``v`` already holds X(k), V(k), B(k) at
    the IMU prediction; ``leaving`` are the keyframes marginalized by this update) and
    returns smoother factor indices to remove; ``record_factor_indices`` receives the
    smoother indices of *all* new factors of the update (the source kept the positions
    ``g.size()`` of its own when adding them); ``remap_factor_indices`` maps them to new
    slots after a smoother rebuild (``vio.backend.smoother``). ``reset`` forgets all graph state after
    a solver restart. ``key_dims`` maps the key characters it uses to their dimensions
    (for the relinearization thresholds), ``key_thresholds`` those of its characters
    that have relinearization thresholds of their own (one per tangent dimension, in the
    variable's units; the others take ``SolverConfig.relinearize_threshold``). ``lost``
    (after keyframe ``k``'s update) names why the source's measurements have lost the
    frames, or returns None: a divergence for the health monitor. ``imu_contradicted``
    (after ``prepare_update`` of keyframe ``k``): whether the source's own alignment found
    the IMU prediction of the interval ending at ``k`` wrong; the estimator then bridges
    that interval (``vio.backend.bridge.replace_imu_factor``)."""

    key_dims: dict[str, int]
    key_thresholds: dict[str, tuple[float, ...]]

    def observe(self, k: int, frame: Any) -> None: ...

    def prepare_update(self, k: int, pred: gtsam.NavState, leaving: list[int],
                       g: gtsam.NonlinearFactorGraph, v: gtsam.Values, stamps: dict) -> list[int]: ...

    def record_factor_indices(self, indices: list[int]) -> None: ...

    def remap_factor_indices(self, remap: dict[int, int]) -> None: ...

    def reset(self) -> None: ...

    def lost(self, k: int) -> str | None: ...

    def imu_contradicted(self, k: int) -> bool: ...
