"""Writers for the EuRoC/ASL folder layout (``OUT/mav0/...``) and the simulator truth.

Files match the real EuRoC ones: ``sensor.yaml`` starting with ``%YAML:1.0``,
``data.csv`` with EuRoC headers, LF line endings, integer-nanosecond stamps.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from vio.io.types import CameraCalib

IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
GT_HEADER = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
             "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
             "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
             "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]")
CAM_HEADER = "#timestamp [ns],filename"


def _matrix_block(T: np.ndarray) -> str:
    rows = [", ".join(f"{v:.12g}" for v in T[i]) for i in range(4)]
    return ("T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n")


def write_camera_yaml(path: Path, calib: CameraCalib, comment: str) -> None:
    """EuRoC camera ``sensor.yaml`` plus ``rolling_shutter_line_time_s``."""
    fx, fy, cx, cy = calib.intrinsics
    dist = ", ".join(f"{d:.12g}" for d in calib.distortion)
    text = ("%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\n"
            f"comment: {comment}\n\n# Sensor extrinsics wrt. the body-frame.\n"
            + _matrix_block(calib.T_b_c.matrix())
            + f"\n# Camera specific definitions.\nrate_hz: {calib.rate_hz:g}\n"
            f"resolution: [{calib.width}, {calib.height}]\ncamera_model: pinhole\n"
            f"intrinsics: [{fx:.12g}, {fy:.12g}, {cx:.12g}, {cy:.12g}] #fu, fv, cu, cv\n"
            f"distortion_model: {calib.distortion_model}\n"
            f"distortion_coefficients: [{dist}]\n"
            "# Simulator: row r is exposed at stamp + td + r * line_time (0 = global shutter).\n"
            f"rolling_shutter_line_time_s: {calib.line_time_s:.12g}\n")
    path.write_text(text)


def write_imu_yaml(path: Path, rate_hz: float, densities: tuple[float, float, float, float]) -> None:
    """EuRoC ``imu0/sensor.yaml`` (identity T_BS: the IMU is the body frame)."""
    g, gw, a, aw = densities
    text = ("%YAML:1.0\n#Default imu sensor yaml file\nsensor_type: imu\n"
            "comment: Simulated IMU (ADIS16448-like noise)\n\n# Sensor extrinsics wrt. the body-frame.\n"
            + _matrix_block(np.eye(4)) + f"rate_hz: {rate_hz:g}\n\n"
            "# inertial sensor noise model parameters (static)\n"
            f"gyroscope_noise_density: {g:.6e}     # [ rad / s / sqrt(Hz) ]   ( gyro \"white noise\" )\n"
            f"gyroscope_random_walk: {gw:.6e}       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )\n"
            f"accelerometer_noise_density: {a:.6e}  # [ m / s^2 / sqrt(Hz) ]   ( accel \"white noise\" )\n"
            f"accelerometer_random_walk: {aw:.6e}   # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )\n")
    path.write_text(text)


def _write_table(path: Path, header: str, t_ns: np.ndarray, values: np.ndarray, fmt: str) -> None:
    lines = [header]
    row_fmt = ",".join([fmt] * values.shape[1])
    for t, row in zip(t_ns.tolist(), values.tolist()):
        lines.append(f"{t}," + row_fmt % tuple(row))
    path.write_text("\n".join(lines) + "\n")


def write_imu(imu_dir: Path, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
    """``imu0/data.csv``: stamp, gyro (rad/s), accel (m/s^2) in the body frame."""
    imu_dir.mkdir(parents=True, exist_ok=True)
    _write_table(imu_dir / "data.csv", IMU_HEADER, t_ns, np.hstack([gyro, accel]), "%.12g")


def write_groundtruth(gt_dir: Path, t_ns: np.ndarray, p_w: np.ndarray, q_wxyz: np.ndarray,
                      v_w: np.ndarray, bg: np.ndarray, ba: np.ndarray) -> None:
    """``state_groundtruth_estimate0/{data.csv, sensor.yaml}`` (17 columns, T_w_b)."""
    gt_dir.mkdir(parents=True, exist_ok=True)
    _write_table(gt_dir / "data.csv", GT_HEADER, t_ns, np.hstack([p_w, q_wxyz, v_w, bg, ba]), "%.12g")
    (gt_dir / "sensor.yaml").write_text(
        "%YAML:1.0\n# General sensor definitions.\nsensor_type: visual-inertial\n"
        "comment: Simulator ground truth (exact body/IMU state and biases at the IMU stamps).\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n" + _matrix_block(np.eye(4)))


def write_body_yaml(mav0: Path) -> None:
    (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: vio sim synthetic body (IMU frame)\n")


class CameraWriter:
    """Writes ``camN/data/<stamp>.png`` one by one, then ``data.csv`` and ``sensor.yaml``."""

    def __init__(self, cam_dir: Path, calib: CameraCalib) -> None:
        self.dir = cam_dir
        self.calib = calib
        self.stamps: list[int] = []
        (cam_dir / "data").mkdir(parents=True, exist_ok=True)

    def add(self, t_ns: int, image: np.ndarray) -> None:
        """Write one uint8 (H, W) image stamped ``t_ns`` (must increase)."""
        if self.stamps and t_ns <= self.stamps[-1]:
            raise ValueError(f"{self.dir}: stamp {t_ns} does not increase")
        if not cv2.imwrite(str(self.dir / "data" / f"{t_ns}.png"), image):
            raise OSError(f"{self.dir}: cannot write image {t_ns}.png")
        self.stamps.append(int(t_ns))

    def close(self, comment: str) -> None:
        lines = [CAM_HEADER] + [f"{t},{t}.png" for t in self.stamps]
        (self.dir / "data.csv").write_text("\n".join(lines) + "\n")
        write_camera_yaml(self.dir / "sensor.yaml", self.calib, comment)


def write_exposure_csv(path: Path, t_ns: np.ndarray, ab: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Per-frame affine brightness: ``timestamp [ns], a_<cam>, b_<cam>, ...``
    (image = clip(exp(a) * radiance + b + noise))."""
    names = sorted(ab)
    header = "#timestamp [ns]," + ",".join(f"a_{n},b_{n}" for n in names)
    vals = np.column_stack([c for n in names for c in ab[n]]) if names else np.zeros((len(t_ns), 0))
    _write_table(path, header, t_ns, vals, "%.9g")


def write_truth_yaml(path: Path, truth: dict) -> None:
    """``sim_truth.yaml`` (plain YAML, no ``%YAML`` directive)."""
    path.write_text("# vio sim ground truth that EuRoC files cannot hold\n"
                    + yaml.safe_dump(truth, sort_keys=False, default_flow_style=None))
