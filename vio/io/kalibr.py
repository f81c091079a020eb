"""Kalibr calibration files: ``camchain.yaml`` (cameras) and ``imu.yaml`` (IMU noise).

camchain (``camchain-imucam-*.yaml``): ``cam0``, ``cam1``, ... each with
``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model``
(``radtan`` or ``equidistant``) with four ``distortion_coeffs``, ``resolution: [w, h]``,
``T_cam_imu`` (4x4: IMU point -> camera point, so ``T_b_c = T_cam_imu^-1``), for camN
(N > 0) ``T_cn_cnm1`` (cam N-1 point -> cam N point; used when ``T_cam_imu`` is
absent), optional ``timeshift_cam_imu`` (s, ``t_imu = t_cam + shift``: the initial
td), ``line_delay`` (s per image row of a rolling shutter, as Kalibr's rolling-shutter
calibration writes it; absent or 0: global shutter) and ``rostopic``. imu.yaml: ``accelerometer_noise_density``,
``accelerometer_random_walk``, ``gyroscope_noise_density``, ``gyroscope_random_walk``,
``update_rate`` and optional ``rostopic`` / ``T_i_b``, flat or under ``imu0:``.

Every missing or malformed key is a ``DataError`` naming the file and the key.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from vio.config import read_yaml
from vio.conventions import pose_from_matrix
from vio.errors import ConfigError, DataError
from vio.io.types import CameraCalib, ImuCalib

log = logging.getLogger(__name__)

_MODELS = {"radtan": "radial-tangential", "equidistant": "equidistant", "none": "none"}
_NOISE_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk",
               "accelerometer_noise_density", "accelerometer_random_walk")


@dataclass(frozen=True)
class KalibrCameras:
    """The cameras of a camchain (cam0 first), their ``rostopic`` (None when absent)
    and cam0's ``timeshift_cam_imu`` as the initial td in seconds."""

    cams: tuple[CameraCalib, ...]
    topics: tuple[str | None, ...]
    td_s: float


@dataclass(frozen=True)
class KalibrImu:
    """IMU noise parameters and the IMU ``rostopic`` (None when absent)."""

    calib: ImuCalib
    topic: str | None


def _read(path: Path) -> dict:
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise DataError(path, str(exc).split(": ", 1)[-1]) from None
    if not isinstance(data, dict):
        raise DataError(path, "not a Kalibr YAML mapping")
    return data


def _get(block: dict, key: str, where: str, path: Path):
    if key not in block:
        raise DataError(path, f"missing key {where}{key}")
    return block[key]


def _floats(block: dict, key: str, n: int, where: str, path: Path) -> tuple[float, ...]:
    val = _get(block, key, where, path)
    try:
        out = tuple(float(v) for v in val)
    except (TypeError, ValueError):
        raise DataError(path, f"{where}{key} must be a list of {n} numbers, found {val!r}") from None
    if len(out) != n or not np.all(np.isfinite(out)):
        raise DataError(path, f"{where}{key} must be a list of {n} finite numbers, found {val!r}")
    return out


def _scalar(block: dict, key: str, where: str, path: Path, positive: bool = True,
            default: float | None = None) -> float:
    if default is not None and key not in block:
        return default
    val = _get(block, key, where, path)
    ok = isinstance(val, (int, float)) and not isinstance(val, bool) and np.isfinite(val)
    if not ok or (positive and val <= 0):
        kind = "a positive number" if positive else "a number"
        raise DataError(path, f"{where}{key} must be {kind}, found {val!r}")
    return float(val)


def _matrix(block: dict, key: str, where: str, path: Path) -> np.ndarray:
    val = _get(block, key, where, path)
    try:
        T = np.array(val, dtype=float)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DataError(path, f"{where}{key} must be a 4x4 matrix (four rows of four numbers)")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-3 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise DataError(path, f"{where}{key} is not a rigid transform (|R^T R - I| = {err:.2e})")
    return T


def _camera(block: dict, name: str, path: Path, T_cam_imu: np.ndarray) -> CameraCalib:
    where = f"{name}."
    model = _get(block, "camera_model", where, path)
    if model != "pinhole":
        raise DataError(path, f"{where}camera_model {model!r} unsupported (pinhole only)")
    fx, fy, cx, cy = _floats(block, "intrinsics", 4, where, path)
    w, h = (int(v) for v in _floats(block, "resolution", 2, where, path))
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
        raise DataError(path, f"{where}intrinsics / resolution must be positive")
    dist_model = _get(block, "distortion_model", where, path)
    if dist_model not in _MODELS:
        raise DataError(path, f"{where}distortion_model {dist_model!r} not in {sorted(_MODELS)}")
    dist = _floats(block, "distortion_coeffs", 4, where, path) if dist_model != "none" else ()
    T_b_c = pose_from_matrix(np.linalg.inv(T_cam_imu))
    line = _scalar(block, "line_delay", where, path, positive=False, default=0.0)
    if not 0.0 <= line < 1e-3:
        raise DataError(path, f"{where}line_delay {line!r} s per row out of range [0, 1e-3)")
    return CameraCalib(T_b_c, (fx, fy, cx, cy), _MODELS[dist_model], dist, (w, h), name=name,
                       line_time_s=line)


def read_camchain(path: str | Path) -> KalibrCameras:
    """Cameras from a Kalibr camchain (see the module docstring)."""
    path = Path(path)
    data = _read(path)
    names = sorted((k for k in data if isinstance(k, str) and k.startswith("cam") and k[3:].isdigit()),
                   key=lambda k: int(k[3:]))
    if not names or names[0] != "cam0":
        raise DataError(path, "missing key cam0")
    cams, topics, prev = [], [], None
    for i, name in enumerate(names):
        if name != f"cam{i}":
            raise DataError(path, f"missing key cam{i} (found {name})")
        block = data[name]
        if not isinstance(block, dict):
            raise DataError(path, f"{name} must be a mapping")
        if "T_cam_imu" in block or prev is None:
            T = _matrix(block, "T_cam_imu", f"{name}.", path)
        else:
            T = _matrix(block, "T_cn_cnm1", f"{name}.", path) @ prev
        cams.append(_camera(block, name, path, T))
        topic = block.get("rostopic")
        if topic is not None and not isinstance(topic, str):
            raise DataError(path, f"{name}.rostopic must be a string, found {topic!r}")
        topics.append(topic)
        prev = T
    td = _scalar(data["cam0"], "timeshift_cam_imu", "cam0.", path, positive=False, default=0.0)
    return KalibrCameras(tuple(cams), tuple(topics), td)


def read_kalibr_imu(path: str | Path) -> KalibrImu:
    """IMU noise from a Kalibr imu.yaml (flat, or under ``imu0:``)."""
    path = Path(path)
    data = _read(path)
    where = ""
    if isinstance(data.get("imu0"), dict):
        data, where = data["imu0"], "imu0."
    vals = [_scalar(data, k, where, path) for k in _NOISE_KEYS]
    rate = _scalar(data, "update_rate", where, path)
    T_b_s = pose_from_matrix(np.linalg.inv(_matrix(data, "T_i_b", where, path))) if "T_i_b" in data else None
    topic = data.get("rostopic")
    if topic is not None and not isinstance(topic, str):
        raise DataError(path, f"{where}rostopic must be a string, found {topic!r}")
    calib = ImuCalib(*vals, rate_hz=rate) if T_b_s is None else ImuCalib(*vals, rate_hz=rate, T_b_s=T_b_s)
    return KalibrImu(calib, topic)


def _rows(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T, float)]


def write_camchain(path: str | Path, cams: list[CameraCalib], topics: list[str] | None = None,
                   td_s: float = 0.0) -> None:
    """Write cameras (``T_b_c`` etc.) as a Kalibr camchain-imucam YAML."""
    out, prev = {}, None
    for i, c in enumerate(cams):
        T_cam_imu = np.linalg.inv(c.T_b_c.matrix())
        model = {v: k for k, v in _MODELS.items()}[c.distortion_model]
        block = {"T_cam_imu": _rows(T_cam_imu), "camera_model": "pinhole",
                 "distortion_coeffs": [float(v) for v in c.distortion] if c.distortion else [0.0] * 4,
                 "distortion_model": "radtan" if model == "none" else model,
                 "intrinsics": [float(v) for v in c.intrinsics], "resolution": [int(v) for v in c.resolution],
                 "rostopic": topics[i] if topics else f"/cam{i}/image_raw", "timeshift_cam_imu": float(td_s)}
        if c.line_time_s > 0.0:
            block["line_delay"] = float(c.line_time_s)
        if prev is not None:
            block["T_cn_cnm1"] = _rows(T_cam_imu @ np.linalg.inv(prev))
            block["cam_overlaps"] = [i - 1]
        out[f"cam{i}"] = block
        prev = T_cam_imu
    Path(path).write_text(yaml.safe_dump(out, sort_keys=False, default_flow_style=None))


def write_kalibr_imu(path: str | Path, calib: ImuCalib, topic: str = "/imu0") -> None:
    """Write IMU noise as a Kalibr imu.yaml (flat, the calibration-input form)."""
    out = {"rostopic": topic, "update_rate": float(calib.rate_hz),
           "accelerometer_noise_density": calib.accel_noise_density,
           "accelerometer_random_walk": calib.accel_random_walk,
           "gyroscope_noise_density": calib.gyro_noise_density,
           "gyroscope_random_walk": calib.gyro_random_walk}
    Path(path).write_text(yaml.safe_dump(out, sort_keys=False, default_flow_style=None))
