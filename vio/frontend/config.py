"""Parameters of the image front end (KLT tracking + stereo matching)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from vio.config import check_ranges


@dataclass(frozen=True)
class FrontendConfig:
    """Front-end parameters; load with ``vio.config.from_dict(FrontendConfig, d)``.

    Pixel thresholds are in distorted-image pixels unless noted. Thresholds that act on
    the normalized plane (RANSAC, epipolar) are given in pixels and divided by the
    camera's fx internally (VINS' virtual-focal convention).
    """

    # detection (Shi-Tomasi, cv2.goodFeaturesToTrack)
    max_features: int = 150
    min_dist_px: int = 30           # radius of the mask circle around each track
    quality_level: float = 0.01
    block_size: int = 3
    border_px: int = 2              # tracks closer than this to the edge are dropped
    # detect only when at least min(this, half the target count) tracks are missing (as
    # OpenVINS' TrackKLT, which uses 20); between detections the surviving tracks age.
    # 1 / 10 / 20 on the rolling-shutter render (seed 12): td 10.11 / 9.82 / 9.46 ms for 10
    # ms; real MH_01 stereo 6.6 / 6.3 / 6.7 mm at 17.4 / 16.6 / 17.1 s of CPU
    detect_min_missing: int = 10
    # tracks older than this many frames are ended (their places detected again, under new
    # ids); 0: never. An LK track's position leaves its first observation's point as the view
    # changes: against the rendered scene (sharp V2_02 flight, 300 frames) the median error
    # is 0.10 px one frame on, 0.54 px at 8-15 frames, 0.92 px at 32-63, 1.37 px beyond,
    # the same when each track is re-tracked from its first image, so it is the view, not
    # chained LK steps. The backend reads each observation as independent 1-px noise. On
    # for stereo (vio.modes), whose pairs give depth at every keyframe; mono needs the
    # parallax of long tracks (real MH_05 mono at 40 frames: 47.8 -> 100 mm)
    max_track_len: int = 0
    # each track's position aligned, every frame, to the patch of its first observation by
    # an affine warp with gain and offset (vio.frontend.anchor), starting at LK's answer; an
    # alignment that fails (leaves the image, no convergence, more than anchor_max_shift_px
    # from LK, zero-mean NCC below anchor_min_zncc) keeps LK's position and anchors anew there
    anchor: bool = False
    anchor_patch: int = 15          # template side, px (odd)
    anchor_max_iter: int = 10
    anchor_max_shift_px: float = 2.0
    anchor_min_zncc: float = 0.8
    # pyramidal Lucas-Kanade
    lk_window: int = 21
    lk_levels: int = 3              # extra pyramid levels above full resolution
    lk_max_iter: int = 30
    lk_eps: float = 0.01
    fb_check: bool = True
    fb_threshold_px: float = 0.5    # forward-backward round-trip error
    # pyramid levels of the backward pass, which starts at the origin (VINS-Fusion: 1).
    # Real MH_01 stereo, all (3) -> 1 / 0: LK 8.9 -> 7.4 / 6.0 ms a frame; 0 lets drifting
    # tracks through on renders with exposure changes (seed 14: 10 -> 17 mm; 1: 10.5 mm)
    lk_back_levels: int = 1
    # LK assumes brightness constancy, which a camera's exposure control breaks: where the
    # grey levels of the tracked points' 7x7 windows say the frame's brightness changed by
    # at least lk_brightness_min grey levels at mid-grey (an affine fit, b = g a + o), the
    # pair is brought to one brightness and LK runs again from the first pass's result
    # (vio.frontend.tracker.brightness_matched). Renders with exposure changes (vio sim
    # --exposure smooth, stereo): td error 2.04 / 0.58 -> 0.26 / 0.02 ms on seeds 201 / 202,
    # sim14 6 stretches 7.15 -> 5.70 mm; real MH_01 stereo, 22 stretches, 5.47 -> 5.32 mm
    # (benchmarks/README.md, stop 58).
    lk_brightness: bool = True
    lk_brightness_min: float = 1.0
    # geometric outlier rejection between consecutive frames
    ransac: bool = True
    ransac_model: Literal["fundamental", "essential"] = "fundamental"
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.99
    # the tone curve applied before tracking and detection (``vio.frontend.tracker.Preprocess``):
    # "sqrt": a fixed square-root curve (the variance-stabilising transform of shot noise:
    # every grey level gets the same noise, dark regions their share of contrast); "clahe":
    # VINS-Fusion's EuRoC setting (equalize: 1), a curve fitted to each tile's histogram,
    # so a patch's grey levels change as the scene moves through the grid, which LK reads
    # as motion; "none": the raw image. Measured in benchmarks/README.md (the tone curve).
    contrast: Literal["sqrt", "clahe", "none"] = "sqrt"
    clahe_clip: float = 3.0
    clahe_tiles: int = 8
    # stereo matching cam0 -> cam1
    stereo: bool = True
    stereo_init_depth_m: float = 3.0   # rough depth for the first LK guess in cam1
    # a track without a depth of its own starts at the median of its nearest matched
    # tracks' (0: at stereo_init_depth_m). Real MH_01 stereo, 0 -> 3: 35 -> 56 % matched
    stereo_guess_neighbours: int = 3
    stereo_lk_levels: int = 2          # the guess is close: fewer levels, fewer ambiguities
    stereo_gain_compensation: bool = True  # scale cam1 to cam0's mean brightness
    stereo_fb_threshold_px: float = 1.0
    # the stereo match's backward pass (as lk_back_levels): 0 costs nothing in accuracy
    # there (render seed 14: 10.3 mm with the temporal pass at 3, 10.5 mm at 1)
    stereo_back_levels: int = 0
    # LK iterations per level of the stereo match: a good start converges in a few, a
    # point that is not in cam1 runs to the limit. Real MH_01 stereo, 30 -> 10: stereo
    # and temporal LK 6.71 -> 5.92 ms a frame, 60.3 -> 60.0 % matched
    stereo_lk_max_iter: int = 10
    stereo_epipolar_px: float = 1.5    # max distance to the epipolar line
    min_depth_m: float = 0.1           # closer triangulations reject the match
    max_depth_m: float = 100.0         # farther ones keep the match, depth NaN
    # where cam1 is decoded and matched: at every frame, or ("keyframe") only at the frames
    # the image stage's keyframe policy chooses (``vio.keyframes``; the pipeline then takes
    # those as its keyframes, the backend uses cam1 at keyframes alone) and at every frame
    # of the stereo initialization's window; the default of stereo and hybrid (``vio.modes``),
    # ignored by direct mode (its KLT runs only until it is initialized)
    stereo_at: Literal["frame", "keyframe"] = "frame"
    # concurrency (vio.overlap): track in a worker process while the backend solves;
    # the output is identical either way, only the wall time changes
    worker_process: bool = True
    # the worker's nice value (0-19; same output at any). 19 lets the backend preempt the
    # worker on an idle machine (stop 52's Xeon, real MH_01 stereo / hybrid / MH_05 mono, 0
    # -> 19: 2.79 -> 2.81x / 1.9 -> 2.06x / 3.7 -> 3.8x real time, backend p95 52 -> 32 / 92
    # -> 75 / 43 -> 39 ms) but starves it behind any other load of the same session or
    # cgroup (a launch file's other nodes): real MH_01 stereo beside two busy processes, 19 /
    # 10 / 5 / 2 / 0: 0.1 / 0.4 / 0.9 / 1.6 / 2.2x real time over the loop; `--live` took
    # 236 s for 16 s of data. Idle at 0 (2.6-GHz Xeon VM, stop 70, 3 alternated runs): MH_01 stereo
    # wall 5.30 -> 5.06 s, p95 20.1 -> 22.7 ms, max 26 -> 30 ms; MH_05 mono p95 38 ms both
    worker_nice: int = 0
    # a cam0 image whose intensities' standard deviation (gray levels, every 4th pixel of
    # every 4th row) is below this shows nothing (black, saturated, the lens covered): its
    # frame is dropped as an undecodable one is (``vio.tracking.blank_image``; real EuRoC
    # frames 53-83); 0: never
    min_image_std: float = 4.0

    def __post_init__(self) -> None:
        positive = ("max_features", "detect_min_missing", "min_dist_px", "lk_window", "lk_max_iter",
                "stereo_lk_max_iter", "block_size", "anchor_max_iter", "anchor_max_shift_px",
                    "fb_threshold_px", "ransac_threshold_px", "clahe_clip", "clahe_tiles",
                    "stereo_init_depth_m", "stereo_fb_threshold_px", "stereo_epipolar_px",
                    "min_depth_m", "max_depth_m", "quality_level", "lk_eps")
        check_ranges(self, positive=positive)   # and every other number >= 0 (the levels, border_px, ...)
        if self.anchor_patch < 5 or self.anchor_patch % 2 == 0:
            raise ValueError(f"FrontendConfig.anchor_patch must be odd and >= 5, got {self.anchor_patch}")
        if not 0.0 <= self.anchor_min_zncc <= 1.0:
            raise ValueError(f"FrontendConfig.anchor_min_zncc must be in [0, 1], got {self.anchor_min_zncc}")
        if self.lk_window < 5:
            raise ValueError(f"FrontendConfig.lk_window must be >= 5, got {self.lk_window}")
        if not 0.0 < self.ransac_confidence < 1.0:
            raise ValueError("FrontendConfig.ransac_confidence must be in (0, 1)")
        if not 0 <= self.worker_nice <= 19:
            raise ValueError(f"FrontendConfig.worker_nice must be in 0..19, got {self.worker_nice}")
        if self.contrast not in ("sqrt", "clahe", "none"):
            raise ValueError(f"FrontendConfig.contrast must be 'sqrt', 'clahe' or 'none', got {self.contrast!r}")
        if self.stereo_at not in ("frame", "keyframe"):
            raise ValueError(f"FrontendConfig.stereo_at must be 'frame' or 'keyframe', got {self.stereo_at!r}")
        if self.max_depth_m <= self.min_depth_m:
            raise ValueError("FrontendConfig.max_depth_m must exceed min_depth_m")
