"""One entry point for every input ``vio run`` accepts: ASL/EuRoC or TUM-VI folders,
ROS 1 bags and ROS 2 bag folders, with optional Kalibr calibration and ground truth
from any supported file.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Sequence

from vio.errors import DataError
from vio.io.bag import is_bag, load_bag
from vio.io.euroc import EurocDataset, LoadOptions, find_mav0, load_euroc, read_groundtruth, read_tum
from vio.io.kalibr import read_camchain, read_kalibr_imu
from vio.io.types import GroundTruth

log = logging.getLogger(__name__)


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
        data = load_bag(path, kc.cams[:2], ki.calib, topics, kc.topics[:2], ki.topic, kc.td_s)
    else:
        if topics:
            raise DataError(path, "--topics applies to bags only")
        if path.is_file():
            raise DataError(path, "not a dataset: expected an ASL folder, a .bag file or a ROS 2 bag folder")
        data = with_calibration(load_euroc(path, LoadOptions(trim_to_imu=trim)), calib, imu_calib)
    if groundtruth is not None:
        data = dataclasses.replace(data, groundtruth=load_groundtruth(groundtruth))
    return data


def with_calibration(data: EurocDataset, calib: str | Path | None, imu_calib: str | Path | None) -> EurocDataset:
    """The dataset with its cameras (and td) and/or IMU noise taken from Kalibr files.
    A camera absent from the camchain is dropped (with a warning)."""
    if calib is not None:
        kc = read_camchain(calib)
        cam0 = dataclasses.replace(data.cam0, calib=kc.cams[0])
        cam1 = data.cam1
        if cam1 is not None and len(kc.cams) > 1:
            cam1 = dataclasses.replace(cam1, calib=kc.cams[1])
        elif cam1 is not None:
            log.warning("%s: no cam1 in %s: the second camera is not used", data.root, calib)
            cam1 = None
        data = dataclasses.replace(data, cam0=cam0, cam1=cam1, td_s=kc.td_s)
    if imu_calib is not None:
        data = dataclasses.replace(data, imu_calib=read_kalibr_imu(imu_calib).calib)
    return data


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
