"""What the pipeline gives out: the online estimate at each frame (``FrameOutput``) and
how the estimator was initialized (``InitInfo``). Frames: ``T_w_b`` body in world."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.io.types import FeatureFrame
from vio.sync import FramePacket

__all__ = ["FrameOutput", "InitInfo"]


@dataclass(frozen=True)
class FrameOutput:
    """The online estimate at one frame (``T_w_b`` body in world, ``v_w`` m/s)."""

    index: int
    t_ns: int
    T_w_b: gtsam.Pose3
    v_w: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    keyframe: bool
    still: bool
    seconds: float
    n_features: int
    n_landmarks: int
    td_s: float
    T_b_c: gtsam.Pose3
    landmark_ids: np.ndarray | None = None
    landmarks_w: np.ndarray | None = None
    features: FeatureFrame | None = None
    packet: FramePacket | None = None


@dataclass(frozen=True)
class InitInfo:
    """How and when the estimator was initialized: ``method`` (stereo, static, dynamic),
    ``decided_s``: data seconds from the first frame to the decision (the latency
    before the first output), ``state_s``: from the first frame to the initial state
    (the first frame with a pose), ``td_s``: the camera-IMU offset remainder (s) a dynamic
    initialization found and aligned its window at (0: the sync layer's offset);
    ``scale_sigma``: the relative standard deviation of the metric scale a dynamic
    (monocular) initialization gave its window (None: a stereo baseline or a still start
    fixes the scale)."""

    method: str
    decided_s: float
    state_s: float
    td_s: float = 0.0
    scale_sigma: float | None = None
