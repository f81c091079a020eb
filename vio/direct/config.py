"""Frozen configuration of the direct (photometric) components.

Each component takes its own dataclass; ``DirectConfig`` groups them for one YAML
section, loaded strictly with ``vio.config.load(DirectConfig, path, "direct")``.
Units: pixels for image distances, intensity units (0-255) for photometric ones,
1/m for inverse depths.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from vio.direct.photocal import PhotoCalConfig


@dataclass(frozen=True)
class SelectConfig:
    """DSO-style point selection.

    ``n_points`` target count per image; ``block`` size (px) of the blocks whose
    gradient-magnitude median (+ ``grad_offset``) sets the adaptive threshold;
    ``levels`` number of cell scales (cell, 2 cell, 4 cell), each lowering the
    threshold by ``level_factor``; ``border`` pixels excluded at the image edge.
    """

    n_points: int = 400
    block: int = 32
    grad_offset: float = 7.0
    levels: int = 3
    level_factor: float = 0.75
    border: int = 8

    def __post_init__(self) -> None:
        if self.n_points < 1 or self.block < 4 or not 1 <= self.levels <= 4 or self.border < 3:
            raise ValueError("SelectConfig: need n_points >= 1, block >= 4, 1 <= levels <= 4, border >= 3")


@dataclass(frozen=True)
class EpipolarConfig:
    """Epipolar line search (seed eq. 4.1, 4.2).

    ``idepth_min``/``idepth_max`` (1/m) bound the search; ``step_px`` sampling step
    along the line; ``max_steps`` cap on samples per point; ``gn_iters`` sub-pixel
    Gauss-Newton iterations along the line; ``min_quality`` minimum ratio of the
    second-best to the best SSD (outside +-2 px of the best); ``max_energy`` maximum
    best SSD per pattern pixel (intensity^2); ``sigma_I`` image noise std; ``zero_mean``
    subtracts each patch's mean before the SSD (robust to a gain/offset between cameras).
    """

    idepth_min: float = 0.05
    idepth_max: float = 3.0
    step_px: float = 1.0
    max_steps: int = 256
    gn_iters: int = 3
    min_quality: float = 1.5
    max_energy: float = 100.0
    sigma_I: float = 4.0
    zero_mean: bool = True

    def __post_init__(self) -> None:
        if not (0.0 <= self.idepth_min < self.idepth_max) or self.step_px <= 0 or self.max_steps < 3:
            raise ValueError("EpipolarConfig: need 0 <= idepth_min < idepth_max, step_px > 0, max_steps >= 3")


@dataclass(frozen=True)
class LMConfig:
    """Levenberg-Marquardt with Nielsen damping (seed 003).

    ``tau`` initial damping mu = tau * max diag(J^T W J) (``damping="identity"``) or
    mu = tau with Marquardt's diag(J^T W J) scaling (``"diagonal"``). Stops: ``eps1`` on
    ||gradient||_inf, ``eps2`` on the relative step, ``eps3`` on ||r||, ``eps4`` on the
    relative decrease of ||r||; ``max_iters`` outer iterations (each ends in an accepted
    step or a stop); ``max_rejects`` consecutive rejected trial steps before giving up;
    ``huber_k`` robust threshold on the residuals (None: least squares).
    """

    tau: float = 1e-3
    eps1: float = 1e-10
    eps2: float = 1e-8
    eps3: float = 1e-12
    eps4: float = 1e-8
    max_iters: int = 100
    max_rejects: int = 6
    damping: Literal["identity", "diagonal"] = "identity"
    huber_k: float | None = None


@dataclass(frozen=True)
class TrackConfig:
    """TrackFrame (seed Algorithm 3): coarse-to-fine direct alignment to a keyframe.

    ``enabled``: run it at each keyframe (direct mode's failure signal); ``levels`` pyramid
    levels; ``iters`` max LM iterations per level, coarsest first (one entry per level);
    ``sigma_I``, ``grad_c``: photometric weights (factors.photometric); ``huber_k`` on the
    whitened residual; ``oob_residual`` whitened residual charged to a pattern pixel that
    leaves the image (so leaving is never rewarded); ``min_valid_fraction`` of residuals inside at level 0 for ``ok``;
    ``max_rmse`` (intensity units) for ``ok``; ``use_idepth_var`` includes the seed's
    (dr/drho)^2 V term. ``lm_*`` set the per-level ``LMConfig`` (Marquardt diagonal
    damping by default: pose and the intensity offset b have very different scales).
    ``imu_prior``: once the IMU is initialized, the IMU-predicted relative pose is a
    Gaussian prior of the alignment (``vio.direct.trackframe.MotionPrior``) with sigmas
    from the preintegration covariance, at least ``prior_rot_sigma`` (rad) and, for the
    translation, ``prior_trans_sigma`` (m) plus ``prior_vel_sigma`` (m/s, the previous
    keyframe's velocity uncertainty) times the interval. ``retry_visual``: a failed
    alignment runs once more without the prior from the previous interval's camera motion
    (``vio.direct.imu_check``); converged far from the IMU prediction, the keyframe
    interval's IMU is contradicted and bridged (``BridgeConfig.imu_check``).
    ``window_cell_px``: the keyframe tracked against also carries the window's other
    hosts' points at their refined depths, one point per cell of that size
    (``vio.direct.coarse_ref``); 0: its own points only.
    """

    enabled: bool = True
    levels: int = 4
    iters: tuple[int, ...] = (20, 15, 10, 8)
    sigma_I: float = 4.0
    grad_c: float = 50.0
    huber_k: float = 1.345
    oob_residual: float = 2.0
    min_valid_fraction: float = 0.3
    # DSO's CoarseTracker calls a frame tracked whenever its residual is finite; here the
    # IMU gate (``PointsConfig.track_gate_*``) checks the pose. On real MH_01 successful
    # alignments reach rmse 21 (median 8; renders 3-7); at 15, the stretch from frame 160
    # failed at 5 keyframes in a row (rmse 15-22, poses within 1-10 mm of the IMU's) and
    # hybrid gave 7.7 instead of 5.9 mm (stereo 5.7). Across a 1-s camera gap (real MH_01
    # frames 240-259 dropped: 0.4 m, 15 degrees) the alignment converges at RMSE 31, from
    # the ground-truth pose too; at 25 it was refused and direct / hybrid kept the IMU
    # prediction's 34 / 67 mm (ATE 14.7 / 21.9 mm, 4.3 / 4.8 at 40 with the PnP guess of
    # vio.direct.source_track; the 12 clean stretches, the renders and the other image
    # faults of bench_image_faults.py the same, benchmarks/README.md stop 78)
    max_rmse: float = 40.0
    use_idepth_var: bool = True
    lm_tau: float = 1e-4
    lm_eps2: float = 1e-6
    lm_eps4: float = 1e-5
    lm_max_rejects: int = 4
    lm_damping: Literal["identity", "diagonal"] = "diagonal"
    imu_prior: bool = True
    prior_rot_sigma: float = 0.0005
    prior_trans_sigma: float = 0.001
    prior_vel_sigma: float = 0.02
    retry_visual: bool = True
    window_cell_px: float = 32.0

    def __post_init__(self) -> None:
        if self.window_cell_px < 0:
            raise ValueError(f"TrackConfig.window_cell_px must be >= 0, got {self.window_cell_px}")
        if min(self.prior_rot_sigma, self.prior_trans_sigma) <= 0 or self.prior_vel_sigma < 0:
            raise ValueError("TrackConfig: prior sigmas must be positive")
        if self.levels < 1 or len(self.iters) != self.levels:
            raise ValueError(f"TrackConfig: iters needs one entry per level ({self.levels}), "
                             f"got {len(self.iters)}")

    def lm(self, max_iters: int) -> LMConfig:
        """The LM configuration of one level."""
        return LMConfig(tau=self.lm_tau, eps2=self.lm_eps2, eps4=self.lm_eps4,
                        max_iters=max_iters, max_rejects=self.lm_max_rejects,
                        damping=self.lm_damping, huber_k=self.huber_k)


@dataclass(frozen=True)
class PointsConfig:
    """Photometric points in the estimator's graph (``vio.direct.source``).

    Every keyframe hosts up to ``max_points`` of its ``select.n_points`` candidates that
    got an epipolar depth within [``min_depth_m``, ``max_depth_m``]; they are observed in
    the next ``max_targets`` keyframes, one factor per host
    (``factors.photometric_host``: inverse depths eliminated inside, refined with
    ``refine_iters`` Gauss-Newton steps per linearization). A host stops gaining
    targets once fewer than ``min_visible`` of its points project into the new
    keyframe. ``sigma_I``, ``grad_c``, ``huber_k``: residual weights
    (``factors.photometric``; Huber on the whitened residual); ``stereo_weight`` lambda
    of E = E_d + lambda E_s. ``outlier_rms`` (intensity units): a (point, target) pair
    whose raw residual RMS exceeds it after the depth refinement is switched off for
    good (DSO's outlier state), likewise a point whose static stereo RMS does.
    ``damping``: Marquardt damping mu diag(H) in each host factor's square-root form
    (iSAM2 takes undamped Gauss-Newton steps; the photometric cost is convex only
    within a pixel or two, so a damped step keeps the keyframes in the basin; it
    vanishes at convergence since the gradient is left as is).
    ``affine_sigma`` (a, b) prior std of every keyframe's [a, b] around 0 (gauge and
    weak regularization). ``affine_relinearize`` (a, b): iSAM2's relinearization
    thresholds of every keyframe's [a, b] (log exposure; intensity units). The residual
    is linear in b and its Jacobians change with a move of a or b by that move relative
    to 1 or to the patch intensity (``factors.photometric``), so 0.05 and 2 are about
    the linearization error the poses' 0.005 rad allow; at the poses' 0.005 the offsets
    b (a drift of ~0.3 per update along the affine gauge) relinearized every host factor
    of the window at every relinearization check. ``use_track_guess``: TrackFrame's pose
    replaces the IMU prediction as the keyframe's initial guess when it is ``ok`` and within
    ``track_gate_m`` / ``track_gate_rad`` of the prediction (the distance scaled as
    ``vio.backend.bridge.long_interval`` says over an interval longer than a keyframe
    interval, a camera gap; with a rolling shutter
    TrackFrame models it as the factors do; unmodelled, its pose pulled the window off). The backend settings these
    modes need (iSAM2 relinearization, direct mode's keyframe parallax) are mode
    defaults in ``vio.modes.MODE_DEFAULTS``, so a YAML file overrides them.
    ``exposure_td`` (off by default): while the backend estimates td
    (``backend.calib.estimate_td``), each host factor carries td's key and sees every
    frame at its exposure time, the keyframe pose moved along its body twist by ``td``
    minus the part its time already holds (``factors.photometric_host.HostTiming``), and
    the sync layer's td feedback (``CalibConfig``) runs in these modes. Without it the
    photometric term takes each image as taken at its keyframe's time and holds td at the
    sync layer's value. It needs iSAM2 to relinearize at every update
    (``backend.solver.relinearize_skip: 1``; hybrid's backend time per frame
    +3 % on real MH_01 since ``affine_relinearize``, ~40 % before):
    ``examples/photometric_td.yaml`` has the setting and benchmarks/README.md (td in the
    photometric modes) the figures.
    """

    max_points: int = 150
    max_targets: int = 5
    min_visible: float = 0.3
    refine_iters: int = 2
    damping: float = 0.01
    outlier_rms: float = 15.0
    sigma_I: float = 4.0
    grad_c: float = 50.0
    huber_k: float = 1.5
    stereo_weight: float = 1.0
    affine_sigma: tuple[float, float] = (1.0, 20.0)
    affine_relinearize: tuple[float, float] = (0.05, 2.0)
    # the frames are lost (PhotometricSource.lost; a divergence, vio.backend.health, where no
    # landmark is in the window: direct mode, not hybrid) when
    # fewer than lost_fraction * max_points (point, keyframe) pairs are in use at each of
    # lost_keyframes keyframes in a row (0: never). Real MH_01, 8 renders and the static
    # V1_01 pairs never had fewer than 252 (direct) / 144 (hybrid); a window linearized
    # pixels away (IMU predictions as the keyframes' initial poses) had 0 at most keyframes
    # and ran off at up to 29 m/s unnoticed (benchmarks/README.md, stop 55)
    lost_fraction: float = 0.1
    lost_keyframes: int = 5
    # ... or when the median raw RMS of the window's (point, keyframe) pairs (intensity
    # units) exceeds lost_rms at each of those keyframes: real MH_01 and its image-fault
    # copies stay at or below 12.3 over any 5 keyframes in a row (renders 4.2), windows
    # that ran off with their pairs still in use at 38-67 (benchmarks/README.md, stop 56)
    lost_rms: float = 25.0
    min_depth_m: float = 0.2
    max_depth_m: float = 30.0
    use_track_guess: bool = True
    track_gate_m: float = 0.05
    track_gate_rad: float = 0.05
    exposure_td: bool = False
    # a host with fewer than max_points stereo-matched candidates is filled up with
    # candidates whose depth an epipolar search in one of the last temporal_refs keyframes
    # (the widest baseline) finds with a standard deviation of at most temporal_max_rel_std
    # of the inverse depth and a search in each of the temporal_checks keyframes before it
    # does not contradict beyond temporal_agree_k sigmas (vio.direct.temporal; those points
    # carry no static stereo term)
    temporal_depth: bool = True
    temporal_refs: int = 1
    temporal_max_rel_std: float = 0.25
    temporal_checks: int = 1
    temporal_agree_k: float = 3.0

    def __post_init__(self) -> None:
        if (self.temporal_refs < 1 or self.temporal_max_rel_std <= 0 or self.temporal_checks < 0
                or self.temporal_agree_k <= 0):
            raise ValueError("PointsConfig: need temporal_refs >= 1, temporal_max_rel_std > 0, "
                             "temporal_checks >= 0 and temporal_agree_k > 0")
        if self.max_points < 1 or self.max_targets < 1 or not 0 <= self.min_visible <= 1:
            raise ValueError("PointsConfig: need max_points >= 1, max_targets >= 1, 0 <= min_visible <= 1")
        if len(self.affine_sigma) != 2 or min(self.affine_sigma) <= 0:
            raise ValueError("PointsConfig: affine_sigma needs two positive stds (a, b)")
        if not 0.0 <= self.lost_fraction <= 1.0 or self.lost_keyframes < 0 or self.lost_rms <= 0:
            raise ValueError("PointsConfig: need 0 <= lost_fraction <= 1, lost_keyframes >= 0 and lost_rms > 0")
        if len(self.affine_relinearize) != 2 or min(self.affine_relinearize) <= 0:
            raise ValueError("PointsConfig: affine_relinearize needs two positive thresholds (a, b)")
        if self.outlier_rms <= 0 or self.refine_iters < 0 or not 0 < self.min_depth_m < self.max_depth_m:
            raise ValueError("PointsConfig: need outlier_rms > 0, refine_iters >= 0, 0 < min_depth_m < max_depth_m")


@dataclass(frozen=True)
class DirectConfig:
    """All direct-method parameters (YAML section ``direct``)."""

    select: SelectConfig = field(default_factory=SelectConfig)
    epipolar: EpipolarConfig = field(default_factory=EpipolarConfig)
    track: TrackConfig = field(default_factory=TrackConfig)
    points: PointsConfig = field(default_factory=PointsConfig)
    photometric: PhotoCalConfig = field(default_factory=PhotoCalConfig)
