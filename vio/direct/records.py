"""What the photometric source reports besides its factors: TrackFrame's outcome at each
keyframe and the newest keyframe's points (``vio.direct.source.PhotometricSource``; the
Rerun sink draws the points, ``vio.viz``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackRecord:
    """TrackFrame at keyframe ``k``: level-0 ``rmse`` (intensity units), ``ok``, whether
    its pose was ``used`` as the initial guess, its distance to the IMU prediction
    (m, rad) and the wall time (ms)."""

    k: int
    t_ns: int
    rmse: float
    ok: bool
    used: bool
    dist_m: float
    angle_rad: float
    ms: float


@dataclass(frozen=True)
class PointSnapshot:
    """Points seen in the newest keyframe: ``uv`` (N, 2) normalized cam0 coordinates,
    ``rmse`` (N,) residual RMSE (intensity units) at the current estimate (stereo term
    for points hosted there, else the temporal term), ``hosted`` (N,) bool,
    ``inv_depth`` (N,) inverse depth (1/m) in that keyframe's cam0 at the estimate."""

    k: int
    t_ns: int
    uv: np.ndarray
    rmse: np.ndarray
    hosted: np.ndarray
    inv_depth: np.ndarray | None = None
