"""Backend configuration (one frozen dataclass per concern, loadable from YAML)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from vio.backend.gauge import GaugeConfig
from vio.backend.health import BridgeConfig, HealthConfig, RealignConfig
from vio.backend.init_config import (DynamicInitConfig, InitConfig,  # noqa: F401 - re-exported
                                     StereoInitConfig, TdSearchConfig)
from vio.backend.scale_refine import RefineConfig
from vio.config import check_ranges
from vio.imu import ImuNoiseConfig


@dataclass(frozen=True)
class KeyframeConfig:
    """Keyframe policy: a frame becomes a keyframe when the mean feature parallax
    since the last keyframe reaches ``min_parallax_px``, when ``max_interval_s``
    has elapsed, or when fewer than ``min_tracked`` features remain tracked."""

    min_parallax_px: float = 20.0
    max_interval_s: float = 0.25
    min_interval_s: float = 0.0
    min_tracked: int = 12

    def __post_init__(self) -> None:
        check_ranges(self, positive=("max_interval_s",))


@dataclass(frozen=True)
class VisionConfig:
    """Visual factors. ``pixel_sigma`` is converted to normalized units with fx.
    ``td_velocity``: image velocities multiplying td in the td factor, "predicted"
    from the state (velocity, gyro, depth) or "measured" by the front end; an
    observation whose prediction is further than ``td_velocity_gate`` (1/s) from the
    measurement (a wrong depth or a mistrack) gets no td term, and so does one whose
    velocity exceeds ``td_velocity_max`` (1/s; 20/s is ~460 px per frame at EuRoC's
    20 Hz, beyond any real track): one such observation would otherwise dominate the
    td estimate. A tighter cap costs td: 3/s (~70 px per frame) dropped the td terms of
    correctly predicted fast observations and left MH_05 at 4.03 ms for a true 5 ms
    (4.16 ms without it). ``max_landmarks``: cap on landmarks in the window
    (new tracks wait while it is reached; Python factor callbacks dominate the cost).
    ``kernel``: robust kernel per observation, ``kernel_k`` its threshold in sigmas: at
    1.345 (95% Gaussian efficiency) Huber down-weighted the fast-moving observations that
    carry td and left td 0.2-0.6 ms short on 7 of the 8 generated excerpts; at 3 every
    excerpt is within 0.2 ms, and outliers (10-50 px) stay down-weighted. ``outlier_px``:
    landmarks whose worst reprojection error exceeds it after an update are dropped and
    restarted from the front end's next observation; an id dropped ``max_rejections``
    times is ignored for good. ``outlier_obs`` (world points, ``reanchor = "point"``): a point
    whose error past the limit is isolated (one observation; at least three others agree
    within ``outlier_obs_agree`` times the limit; at most half of the window's points
    flagged) loses only that observation and is retired (its factor rebuilt from the
    others; it takes no new observation, and its id starts a new track once it has left
    the window), as ORB-SLAM3's local bundle adjustment drops outlier edges
    (``vio.backend.point_outliers``); points whose errors are spread are dropped whole.
    Measured against dropping every flagged point whole: real MH_05 mono from 17 starts
    63.95 -> 59.32 mm; real V1_01 tracks 0.0241 -> 0.0191 m (figures of the other data
    in ``benchmarks/README.md``, "Stop 47"). Trimming any observation past the limit
    while two stay (spread errors included) lost on real MH_05 (73.8 mm); not retiring
    the point let a drifting KLT track's later observations into it (real MH_05 61.17 mm,
    V1_01 0.0225 m). ``anchor_noise``: the inverse-depth factors take a
    landmark's anchor observation as its exact ray; with this on, each factor whitens its
    residuals with the anchor's pixel noise marginalized (``factors.anchor_noise.
    anchor_whitening``, at the estimate when the factor is built), so the anchor's error is
    not counted once per target observation: on the generated excerpts geometric-mean ATE
    0.128% -> 0.078% (3 runs over 0.2% without it, none with it); on the real V1_01 KLT
    tracks 0.027 (off) vs 0.028 m (on).
    ``marginalize_reanchored``: when a live landmark's anchor leaves the window, its
    observations in the leaving keyframes become a farewell factor of its new key and a
    depth-transfer factor (relative depth sigma ``reanchor_sigma``) ties the old key to the
    new one, both marginalized with those keyframes; off, they are dropped, which on long
    tracks keeps only the window's last 2.5 s of each track.
    ``reanchor``: what a triangulated monocular track becomes, ``"anchor"`` (the VINS-Mono
    inverse depth on its first observation's ray, re-anchored when that keyframe leaves)
    or ``"point"`` (a world point with every observation an ordinary measurement,
    ``vio.backend.point_tracks``; a low-parallax entry gets an isotropic prior of
    ``point_prior_sigma_m``). Measured (generated tracks, real IMU): the anchored
    trajectory comes out 0.5-2% short where a GTSAM-native ``Point3`` pipeline and the
    world points do not (``bench_midflight``: MH_04@40 0.378 -> 0.235%, MH_05@40 0.312 ->
    0.165%); real V1_01 features 0.0267 / 0.0266 m; real MH_05 mono starts at frames
    0-150 mean 0.127 (anchor) / 0.135 m (point), each single run chaotic at +-50%.
    ``eliminate_depth``: landmarks keep their inverse depth inside the factor instead of
    as a graph variable: one factor per anchor keyframe over all landmarks anchored there,
    depths Schur-eliminated at each linearization (``vio.backend.bundles``,
    ``factors.landmark_schur``), refined at the estimate after each update and by
    ``depth_iters`` Gauss-Newton steps inside each linearization; ``farewell_poses`` /
    ``reanchor_depth_prior``: what a re-anchored landmark's leaving observations pass on
    (pose information through the final factor / a depth prior; see the module);
    ``reanchor_prior_sigma`` > 0 carries the depth prior over from one re-anchoring to the
    next, with this relative depth sigma added at each (the prior holds the leaving poses
    fixed, so carried over unbounded it grows overconfident: real V1_01 0.025 -> 0.064 m).
    Measured (real V1_01 features / MH_05 mono ATE, m): 0 (default, not carried) 0.025 /
    0.191; 0.05: 0.037 / 0.119; 0.1: 0.043 / 0.113; 0.2: 0.030 / 0.126 (variable mode
    0.027 / 0.130; single runs, so differences of ~20 % are within run-to-run spread of
    configurations)."""

    model: Literal["pinhole", "sphere"] = "pinhole"
    use_td: bool = True
    td_velocity: Literal["predicted", "measured"] = "predicted"
    td_velocity_gate: float = 5.0
    td_velocity_max: float = 20.0
    pixel_sigma: float = 1.0
    kernel: Literal["huber", "cauchy", "none"] = "huber"
    kernel_k: float = 3.0
    outlier_px: float = 6.0
    max_rejections: int = 3
    outlier_obs: bool = True
    outlier_obs_agree: float = 0.5
    anchor_noise: bool = True
    marginalize_reanchored: bool = True
    reanchor: Literal["anchor", "point"] = "anchor"
    point_prior_sigma_m: float = 20.0
    reanchor_sigma: float = 1e-4
    min_parallax_deg: float = 1.0
    max_wait_keyframes: int = 6
    default_depth_m: float = 5.0
    max_stereo_depth_m: float = 20.0
    max_landmarks: int = 120
    min_depth_m: float = 0.1
    max_depth_m: float = 100.0
    eliminate_depth: bool = False
    depth_iters: int = 0
    reanchor_depth_prior: bool = True
    reanchor_prior_sigma: float = 0.0
    farewell_poses: bool = True

    def __post_init__(self) -> None:
        check_ranges(self, positive=("pixel_sigma", "kernel_k", "outlier_px", "td_velocity_max", "max_landmarks",
                                     "min_depth_m", "max_depth_m", "default_depth_m", "max_stereo_depth_m",
                                     "max_rejections", "point_prior_sigma_m", "reanchor_sigma"),
                     fractions=("outlier_obs_agree",))
        if not self.max_depth_m > self.min_depth_m:
            raise ValueError("VisionConfig.max_depth_m must exceed min_depth_m")


@dataclass(frozen=True)
class CalibConfig:
    """Online calibration. When off, extrinsic and td are held by tight priors.

    ``td_feedback_s``: once the td estimate differs from the offset the sync layer applies
    by at least this much (s), the sync layer applies the estimate to the following frames
    (at most ``td_feedback_step_s`` per frame, and only from ``td_feedback_after_s`` of
    camera time after initialization on: the first seconds' estimate swings by up to
    15 ms, and following it cost the real V1_01 tracks 0.027 -> 0.031 m), so the td
    variable's factors only ever model a small remainder; 0 turns it off (the sync layer
    keeps the initial ``--td``).
    The td factor shifts each observation along a velocity predicted from the state, and
    the noise in that prediction (depth, velocity, gyro vibration) attenuates the offset
    the factors measure towards no shift, like any regressor with errors in its variables;
    the feedback puts the no-shift point at the estimate (VINS-Mono feeds its td into the
    feature stamps the same way), and keyframe states then sit at the estimated exposure
    times. Measured on the MH_03 excerpt at takeoff (our generator, true +25 ms): ATE
    0.186 -> 0.054 m (its td = 0 twin: 0.028 m), td 24.21 -> 24.36 ms; the same tracks
    synced at the true offset from the start give 24.91 ms and an excerpt starting in
    flight (30 s) 24.87 ms without feedback: what remains is learnt on the ground and at
    takeoff with the offset still unknown, before any feedback, and kept in the window's
    marginal (starting the feedback after 3 s instead of 10 s changes nothing). Steps of
    1 ms per frame rather than 5: boxwall MH_03 (seed 300) true +25 ms ATE 0.658 -> 0.222 m
    (0.261 m without feedback), our generator's 0.054 -> 0.051 m.

    ``td_feedback_at_init``: the sync layer takes the initialization's td at once (a dynamic
    initialization's search, ``vio.backend.td_init``, found 20.3-30.3 ms for a true 25 on
    hand-held starts), then follows the estimate as above; the first window and seconds
    were otherwise spent with the whole offset left to the td factor's velocity shifts (the
    generator variants at true 25 ms were 1.2-1.9x their td = 0 twins, 1.08x with the sync
    layer at the truth from the start). Both feature tables (``benchmarks/bench_configs.py
    --sets variants,features``, 48 runs): twins within 1.25x 18 -> 21 of 25 (variants 11 ->
    14 of 17; far-walls 1.86 -> 1.04x, raw-gt-nearest 1.28 -> 1.04x; still out: outliers
    1.69x, boxwall MH_03 at 12 / 25 ms 1.60 / 1.45x), geometric-mean ATE 0.0405 -> 0.0391 m,
    under 0.2 % of the path 41 -> 42 of 48, td within 0.5 ms 46 of 47 either way; still
    starts (static initialization: no search) unchanged, real V1_01 tracks 0.0191 m.

    ``td_reanchor_s``: once the sync layer applies this much more of the fed-back td than at
    the window's last (re)start, and td is known to ``td_reanchor_sigma_s`` (1 sigma), the
    window restarts once at the current state and td (``vio.backend.td_reanchor``;
    landmarks re-triangulated, td prior ``td_sigma`` again): the td information the window's
    marginal carries was gathered while the remainder left to the td variable was large, and
    there the regressor's noise attenuates it (``CalibConfig`` above); it never washes out,
    since td is never marginalized. Measured from a sync layer at 0 with true +25 ms (our
    generator, seeds 300/301): MH_03@1 td 24.16 -> 24.89 ms, ATE 0.049 -> 0.054 m; V1_03@1
    24.58 -> 24.97 ms, 0.048 -> 0.047 m; the same excerpts synced 5 ms off from the start
    (no re-anchoring) give 24.93 and 24.83 ms. Only once the feedback has caught up with
    the estimate (else it restarted twice while the offset was still being stepped in).
    0 turns it off.

    ``td_init_retime``: a dynamic initialization that found a td remainder (and aligned its
    window there, ``vio.backend.td_init``) replays its window cut at that td, as a sync
    layer told it would have cut it (``vio.init_retime``), when the sync layer takes the
    initialization's td (``td_feedback_at_init``; feature and photometric modes): the
    window's observations start with no remainder for the td factors, and the td
    re-anchoring restart that followed every such start a second or two later is not
    needed. Generated mid-flight starts (``benchmarks/bench_midflight.py``, 158 runs at
    -30 to +30 ms; ``benchmarks/README.md``, stop 71): geometric mean 0.0925 -> 0.0893 % of
    the path, 82 better and 44 worse, above 0.2 % 8 -> 6 (MH_04@65 at +30 ms, seed 81:
    0.427 -> 0.216 %, told the true td 0.22 %; MH_04@40 at -30 ms, seed 80, 0.159 ->
    0.232 %, where the restart had helped)."""

    estimate_extrinsic: bool = False
    estimate_td: bool = True
    extrinsic_rot_sigma: float = 0.01
    extrinsic_pos_sigma: float = 0.01
    td_sigma: float = 0.01
    fixed_sigma: float = 1e-6
    td_feedback_s: float = 0.002
    td_feedback_step_s: float = 0.001
    td_feedback_after_s: float = 10.0
    td_feedback_at_init: bool = True
    td_init_retime: bool = True
    td_reanchor_s: float = 0.005
    td_reanchor_sigma_s: float = 0.001

    def __post_init__(self) -> None:
        check_ranges(self, positive=("extrinsic_rot_sigma", "extrinsic_pos_sigma", "td_sigma", "fixed_sigma",
                                     "td_reanchor_sigma_s"))


@dataclass(frozen=True)
class SolverConfig:
    """Fixed-lag smoother. ``lag_s``: window length; ``relinearize_*`` map onto
    ``ISAM2Params``: every update relinearizes the variables whose step from their
    linearization point exceeds the threshold (0.01 rad / m). Checked only every 10th
    update (GTSAM's default, this project's until stop 32), the steps of a weakly observed
    monocular scale ran up to 0.5-1.6 m before they were relinearized, and the window
    jumped back and forth by as much at every 10th update (generated MH_04@50: 0.99 % of
    the path; skip 2 gave 4.2 %, skip 5 16 restarts, skip 1 0.25 %). With the gauge prior
    (``vio.backend.gauge``), 20 ``bench_midflight`` excerpts: worst 0.99 -> 0.38 %, 18 ->
    19 under 0.2 %, geometric mean 0.109 -> 0.097 %; real MH_05 mono from 14 start frames
    mean 0.151 -> 0.120 m (``benchmarks/README.md``). Threshold 0.05 took a take-off
    (V1_03@0, td 0) from 0.018 to 0.085 m. (Those runs still had the rebuilt smoothers'
    dragged marginals, ``vio.backend.smoother.anchored``; without them every 10th update
    still leaves the 20 excerpts at 0.103 %, worst 1.55 %, against 0.091 %, worst 0.17 %
    at every update.) The photometric modes keep every 10th update
    (``vio.modes``). ``factorization``: CHOLESKY eliminates ~1.4x faster than dense
    Householder QR (real MH_05 mono: main process CPU 6.63 -> 4.68 s, p95 per frame
    111 -> 65 ms, same ATE); when GTSAM's Cholesky refuses an ill-conditioned clique
    the update is re-solved with QR (``vio.backend.smoother``), which stays at ~1.9x the
    keyframe cost until the refused variable has left the window (else the keyframes of
    that moment: real MH_01 mono, two refusals put 18 of 89 keyframes on QR, 91 vs 54 ms
    each, per-frame p95 78-96 ms; their world points gone by the next keyframe, none
    now, p95 61-65 ms). With
    ``refusal_point_sigma`` > 0 a refusal that names a world point is re-solved with
    Cholesky instead and a prior holding that point where it is (sigma: this times its
    distance from the newest keyframe): latency first (real MH_01 mono p95 53-60 ms, ATE
    over 7 stretches 5.95 -> 5.97 mm). Off by default: with QR throughout (no refusal,
    no rebuild) the generator variants that refused give what the hold gives to within
    a few rows (raw-gt 0.0833 m both, loss3pct 0.0410 both), and so does the default
    since rebuilds are neutral (``vio.backend.smoother``: the keys iSAM2 held fixed stay
    fixed). Against that default the hold moves 3 of the 31 variants (boxwall MH_03 td
    12 ms 0.253 -> 0.242 %, raw-gt-nearest td 12 ms 0.184 -> 0.225 %; under 0.2 % 24 ->
    23). (Before rebuilds were neutral the default's return to Cholesky relinearized the
    fixed points, which happened to help those runs: 25 under 0.2 %; one such rebuild
    takes real MH_05 mono from 0.067 to 0.54 m.) A prior on every point instead
    (``point_prior_sigma_m`` 2 or 5 m rather than 20) ends the refusals but holds the
    monocular scale: real MH_05 mono from 17 starts 88 -> 214 / 99 mm.
    ``wildfire_threshold``:
    iSAM2 stops propagating updates smaller than this; GTSAM's default 1e-3 freezes the
    time offset td (seconds), whose steps are ~1e-4. ``incremental_padding``: inert
    keys that keep iSAM2 off its batch step, which calls every Python factor again
    (``vio.backend.padding``; real MH_05 mono: same trajectory, fewer callbacks).
    ``point_relinearize_threshold`` (m): the world points' own threshold (None: the
    general one). A point seen from metres away is uncertain by centimetres to decimetres
    along its ray; relinearizing it at every centimetre it moves mostly re-linearizes
    noise. At 0.05 instead of 0.01 (poses, velocities and biases kept at 0.01): real
    V1_01 tracks 0.0297 -> 0.0241 m; generated excerpts neutral (features table ATE
    geometric mean x1.013; 31 generator variants x1.004, within 1.25x of the td 0 twin 7
    -> 10 of 17, under 0.2 % 24 -> 26; 20 mid-flight excerpts 0.0908 -> 0.0901 % with
    generator seed 1, 0.0894 -> 0.0957 % with seed 2). The general threshold at 0.05
    cost take-offs (V1_03@0 td 0 0.027 -> 0.156 m).
    ``outlier_update``: the second update that takes the rejected landmarks' factors out
    after a keyframe's runs at once (``"now"``) or when the next frame arrives
    (``"next_frame"``, ``vio.backend.outlier_carry``): same updates in the same order, the
    keyframe's frame does not wait for it. ``bookkeeping``: what follows a keyframe's
    update (the outlier check, the divergence monitor, the scale refinement, the gravity
    re-alignment, td re-anchoring: ``Estimator._after_update``) runs at once
    (``"keyframe"``) or when the next frame arrives (``"next_frame"``), before anything
    else of that frame: the same operations in the same order; the keyframe's own output
    is the update's estimate, and a restart the monitor decides shows one frame later.
    ``reiterate_chi2``: when the newest IMU factor's whitened squared error (15 dof) after
    a keyframe's update exceeds it, ``reiterate_max`` more iSAM2 iterations run before
    the outlier check (``vio.backend.recovery.reiterate``; 0: never)."""

    lag_s: float = 2.5
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    factorization: Literal["QR", "CHOLESKY"] = "CHOLESKY"
    refusal_point_sigma: float = 0.0
    wildfire_threshold: float = 1e-6
    td_relinearize_threshold: float = 1e-4
    point_relinearize_threshold: float | None = 0.05
    extra_iterations: int = 0
    incremental_padding: bool = True
    outlier_update: Literal["now", "next_frame"] = "now"
    bookkeeping: Literal["keyframe", "next_frame"] = "keyframe"
    reiterate_chi2: float = 100.0
    reiterate_max: int = 4

    def __post_init__(self) -> None:
        check_ranges(self, positive=("lag_s", "relinearize_threshold", "relinearize_skip", "td_relinearize_threshold",
                                     "point_relinearize_threshold"))


@dataclass(frozen=True)
class BackendConfig:
    """All backend parameters."""

    imu: ImuNoiseConfig = field(default_factory=ImuNoiseConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    init: InitConfig = field(default_factory=InitConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    calib: CalibConfig = field(default_factory=CalibConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    realign: RealignConfig = field(default_factory=RealignConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    gauge: GaugeConfig = field(default_factory=GaugeConfig)
