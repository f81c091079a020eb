"""One entry point for every input ``vio run`` accepts: ASL/EuRoC or TUM-VI folders,
ROS 1 bags and ROS 2 bag folders, with optional Kalibr calibration and ground truth
from any supported file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

from vio.errors import DataError
from vio.io.bag import is_bag, load_bag
from vio.io.euroc import EurocDataset, LoadOptions, find_mav0, load_euroc, read_groundtruth, read_tum
from vio.io.kalibr import read_camchain, read_kalibr_imu
from vio.io.types import GroundTruth


def load_dataset(path: str | Path, trim: bool = False, topics: Sequence[str] | None = None,
                 calib: str | Path | None = None, imu_calib: str | Path | None = None,
                 groundtruth: str | Path | None = None) -> EurocDataset:
    """Load a folder or a bag. ``calib`` / ``imu_calib``: Kalibr camchain / imu.yaml
    (required for bags; for folders they override ``sensor.yaml``). ``topics``: bag
    topics (see ``vio.io.bag.choose_topics``). ``groundtruth``: a TUM file, ASL csv or
    dataset folder replacing the dataset's own ground truth."""
    path = Path(path)
    if is_bag(path):
        for flag, value in (("--calib camchain.yaml", calib), ("--imu-calib imu.yaml", imu_calib)):
            if value is None:
                raise DataError(path, f"a bag carries no calibration: give {flag} (Kalibr)")
        kc, ki = read_camchain(calib), read_kalibr_imu(imu_calib)
        data = load_bag(path, kc.cams, ki.calib, topics, kc.topics, ki.topic, kc.td_s)
    else:
        if topics:
            raise DataError(path, "--topics applies to bags only")
        if path.is_file():
            raise DataError(path, "not a dataset: expected an ASL folder, a .bag file or a ROS 2 bag folder")
        data = load_folder(path, trim, calib, imu_calib)
    if groundtruth is not None:
        data = dataclasses.replace(data, groundtruth=load_groundtruth(groundtruth))
    return data


def tumvi_calibration(path: str | Path) -> tuple[Path | None, Path | None]:
    """TUM-VI folders carry Kalibr files: ``dso/camchain.yaml`` and ``dso/imu_config.yaml``
    (each None when absent)."""
    mav0 = find_mav0(path)
    root = mav0.parent if mav0.name == "mav0" else mav0
    found = [root / "dso" / n for n in ("camchain.yaml", "imu_config.yaml")]
    return tuple(p if p.is_file() else None for p in found)


def load_folder(path: str | Path, trim: bool = False, calib: str | Path | None = None,
                imu_calib: str | Path | None = None) -> EurocDataset:
    """An ASL folder; Kalibr files (given, or TUM-VI's ``dso/`` ones) replace sensor.yaml,
    and the camchain's ``timeshift_cam_imu`` is the initial td."""
    dso_cams, dso_imu = tumvi_calibration(path)
    calib, imu_calib = calib or dso_cams, imu_calib or dso_imu
    kc = read_camchain(calib) if calib is not None else None
    ki = read_kalibr_imu(imu_calib).calib if imu_calib is not None else None
    return load_euroc(path, LoadOptions(trim_to_imu=trim), kc.cams if kc else None, ki,
                      kc.td_s if kc else None)


def load_groundtruth(path: str | Path) -> GroundTruth:
    """Ground truth from a TUM file, an ASL ``data.csv`` (state_groundtruth_estimate0 or
    mocap0) or a dataset folder holding one."""
    path = Path(path)
    if path.is_dir():
        gt = read_groundtruth_folder(find_mav0(path))
        if gt is None:
            raise DataError(path, "no ground truth (state_groundtruth_estimate0/ or mocap0/) found")
        return gt
    if not path.is_file():
        raise DataError(path, "ground-truth file not found")
    if path.suffix == ".csv":
        gt = read_groundtruth(path.parent, path.name)
        assert gt is not None
        return gt
    return read_tum(path)


def read_groundtruth_folder(mav0: Path) -> GroundTruth | None:
    """The ground truth of an ASL ``mav0`` folder: EuRoC's estimate, else TUM-VI's mocap0."""
    for sub in ("state_groundtruth_estimate0", "mocap0"):
        gt = read_groundtruth(mav0 / sub)
        if gt is not None:
            return gt
    return None
