"""Configuration and result of the feature-track generator (``vio.sim.tracks``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class TrackGenConfig:
    """Generator settings. Times in seconds, distances in metres, noise in pixels.

    ``start_s`` is measured from the first ground-truth row; ``duration_s=None``
    runs to the end. ``td_s``: true exposure = stamp + td (may be negative).
    ``outlier_rate``: fraction of observations displaced by ``outlier_px`` or
    (``swap_fraction`` of them) swapped in pairs within a frame. Image bounds use
    the pinhole intrinsics (the undistorted image), not the wider distorted one.
    Track lifetimes: ``persistent_fraction`` of new tracks are kept until their point
    leaves the view, the others are lost after a geometric number of frames (mean
    ``mean_track_len``), like a KLT tracker that drops weak features early and keeps good
    ones. Calibrated on the first 30 s of V1_01 against the real EqVIO KLT tracks shipped
    with it: median length 15 frames for both, mean 34 (real 43), a typical observation's
    track 92 frames long (real 124); purely geometric lifetimes gave 8, 12 and 23.
    ``imu_consistent``: render from (and write as ground truth) the source ground
    truth smoothed against the real IMU (:mod:`vio.sim.fuse`, priors ``gt_pos_sigma_m``,
    ``gt_rot_sigma_rad``; the IMU with its sensor.yaml densities times
    ``gt_imu_noise_scale``, 1 = the datasheet) instead of the raw ground truth, whose time
    shift (up to about 1 ms) and jitter against the gyro a real camera would not see.
    ``gt_priors``: which of that smoothing's nodes (the frame stamps, where the estimator
    reports while its td is still off, and the exposure times, stamp + td, where the
    tracks are rendered; both written as ground-truth rows) hold a ground-truth pose
    prior: ``"exposure"`` (those only; the stamps follow from the IMU) or
    ``"stamp_and_exposure"`` (the earlier generator: with td != 0 twice the priors, so
    twice the pull towards the raw ground truth's errors, and a td != 0 excerpt was
    harder than its td = 0 twin, whose two node sets coincide. Issue 20, ours on
    MH_03@1+60s, true td given by the sync layer: +25 ms 0.0575 m against the twin's
    0.0337 m; with the exposure nodes alone 0.0313 m; the random-pick variant 0.049 ->
    0.0299 m, its twin 0.024 m).
    ``selection``: how new tracks are picked among the visible candidates, ``"grid"`` (one
    per free image cell first, like a detector with non-maximum suppression) or
    ``"random"`` (uniform over the visible points). ``pose_interp`` (raw ground truth
    only): ``"slerp"`` (position linear, rotation slerp between the bracketing rows) or
    ``"nearest"`` (the nearest row, as a cruder generator might). ``vio.sim.variants``
    names whole other generators built from these settings (``vio tracks --variant``).
    """

    start_s: float = 0.0
    duration_s: float | None = None
    rate_hz: float = 20.0
    td_s: float = 0.005
    seed: int = 0
    noise_px: float = 0.7
    outlier_rate: float = 0.015
    outlier_px: tuple[float, float] = (10.0, 50.0)
    swap_fraction: float = 0.3
    max_features: int = 40
    grid: tuple[int, int] = (8, 5)
    mean_track_len: float = 15.0
    persistent_fraction: float = 0.5
    redetect_cooldown: int = 5
    margin_xy_m: float = 1.5
    floor_margin_m: float = 0.3
    ceiling_margin_m: float = 1.0
    points_per_m2: float = 8.0
    max_points: int = 30000
    n_clutter_boxes: int = 4
    clutter_points_per_m2: float = 30.0
    min_depth_m: float = 0.2
    max_range_m: float = 15.0
    max_incidence_deg: float = 75.0
    border_px: float = 1.0
    imu_margin_s: float = 0.1
    imu_consistent: bool = True
    gt_pos_sigma_m: float = 0.002
    gt_rot_sigma_rad: float = 0.005
    gt_imu_noise_scale: float = 1.0
    gt_priors: Literal["exposure", "stamp_and_exposure"] = "exposure"
    selection: Literal["grid", "random"] = "grid"
    pose_interp: Literal["slerp", "nearest"] = "slerp"

    def __post_init__(self) -> None:
        checks = {
            "start_s >= 0": self.start_s >= 0, "rate_hz > 0": self.rate_hz > 0,
            "duration_s > 0": self.duration_s is None or self.duration_s > 0,
            "noise_px >= 0": self.noise_px >= 0, "0 <= outlier_rate < 0.5": 0 <= self.outlier_rate < 0.5,
            "0 < outlier_px[0] <= outlier_px[1]": 0 < self.outlier_px[0] <= self.outlier_px[1],
            "0 <= swap_fraction <= 1": 0 <= self.swap_fraction <= 1,
            "max_features >= 1": self.max_features >= 1, "grid >= 1": min(self.grid) >= 1,
            "mean_track_len >= 1": self.mean_track_len >= 1,
            "0 <= persistent_fraction <= 1": 0 <= self.persistent_fraction <= 1,
            "redetect_cooldown >= 0": self.redetect_cooldown >= 0,
            "points_per_m2 > 0": self.points_per_m2 > 0, "max_points >= 1": self.max_points >= 1,
            "n_clutter_boxes >= 0": self.n_clutter_boxes >= 0,
            "0 < min_depth_m < max_range_m": 0 < self.min_depth_m < self.max_range_m,
            "0 < max_incidence_deg <= 90": 0 < self.max_incidence_deg <= 90,
            "gt sigmas > 0": self.gt_pos_sigma_m > 0 and self.gt_rot_sigma_rad > 0,
            "gt_imu_noise_scale > 0": self.gt_imu_noise_scale > 0,
            "selection in (grid, random)": self.selection in ("grid", "random"),
            "pose_interp in (slerp, nearest)": self.pose_interp in ("slerp", "nearest"),
            "gt_priors in (exposure, stamp_and_exposure)": self.gt_priors in ("exposure", "stamp_and_exposure"),
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"TrackGenConfig: need {', '.join(bad)}")


@dataclass(frozen=True)
class TrackGenResult:
    """What was written. ``t_ns`` (F,) camera stamps; observations (M,): ``frame_idx``,
    ``landmark_id``, ``uv`` as written and ``uv_true`` (noise-free projection of the
    id's own point at stamp + td), ``outlier_kind`` (0 inlier, 1 displaced, 2 swapped);
    ``landmark_ids`` (K,) with world points ``landmark_p_w`` (K, 3) m; ``n_visible`` (F,)
    visible candidates per frame; ``n_points`` physical points in the room."""

    out: Path
    t_ns: np.ndarray
    td_ns: int
    frame_idx: np.ndarray
    landmark_id: np.ndarray
    uv: np.ndarray
    uv_true: np.ndarray
    outlier_kind: np.ndarray
    landmark_ids: np.ndarray
    landmark_p_w: np.ndarray
    n_visible: np.ndarray
    n_points: int

    @property
    def features_per_frame(self) -> np.ndarray:
        return np.bincount(self.frame_idx, minlength=len(self.t_ns))

    @property
    def track_lengths(self) -> np.ndarray:
        """Observations per landmark id (K,)."""
        return np.unique(self.landmark_id, return_counts=True)[1]
