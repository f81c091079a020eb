"""Reader for the EqVIO-processed EuRoC V1_01 file shipped inside the gtsam wheel
(``gtsam/Data/eqvio_processed_30s.csv``): real IMU and real feature tracks, read in
place so ``vio run --demo`` needs no download.

Rows: ``row_type`` = meta (key, value), imu (t_abs s, gyro, accel) or
vision_feature (t_abs s, frame_idx, landmark_id, u_norm, v_norm).
"""

from __future__ import annotations

import csv
from pathlib import Path

import gtsam
import numpy as np

from vio.conventions import pose_from_tq
from vio.errors import DataError
from vio.io.csvio import parse_seconds_to_ns
from vio.io.euroc import EurocDataset
from vio.io.features import _group
from vio.io.types import CameraCalib, CameraStream, ImuCalib, ImuData

# The V1_01 IMU (ADIS16448) datasheet densities, as in EuRoC's imu0/sensor.yaml.
EUROC_IMU = ImuCalib(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3, 200.0)


def wheel_demo_path() -> Path:
    """Location of the demo file inside the installed gtsam package."""
    return Path(gtsam.__file__).resolve().parent / "Data" / "eqvio_processed_30s.csv"


def load_eqvio(path: Path | None = None) -> EurocDataset:
    """Load the EqVIO file as a feature-track dataset (no ground truth)."""
    path = wheel_demo_path() if path is None else Path(path)
    if not path.is_file():
        raise DataError(path, "demo data not found (is gtsam >= 4.3 installed?)")
    meta, imu_rows, feat_rows = {}, [], []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        for no, row in enumerate(reader, start=2):
            kind = row["row_type"]
            try:
                if kind == "meta":
                    meta[row["key"]] = row["value"]
                elif kind == "imu":
                    imu_rows.append((parse_seconds_to_ns(row["t_abs"]),
                                     *(float(row[c]) for c in ("gx", "gy", "gz", "ax", "ay", "az"))))
                elif kind == "vision_feature":
                    feat_rows.append((parse_seconds_to_ns(row["t_abs"]), int(row["landmark_id"]),
                                      float(row["u_norm"]), float(row["v_norm"]), no))
            except (ValueError, TypeError, ArithmeticError) as exc:
                raise DataError(path, f"malformed {kind} row ({exc})", no) from None
    t_imu = np.array([r[0] for r in imu_rows], dtype=np.int64)
    vals = np.array([r[1:] for r in imu_rows], dtype=float)
    imu = ImuData(t_imu, vals[:, :3].copy(), vals[:, 3:].copy())
    cam = _camera(meta, path)
    t_f = np.array([r[0] for r in feat_rows], np.int64)
    frames = _group(path, t_f, np.array([r[1] for r in feat_rows], np.int64),
                    np.array([(r[2], r[3]) for r in feat_rows]),
                    np.array([r[4] for r in feat_rows]), None)
    stamps = np.array([fr.t_ns for fr in frames], np.int64)
    return EurocDataset(path.parent, imu, EUROC_IMU, CameraStream(cam, stamps), None, None, frames)


def _camera(meta: dict, path: Path) -> CameraCalib:
    try:
        fx, fy, cx, cy = (float(meta[k]) for k in ("camera_fx", "camera_fy", "camera_cx", "camera_cy"))
        t = [float(meta[f"T_ci_t{a}"]) for a in "xyz"]
        q = [float(meta[f"T_ci_q{a}"]) for a in "wxyz"]
    except KeyError as exc:
        raise DataError(path, f"missing meta key {exc}") from None
    return CameraCalib(pose_from_tq(np.array(t), np.array(q)), (fx, fy, cx, cy), "none", (),
                       (752, 480), 20.0, 0.0, "cam0")
