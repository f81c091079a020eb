"""Initialization parameters of the backend: static, dynamic (mid-flight) and stereo
initialization, and the camera-IMU time-offset search of a moving start. Re-exported
by ``vio.backend.config``, whose ``BackendConfig.init`` holds an ``InitConfig``."""

from __future__ import annotations

from dataclasses import dataclass, field

from vio.config import check_ranges


@dataclass(frozen=True)
class TdSearchConfig:
    """Search for the camera-IMU offset at a dynamic initialization
    (``vio.backend.td_init``). ``search_s``:
    half-width of the searched interval (s; 0 turns the search off), ``step_s`` its grid
    step; ``tol_deg``: a pair whose rotation residual exceeds it counts as an outlier;
    ``min_pairs``: fewest keyframe pairs with IMU over the whole interval; ``min_gain``,
    ``max_sigma_s``: when a found remainder is applied; a weaker one (cost drop at least
    ``try_gain`` residual variances) is tried when the alignment without it is refused,
    and kept if the alignment's checks pass. When the rotations see an offset (a
    candidate with at least ``try_gain``), the accepted window is re-aligned at the
    offset its visual-inertial batch prefers (``vio.backend.init_batch``): a walk of
    ``batch_step_s`` steps from the candidate, up to ``batch_range_s`` (``batch_step_s``
    0: off), applied when its sigma is within ``max_sigma_s`` and it moves the remainder by
    more than that sigma and ``batch_min_change_s``. The same walk, from the offset the
    window was aligned at, is given to an accepted window whose rotations' best offset has
    at least ``walk_gain`` (a weak hint: generated MH_05@80 at -15 ms, seed 83, -18.2 ms at
    gain 6.3, accepted at 0 and walked to -14.1 ms), and to a window refused for a
    batch-alignment disagreement before it waits, whatever the rotations saw (V2_03@29 at
    22 ms, seed 83: refused at the rotations' 25.6 ms, accepted at 22.0 ms).
    ``wide_tol_factor``: at each grid point the gyro bias is solved from the window's
    starting bias and again from a first solve at this many times ``tol_deg``, and the
    lower cost is kept: a starting bias fitted with the offset unmodelled can leave no
    pair within ``tol_deg`` near the true offset (generated V2_03@80 and V1_03@70 at -30 ms,
    seed 81: 0 inliers from -45 to -15 ms, the window waited for 2.0 s; with it -31.8 and
    -32.8 ms at 1.5 s). ``refused_try_gain`` (at most ``try_gain``): a window refused at the
    sync layer's offset is aligned at the rotations' best offset when its gain is at least
    this, and, accepted there, walked by the batch as a seen one (smooth rotation shows a
    true offset weakly: generated MH_04@65 at -30 ms, seed 81, best -26.6 ms at gain 3.8,
    refused at 0 for a velocity sigma of 1.8 m/s; accepted at 1.5 s instead of 2.0 s)."""

    search_s: float = 0.05
    step_s: float = 0.0025
    tol_deg: float = 1.5
    min_pairs: int = 8
    min_gain: float = 25.0
    max_sigma_s: float = 0.003
    try_gain: float = 9.0
    batch_step_s: float = 0.005
    batch_range_s: float = 0.03
    batch_min_change_s: float = 0.0005
    wide_tol_factor: float = 8.0
    refused_try_gain: float = 2.0
    walk_gain: float = 2.0

    def __post_init__(self) -> None:
        check_ranges(self, positive=("step_s",))
        if not self.wide_tol_factor >= 1.0:
            raise ValueError(f"TdSearchConfig.wide_tol_factor must be >= 1, got {self.wide_tol_factor}")
        if not 0.0 <= self.walk_gain <= self.try_gain:
            raise ValueError(f"TdSearchConfig.walk_gain must be within [0, try_gain = {self.try_gain}], "
                             f"got {self.walk_gain}")
        if not 0.0 <= self.refused_try_gain <= self.try_gain:
            raise ValueError(f"TdSearchConfig.refused_try_gain must be within [0, try_gain = {self.try_gain}], "
                             f"got {self.refused_try_gain}")


@dataclass(frozen=True)
class DynamicInitConfig:
    """Dynamic initialization (visual-inertial alignment, ``vio.backend.dynamic_init``)
    on ``window_s`` of keyframes every ``step_s``, using the ``max_tracks`` longest
    tracks; a refused window grows by ``retry_s`` per attempt up to ``max_window_s``
    (excitation accumulates), then slides. Its inverse depths are bounded to ``[1/max_depth_m, 10]`` 1/m (the bound
    makes a window without parallax reveal a wrong velocity), its gyro bias has a prior of
    ``visual_gyro_bias_sigma`` rad/s about the bias that aligns the IMU with the visual
    rotations between keyframes (``vio.backend.gyro_init``) when at least
    ``min_rotation_pairs`` keyframe pairs give one, else of ``gyro_bias_sigma``
    about zero; its reprojection errors have a Huber kernel at ``huber_px``.
    A solution is rejected (the pipeline waits for a later window) with fewer than
    ``min_landmarks`` tracks, a free-gravity norm off by more than ``max_gravity_error``
    (relative), fewer than ``min_inlier_ratio`` inlier observations, a median inlier
    reprojection error above ``max_reproj_px``, a velocity standard deviation above
    ``max_v0_sigma`` m/s, an acceleration varying by less than ``min_excitation`` m/s^2
    RMS (no scale) unless the window is still (rotation alone explains the tracks within
    ``max_still_parallax_px`` and ``|v0| <= max_v0_sigma``), a batch mean factor error
    above ``max_mean_error``, or a batch solution further than ``disagreement_widen``
    times ``max_v0_disagreement`` m/s / ``max_gravity_disagreement_deg`` from the
    alignment (between one and ``disagreement_widen`` times, the window is accepted with
    the disagreement as its roll-pitch and velocity prior sigmas. Generated MH_05 tracks
    from 40 s into the flight disagree by 0.145 m/s and 1.8 degrees at 1.5 s, each
    solution about 0.9 degrees from the true gravity: the accelerometer bias (0.14 m/s^2)
    and the tilt are not yet separable. With 2.0 (``bench_midflight``, 25 excerpts) that
    window is accepted at 1.5 s instead of 2.0 s (ATE 0.0523 -> 0.0533 m over 31.6 m),
    MH_03@30 at 1.5 instead of 2.5 s (0.0305 -> 0.0311 m), V2_03@30 at 1.5 instead of
    2.0 s (0.0155 -> 0.0161 m); the other 22 and seven real MH_05 mono starts unchanged.
    With an earlier backend, accepting MH_05@40 at 1.5 s had cost 0.095 -> 0.116 m), or a relative standard
    deviation of the batch window's translation (its metric scale) above
    ``max_scale_sigma`` (unless the translation is within 3 sigma of zero)."""

    window_s: float = 1.5
    max_window_s: float = 3.0
    retry_s: float = 0.5
    step_s: float = 0.1
    max_tracks: int = 80
    min_landmarks: int = 15
    max_depth_m: float = 30.0
    gyro_bias_sigma: float = 0.1
    huber_px: float = 2.0
    max_gravity_error: float = 0.03
    min_inlier_ratio: float = 0.8
    max_reproj_px: float = 2.5
    max_v0_sigma: float = 0.1
    min_excitation: float = 0.1
    max_still_parallax_px: float = 4.0
    max_mean_error: float = 20.0
    max_v0_disagreement: float = 0.15
    max_gravity_disagreement_deg: float = 1.5
    disagreement_widen: float = 2.0
    max_scale_sigma: float = 0.2
    visual_gyro_bias_sigma: float = 0.01
    min_rotation_pairs: int = 3
    td: TdSearchConfig = field(default_factory=TdSearchConfig)

    def __post_init__(self) -> None:
        check_ranges(self, positive=("window_s", "max_window_s", "step_s", "retry_s", "max_tracks", "huber_px",
                                     "max_reproj_px", "max_depth_m"), fractions=("min_inlier_ratio",))


@dataclass(frozen=True)
class StereoInitConfig:
    """Stereo-inertial initialization (``vio.backend.stereo_init``), used first whenever
    cam1 is present. ``window_s``: frames aligned (every frame, from the first stereo
    pair); a rejected window grows up to ``max_window_s``, after which its oldest frames
    are dropped. PnP: inlier threshold ``pnp_px``, at least ``min_inliers`` inliers per
    frame and ``min_points`` stereo points in the first frame. The linear alignment
    weights positions by ``pos_sigma_m`` (m) and velocity increments by ``accel_sigma``
    (m/s^2, the unknown accelerometer bias) times the interval; it is rejected with a
    gravity norm off by more than ``max_gravity_error`` (relative), a gravity direction
    sigma above ``max_gravity_sigma_deg`` or a first-velocity sigma above
    ``max_v0_sigma`` (m/s). The smoother's initial priors are twice the alignment's
    sigmas, at least ``min_rp_sigma`` (rad) and ``min_vel_sigma`` (m/s)."""

    enabled: bool = True
    window_s: float = 0.5
    max_window_s: float = 2.0
    pnp_px: float = 2.0
    min_inliers: int = 12
    min_points: int = 20
    pos_sigma_m: float = 0.002
    accel_sigma: float = 0.1
    max_gravity_error: float = 0.05
    max_gravity_sigma_deg: float = 1.5
    max_v0_sigma: float = 0.1
    min_rp_sigma: float = 0.01
    min_vel_sigma: float = 0.05

    def __post_init__(self) -> None:
        check_ranges(self, positive=("window_s", "max_window_s", "pnp_px", "pos_sigma_m", "accel_sigma",
                                     "min_rp_sigma", "min_vel_sigma"))


@dataclass(frozen=True)
class InitConfig:
    """Initialization. Static: the first ``static_window_s`` of IMU must be still
    (50-ms mean gyro within ``max_gyro_std`` rad/s and accel within ``max_accel_std``
    m/s^2 of the window mean, and the median feature displacement over the window below
    ``max_still_flow_px``: a motionless camera's tracks still move by their noise, a median
    of about 1.7 pixel sigmas (1.1-1.5 px on the 0.7-px generated tracks, where the old 1-px
    mean never detected the Machine Hall's still start). Otherwise
    dynamic initialization (``dynamic``, see ``DynamicInitConfig``). With cam1, the
    stereo initialization (``stereo``, ``StereoInitConfig``) comes first. ``prior_*``: the
    initial state's priors (position and yaw fix the gauge); ``zupt_sigma`` (m/s):
    zero-velocity updates while still."""

    static_window_s: float = 0.5
    max_gyro_std: float = 0.05
    max_accel_std: float = 0.6
    max_still_flow_px: float = 2.0
    dynamic: DynamicInitConfig = field(default_factory=DynamicInitConfig)
    stereo: StereoInitConfig = field(default_factory=StereoInitConfig)
    prior_pos_sigma: float = 1e-3
    prior_yaw_sigma: float = 1e-3
    prior_rp_sigma: float = 0.02
    prior_vel_sigma: float = 0.05
    prior_gyro_bias_sigma: float = 0.01
    prior_accel_bias_sigma: float = 0.2
    zupt_sigma: float = 0.01

    def __post_init__(self) -> None:
        check_ranges(self, positive=("static_window_s", "prior_pos_sigma", "prior_yaw_sigma", "prior_rp_sigma",
                                     "prior_vel_sigma", "prior_gyro_bias_sigma", "prior_accel_bias_sigma",
                                     "zupt_sigma"))
