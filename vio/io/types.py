"""Frozen containers exchanged between the data layer and the pipeline stages.

Arrays are numpy; timestamps are int64 nanoseconds; poses are ``gtsam.Pose3``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import gtsam
import numpy as np

from vio.errors import DataError

DistortionModel = Literal["radial-tangential", "equidistant", "none"]


@dataclass(frozen=True)
class CameraCalib:
    """A pinhole camera with lens distortion, as in EuRoC ``camN/sensor.yaml``.

    ``T_b_c``: camera in the body (IMU) frame (EuRoC's ``T_BS``).
    ``intrinsics``: (fx, fy, cx, cy) in pixels. ``distortion``: radtan
    (k1, k2, p1, p2) or equidistant (k1, k2, k3, k4). ``resolution``: (width, height).
    ``line_time_s``: rolling-shutter readout time per image row in seconds (0 for
    a global shutter; EuRoC's cameras are global shutter).
    """

    T_b_c: gtsam.Pose3
    intrinsics: tuple[float, float, float, float]
    distortion_model: DistortionModel
    distortion: tuple[float, ...]
    resolution: tuple[int, int]
    rate_hz: float = 20.0
    line_time_s: float = 0.0
    name: str = "cam0"

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def width(self) -> int:
        return self.resolution[0]

    @property
    def height(self) -> int:
        return self.resolution[1]

    @property
    def readout_s(self) -> float:
        """Seconds from the first row's exposure to the last row's (0 for a global shutter)."""
        return self.line_time_s * (self.height - 1)

    @property
    def has_lens(self) -> bool:
        """Whether the lens bends the image: a distortion model with a nonzero coefficient."""
        return self.distortion_model != "none" and any(float(d) != 0.0 for d in self.distortion)

    def check_resolution(self, img: np.ndarray, where: object) -> np.ndarray:
        """``img`` if it is ``height x width``, else ``DataError`` naming ``where`` (its file,
        or which frame): images that do not match their calibration are bad input, not a
        sensor fault (an image that does not decode is one: ``vio.tracking`` drops it)."""
        if img.shape[:2] != (self.height, self.width):
            raise DataError(str(where), f"image is {img.shape[1]}x{img.shape[0]} but camera {self.name} is "
                                        f"calibrated for {self.width}x{self.height}")
        return img


@dataclass(frozen=True)
class ImuCalib:
    """Continuous-time IMU noise parameters (EuRoC ``imu0/sensor.yaml``).

    Units: gyro noise rad/s/sqrt(Hz), gyro random walk rad/s^2/sqrt(Hz), accel
    noise m/s^2/sqrt(Hz), accel random walk m/s^3/sqrt(Hz). ``accel_range`` (m/s^2) and
    ``gyro_range`` (rad/s): per-axis measurement ranges (inf when the file gives none);
    a reading beyond them is impossible (``vio.faults``).
    """

    gyro_noise_density: float
    gyro_random_walk: float
    accel_noise_density: float
    accel_random_walk: float
    rate_hz: float = 200.0
    T_b_s: gtsam.Pose3 = field(default_factory=gtsam.Pose3)
    accel_range: float = float("inf")
    gyro_range: float = float("inf")


@dataclass(frozen=True)
class ImuData:
    """IMU samples: ``t_ns`` (N,) int64, ``gyro`` (N, 3) rad/s, ``accel`` (N, 3) m/s^2,
    both in the IMU (body) frame."""

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def slice(self, t0_ns: int, t1_ns: int) -> "ImuData":
        """Samples with ``t0_ns <= t <= t1_ns``."""
        i0 = int(np.searchsorted(self.t_ns, t0_ns, side="left"))
        i1 = int(np.searchsorted(self.t_ns, t1_ns, side="right"))
        return ImuData(self.t_ns[i0:i1], self.gyro[i0:i1], self.accel[i0:i1])

    def segment(self, t0_ns: int, t1_ns: int) -> "ImuData":
        """The readings on ``[t0_ns, t1_ns]`` with both endpoints linearly interpolated
        (the single reading at ``t1_ns`` when ``t1_ns <= t0_ns``); the interval must lie
        inside the samples' span."""
        ts = self.t_ns
        i0 = max(int(np.searchsorted(ts, t0_ns, side="right")) - 1, 0)
        i1 = int(np.searchsorted(ts, t1_ns, side="left")) + 1
        ts, w, a = ts[i0:i1], self.gyro[i0:i1], self.accel[i0:i1]
        inner = ts[(ts > t0_ns) & (ts < t1_ns)]
        stamps = np.concatenate([[t0_ns], inner, [t1_ns]]) if t1_ns > t0_ns else np.array([t1_ns])
        tf = (ts - ts[0]).astype(np.float64)
        sf = (stamps - ts[0]).astype(np.float64)
        gyro = np.stack([np.interp(sf, tf, w[:, k]) for k in range(3)], axis=1)
        acc = np.stack([np.interp(sf, tf, a[:, k]) for k in range(3)], axis=1)
        return ImuData(stamps.astype(np.int64), gyro, acc)


@dataclass(frozen=True)
class GroundTruth:
    """Body (IMU) poses in the world. ``t_ns`` (N,), ``p_w`` (N, 3) m, ``q_wxyz`` (N, 4);
    optional ``v_w`` (N, 3) m/s, ``bg`` and ``ba`` (N, 3) biases (NaN where absent)."""

    t_ns: np.ndarray
    p_w: np.ndarray
    q_wxyz: np.ndarray
    v_w: np.ndarray | None = None
    bg: np.ndarray | None = None
    ba: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def pose(self, i: int) -> gtsam.Pose3:
        """``T_w_b`` of row i."""
        q = self.q_wxyz[i]
        return gtsam.Pose3(gtsam.Rot3.Quaternion(*q), self.p_w[i])


@dataclass(frozen=True)
class FeatureFrame:
    """The feature observations of one camera frame.

    ``ids`` (M,) int64 landmark ids; ``uv`` (M, 2) undistorted normalized image
    coordinates (x/z, y/z) in this camera; ``velocity`` (M, 2) normalized-plane
    velocity in 1/s (zeros when unknown); ``row`` (M,) image row in pixels used
    for rolling shutter (NaN when unknown). ``right_uv`` / ``right_velocity`` (M, 2):
    the same features in the second camera (NaN rows where unmatched; None: mono);
    ``right_row`` (M,) their cam1 pixel rows (NaN or None: unknown, cam0's row is used).
    """

    t_ns: int
    ids: np.ndarray
    uv: np.ndarray
    velocity: np.ndarray
    row: np.ndarray
    right_uv: np.ndarray | None = None
    right_velocity: np.ndarray | None = None
    right_row: np.ndarray | None = None

    @classmethod
    def empty(cls, t_ns: int) -> "FeatureFrame":
        """A frame at ``t_ns`` with no observation."""
        return cls(t_ns, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))

    def subset(self, keep: np.ndarray) -> "FeatureFrame":
        """The observations selected by ``keep`` ((M,) bool or indices), same time."""
        def pick(a):
            return None if a is None else a[keep]
        return FeatureFrame(self.t_ns, self.ids[keep], self.uv[keep], self.velocity[keep], self.row[keep],
                            pick(self.right_uv), pick(self.right_velocity), pick(self.right_row))


@dataclass(frozen=True)
class CameraStream:
    """Frame stamps and (lazily loaded) image files of one camera."""

    calib: CameraCalib
    t_ns: np.ndarray
    files: tuple[Path, ...] = ()

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def has_images(self) -> bool:
        return len(self.files) == len(self.t_ns) and len(self.files) > 0
