"""Configuration of the synthetic EuRoC-style dataset generator (``vio sim``).

Load strictly with ``vio.config.from_dict(SimConfig, d)`` / ``vio.config.load``.
World frame: the room spans ``[0, Lx] x [0, Ly] x [0, Lz]`` metres, z up, gravity
``-gravity * e_z``. Times in seconds are relative to ``t0_ns`` (the IMU clock).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from vio.errors import ConfigError

ExposureMode = Literal["none", "smooth", "step"]
MotionMode = Literal["loop", "constant_velocity"]


@dataclass(frozen=True)
class SimConfig:
    """Every knob of one simulated sequence (defaults: a 10 s EuRoC-like stereo run).

    Timing: ``td_s`` is the camera-IMU offset in the VINS convention (written
    image stamp + td = true exposure time in the IMU clock); ``line_time_s`` is the
    rolling-shutter readout time per row (row r is exposed at stamp + td + r * line_time;
    0 = global shutter).

    Photometry: ``exposure_changes`` makes each frame ``I' = exp(a) I + b``, with
    ``|a| <= exposure_log_gain_amp`` and ``|b| <= exposure_bias_amp`` (gray levels),
    varying smoothly (period ``exposure_period_s``) or stepwise (a new value every
    half period). ``image_noise_sigma``: Gaussian pixel noise, gray levels.
    ``image_scale`` scales the 752x480 EuRoC resolution and intrinsics (tests use 0.5).

    IMU: EuRoC ADIS16448 continuous-time densities (gyro rad/s/sqrt(Hz), gyro walk
    rad/s^2/sqrt(Hz), accel m/s^2/sqrt(Hz), accel walk m/s^3/sqrt(Hz)); they are
    written to ``imu0/sensor.yaml``. ``imu_noise = False`` disables white noise and
    bias random walk (the biases stay at their random initial values, drawn with
    the ``*_bias_init_sigma`` standard deviations).

    Scene and motion: ``room_size`` (Lx, Ly, Lz) metres; ``n_boxes`` boxes and
    ``n_pillars`` floor-to-ceiling cylinders placed at least ``obstacle_clearance_m``
    (horizontally) from the path; ``texels_per_m`` texture resolution. The path is a
    perturbed elliptic loop ``wall_margin_m`` from the walls at mean speed about
    ``speed_mps``; yaw follows the loop plus sweeps peaking near ``yaw_sweep_dps``.
    ``motion = "constant_velocity"``: instead a straight pass along world x at
    ``speed_mps`` (a car, a smooth drone pass), looking sideways at the y = Ly wall with
    the same yaw sweeps and small pitch/roll; position wiggles of 1-2 cm keep the
    acceleration within ~0.03 m/s^2 RMS, so the IMU alone fixes no scale. The room must be
    long enough: ``room_size[0] >= speed_mps * seconds + 2 * wall_margin_m``
    (``vio sim --motion constant_velocity`` lengthens it when ``--config`` does not set it).
    """

    seconds: float = 10.0
    seed: int = 0
    td_s: float = 0.0
    line_time_s: float = 0.0
    stereo: bool = True
    render_images: bool = True
    exposure_changes: ExposureMode = "none"
    exposure_log_gain_amp: float = 0.3
    exposure_bias_amp: float = 8.0
    exposure_period_s: float = 4.0
    image_noise_sigma: float = 1.5
    image_scale: float = 1.0
    cam_rate_hz: float = 20.0
    imu_rate_hz: float = 200.0
    t0_ns: int = 1_600_000_000_000_000_000
    gyro_noise_density: float = 1.6968e-04
    gyro_random_walk: float = 1.9393e-05
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    imu_noise: bool = True
    gyro_bias_init_sigma: float = 0.003
    accel_bias_init_sigma: float = 0.03
    gravity: float = 9.81
    room_size: tuple[float, float, float] = (8.0, 6.0, 3.0)
    n_boxes: int = 4
    n_pillars: int = 2
    obstacle_clearance_m: float = 0.7
    texels_per_m: float = 256.0
    speed_mps: float = 0.7
    yaw_sweep_dps: float = 35.0
    wall_margin_m: float = 1.5
    motion: MotionMode = "loop"

    def __post_init__(self) -> None:
        checks = [
            (self.seconds > 0, "seconds must be > 0"),
            (self.cam_rate_hz > 0 and self.imu_rate_hz > 0, "rates must be > 0"),
            (abs(self.td_s) < 0.5, "|td_s| must be < 0.5 s"),
            (0.0 <= self.line_time_s < 1e-3, "line_time_s must be in [0, 1e-3)"),
            (0.05 <= self.image_scale <= 4.0, "image_scale must be in [0.05, 4]"),
            (self.image_noise_sigma >= 0, "image_noise_sigma must be >= 0"),
            (self.exposure_period_s > 0, "exposure_period_s must be > 0"),
            (min(self.gyro_noise_density, self.gyro_random_walk, self.accel_noise_density,
                 self.accel_random_walk) > 0, "IMU noise densities must be > 0"),
            (min(self.gyro_bias_init_sigma, self.accel_bias_init_sigma) >= 0,
             "bias init sigmas must be >= 0"),
            (min(self.room_size) >= 1.0, "room_size entries must be >= 1 m"),
            (self.n_boxes >= 0 and self.n_pillars >= 0, "obstacle counts must be >= 0"),
            (self.obstacle_clearance_m >= 0.3, "obstacle_clearance_m must be >= 0.3 m"),
            (8.0 <= self.texels_per_m <= 1024.0, "texels_per_m must be in [8, 1024]"),
            (self.speed_mps > 0 and self.yaw_sweep_dps >= 0, "speeds must be positive"),
            (self.wall_margin_m > 0.3, "wall_margin_m must be > 0.3 m"),
            (self.t0_ns > 0, "t0_ns must be > 0"),
            (self.motion != "constant_velocity"
             or self.room_size[0] >= self.speed_mps * self.seconds + 2 * self.wall_margin_m - 1e-9,
             "motion constant_velocity needs room_size[0] >= speed_mps * seconds + 2 * wall_margin_m"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(f"SimConfig: {msg}")

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (max(8, round(752 * self.image_scale)), max(8, round(480 * self.image_scale)))

    @property
    def readout_s(self) -> float:
        """Seconds from the first row's exposure to the last row's (0 for a global shutter)."""
        return (self.resolution[1] - 1) * self.line_time_s
