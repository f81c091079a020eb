"""Calibration files: EuRoC ``sensor.yaml`` for cameras and the IMU."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio.config import read_yaml
from vio.conventions import pose_from_matrix
from vio.errors import ConfigError
from vio.io.types import CameraCalib, ImuCalib

_DISTORTION = {"radial-tangential": 4, "radtan": 4, "equidistant": 4, "none": 0}


def _matrix4(data: dict, key: str, path: Path) -> np.ndarray:
    block = data.get(key)
    if not isinstance(block, dict) or "data" not in block:
        raise ConfigError(f"{path}: missing {key} (4x4 matrix with rows, cols, data)")
    vals = np.asarray(block["data"], dtype=float)
    if vals.size != 16 or not np.all(np.isfinite(vals)):
        raise ConfigError(f"{path}: {key} must hold 16 finite numbers, found {vals.size}")
    T = vals.reshape(4, 4)
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-3 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ConfigError(f"{path}: {key} is not a rigid transform "
                          f"(|R^T R - I| = {err:.2e}, det = {np.linalg.det(R):.3f})")
    return T


def _numbers(data: dict, key: str, n: int | None, path: Path) -> tuple[float, ...]:
    if key not in data:
        raise ConfigError(f"{path}: missing {key}")
    try:
        vals = tuple(float(v) for v in data[key])
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: {key} must be a list of numbers") from None
    if n is not None and len(vals) != n:
        raise ConfigError(f"{path}: {key} must have {n} values, found {len(vals)}")
    if not all(np.isfinite(vals)):
        raise ConfigError(f"{path}: {key} has non-finite values")
    return vals


def _positive(data: dict, key: str, default: float | None, path: Path, inf_ok: bool = False) -> float:
    """``data[key]`` (``default`` when absent; None: required) as a number > 0, finite
    unless ``inf_ok``; otherwise a ``ConfigError`` naming ``path`` and ``key``."""
    if key not in data and default is None:
        raise ConfigError(f"{path}: missing {key}")
    v = data.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v > 0 and (inf_ok or v < float("inf"))):
        raise ConfigError(f"{path}: {key} must be a positive number, found {v!r}")
    return float(v)


def read_camera_yaml(path: Path, name: str = "cam0") -> CameraCalib:
    """Camera calibration from an EuRoC ``sensor.yaml``. Accepts the extra key
    ``rolling_shutter_line_time_s`` written by the simulator."""
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a camera sensor.yaml")
    if data.get("camera_model", "pinhole") != "pinhole":
        raise ConfigError(f"{path}: camera_model {data['camera_model']!r} unsupported (pinhole only)")
    T = _matrix4(data, "T_BS", path)
    fx, fy, cx, cy = _numbers(data, "intrinsics", 4, path)
    w, h = (int(v) for v in _numbers(data, "resolution", 2, path))
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
        raise ConfigError(f"{path}: focal lengths and resolution must be positive")
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise ConfigError(f"{path}: principal point ({cx}, {cy}) outside the {w}x{h} image")
    model = data.get("distortion_model", "none")
    if model not in _DISTORTION:
        raise ConfigError(f"{path}: distortion_model {model!r} not in {sorted(_DISTORTION)}")
    model = "radial-tangential" if model == "radtan" else model
    dist = _numbers(data, "distortion_coefficients", _DISTORTION[model] or None, path) \
        if model != "none" else ()
    line_time = float(data.get("rolling_shutter_line_time_s", 0.0))
    if not (0.0 <= line_time < 1e-3):
        raise ConfigError(f"{path}: rolling_shutter_line_time_s {line_time} out of range [0, 1e-3)")
    return CameraCalib(pose_from_matrix(T), (fx, fy, cx, cy), model, dist, (w, h),
                       _positive(data, "rate_hz", 20.0, path), line_time, name)


def load_camera(path: Path, name: str = "cam0") -> CameraCalib:
    """``read_camera_yaml`` reporting problems as ``DataError`` (data-loading contexts)."""
    from vio.errors import DataError
    try:
        return read_camera_yaml(path, name)
    except ConfigError as exc:
        raise DataError(path, str(exc).split(": ", 1)[-1]) from None


def read_imu_yaml(path: Path) -> ImuCalib:
    """IMU noise densities and random walks from an EuRoC ``imu0/sensor.yaml``; optional
    ``accelerometer_range`` (m/s^2) and ``gyroscope_range`` (rad/s) per axis."""
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not an IMU sensor.yaml")
    keys = ("gyroscope_noise_density", "gyroscope_random_walk",
            "accelerometer_noise_density", "accelerometer_random_walk")
    vals = [_positive(data, k, None, path) for k in keys]
    T = _matrix4(data, "T_BS", path) if "T_BS" in data else np.eye(4)
    ranges = [_positive(data, k, float("inf"), path, inf_ok=True)   # optional (not in EuRoC's files)
              for k in ("accelerometer_range", "gyroscope_range")]
    return ImuCalib(*vals, rate_hz=_positive(data, "rate_hz", 200.0, path), T_b_s=pose_from_matrix(T),
                    accel_range=ranges[0], gyro_range=ranges[1])
