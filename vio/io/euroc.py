"""Reader for EuRoC/ASL dataset folders (images or feature tracks).

Layout (``ROOT`` may be the folder holding ``mav0`` or ``mav0`` itself)::

    mav0/imu0/{data.csv, sensor.yaml}                 required
    mav0/cam0/{data.csv, sensor.yaml, data/*.png}      images, or
    mav0/cam0/features.csv                            feature tracks (normalized coords)
    mav0/cam1/...                                     optional second camera
    mav0/state_groundtruth_estimate0/data.csv or groundtruth_tum.txt   optional
    mav0/mocap0/data.csv                              optional (TUM-VI ground truth)

Every problem is a ``DataError`` naming the file and line. Images load lazily
(``read_image``). Soft problems (IMU gaps) are collected in ``warnings`` and logged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from vio.errors import ConfigError, DataError
from vio.io.calib import load_camera, read_imu_yaml
from vio.io.csvio import check_increasing, read_numeric, read_text_lines
from vio.io.features import read_features
from vio.io.png import read_png_gray8
from vio.io.types import CameraCalib, CameraStream, FeatureFrame, GroundTruth, ImuCalib, ImuData

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoadOptions:
    """How strictly to load. ``max_imu_gap_s``: larger IMU gaps are reported as
    warnings. ``trim_to_imu``: drop camera frames outside the IMU span (with a
    warning) instead of failing."""

    max_imu_gap_s: float = 0.02
    trim_to_imu: bool = False


@dataclass(frozen=True)
class EurocDataset:
    """A loaded EuRoC folder. ``features`` is set for feature-track datasets."""

    root: Path
    imu: ImuData
    imu_calib: ImuCalib
    cam0: CameraStream | None
    cam1: CameraStream | None
    groundtruth: GroundTruth | None
    features: list[FeatureFrame] | None
    warnings: tuple[str, ...] = field(default_factory=tuple)
    td_s: float | None = None   # initial camera-IMU offset from the calibration (Kalibr), if any

    @property
    def kind(self) -> str:
        """``"features"``, ``"stereo"``, ``"mono"`` or ``"imu"`` (no camera data)."""
        if self.features is not None:
            return "features"
        if self.cam0 is not None and self.cam0.has_images():
            return "stereo" if self.cam1 is not None and self.cam1.has_images() else "mono"
        return "imu"


def find_mav0(root: str | Path) -> Path:
    """The ``mav0`` folder of a dataset root (accepts ``mav0`` itself)."""
    root = Path(root)
    if not root.exists():
        raise DataError(root, "dataset folder not found")
    if (root / "imu0").is_dir():
        return root
    if (root / "mav0").is_dir():
        return root / "mav0"
    raise DataError(root, "not an EuRoC/ASL folder: neither mav0/ nor imu0/ found")


def load_euroc(root: str | Path, options: LoadOptions = LoadOptions(),
               cams: Sequence[CameraCalib] | None = None, imu_calib: ImuCalib | None = None,
               td_s: float | None = None) -> EurocDataset:
    """Load and validate a dataset folder (see module docstring). ``cams`` / ``imu_calib``
    (e.g. from Kalibr files) replace the ``sensor.yaml`` files, which then need not
    exist; a camera folder beyond ``len(cams)`` is not used. ``td_s``: initial td."""
    mav0 = find_mav0(root)
    warnings: list[str] = []
    imu_dir = mav0 / "imu0"
    imu = read_imu_csv(imu_dir / "data.csv")
    warnings += imu_gap_warnings(imu, imu_dir / "data.csv", options.max_imu_gap_s)
    if imu_calib is None:
        imu_calib = _calib(read_imu_yaml, imu_dir / "sensor.yaml")
    cal0, cal1 = (None, None) if cams is None else (cams[0], cams[1] if len(cams) > 1 else False)
    cam0, all0 = read_camera(mav0 / "cam0", imu, options, warnings, required=True, calib=cal0)
    cam1 = None
    if cal1 is not False:
        cam1, _ = read_camera(mav0 / "cam1", imu, options, warnings, required=False, calib=cal1)
    elif (mav0 / "cam1").is_dir():
        warnings.append(f"{mav0 / 'cam1'}: not in the calibration given, not used")
    features = None
    feat_path = mav0 / "cam0" / "features.csv"
    if feat_path.is_file():
        features = read_features(feat_path, all0 if all0.size else None)
        keep = {int(t) for t in cam0.t_ns}
        features = [f for f in features if f.t_ns in keep]  # frames trimmed to the IMU span
    gt = read_groundtruth(mav0 / "state_groundtruth_estimate0")
    if gt is None:   # TUM-VI: motion-capture poses of the IMU
        gt = read_groundtruth(mav0 / "mocap0")
    for w in warnings:
        log.warning(w)
    return EurocDataset(mav0.parent if mav0.name == "mav0" else mav0, imu, imu_calib, cam0,
                        cam1, gt, features, tuple(warnings), td_s)


def _calib(reader, path: Path):
    try:
        return reader(path)
    except ConfigError as exc:
        raise DataError(path, str(exc).split(": ", 1)[-1]) from None


def read_imu_csv(path: Path) -> ImuData:
    """EuRoC ``imu0/data.csv``: ``t[ns], wx, wy, wz [rad/s], ax, ay, az [m/s^2]``."""
    table = read_numeric(path, 6)
    check_increasing(table)
    return ImuData(table.t_ns, table.values[:, 0:3].copy(), table.values[:, 3:6].copy())


def imu_gap_warnings(imu: ImuData, path: Path, max_gap_s: float) -> list[str]:
    """One warning per IMU gap longer than ``max_gap_s`` (the data stays usable:
    preintegration bridges the gap, with proportionally larger uncertainty)."""
    if len(imu) < 2:
        raise DataError(path, f"only {len(imu)} IMU sample(s)")
    dt = np.diff(imu.t_ns) * 1e-9
    out = []
    for i in np.flatnonzero(dt > max_gap_s)[:20]:
        out.append(f"{path}: IMU gap of {dt[i] * 1e3:.1f} ms after t={imu.t_ns[i]} "
                   f"(data row {i + 1}); threshold {max_gap_s * 1e3:.1f} ms")
    return out


def read_camera(cam_dir: Path, imu: ImuData, options: LoadOptions, warnings: list[str],
                required: bool, calib: CameraCalib | None = None) -> tuple[CameraStream | None, np.ndarray]:
    """A camera folder: ``sensor.yaml`` (unless ``calib`` is given) and ``data.csv``
    (stamps, image names). Returns the stream (frames inside the IMU span) and all
    stamps of data.csv.
    """
    none = np.zeros(0, dtype=np.int64)
    if not cam_dir.is_dir():
        if required:
            raise DataError(cam_dir, "camera folder not found")
        return None, none
    if calib is None:
        calib = load_camera(cam_dir / "sensor.yaml", cam_dir.name)
    csv = cam_dir / "data.csv"
    if not csv.is_file():  # calibration only (e.g. IMU + ground-truth folders)
        return CameraStream(calib, none), none
    t_ns, names, lines = _read_image_list(csv)
    if required and not len(t_ns):
        raise DataError(csv, "lists no frames")
    all_t = t_ns
    lo, hi = imu.t_ns[0], imu.t_ns[-1]
    outside = np.flatnonzero((t_ns < lo) | (t_ns > hi))
    if outside.size:
        i = int(outside[0])
        if not options.trim_to_imu:
            raise DataError(csv, f"camera stamp {t_ns[i]} outside the IMU span [{lo}, {hi}] "
                                 f"({outside.size} frame(s)); pass trim_to_imu / --trim to drop them",
                            int(lines[i]))
        if required and outside.size == len(t_ns):
            raise DataError(csv, f"none of its {len(t_ns)} frames lies inside the IMU span [{lo}, {hi}]")
        warnings.append(f"{csv}: dropped {outside.size} frame(s) outside the IMU span")
        keep = np.setdiff1d(np.arange(len(t_ns)), outside)
        t_ns, names = t_ns[keep], [names[k] for k in keep]
    if not (cam_dir / "data").is_dir():
        return CameraStream(calib, t_ns, ()), all_t
    files = [cam_dir / "data" / n for n in names]
    missing = [i for i, f in enumerate(files) if not f.is_file()]
    if missing:   # a frame whose image was never written: dropped, as a frame the camera dropped
        row = int(lines[np.searchsorted(all_t, t_ns[missing[0]])])
        if len(missing) == len(files):
            what = f"none of its {len(files)} images exists under {cam_dir / 'data'} (first: {names[missing[0]]})"
            if required:
                raise DataError(csv, what, row)
            warnings.append(f"{csv}:{row}: {what}: the camera's images are not used")
            return CameraStream(calib, t_ns, ()), all_t
        warnings.append(f"{csv}:{row}: {len(missing)} of {len(files)} listed image(s) missing "
                        f"(first: {names[missing[0]]}): those frames are dropped")
        keep = np.setdiff1d(np.arange(len(files)), missing)
        t_ns, files = t_ns[keep], [files[k] for k in keep]
    return CameraStream(calib, t_ns, tuple(files)), all_t


def image_files(data: EurocDataset, stereo: bool, stamps: np.ndarray) -> list[tuple]:
    """The image file(s) of each camera stamp in ``stamps`` (cam0, then cam1 in stereo)."""
    left = dict(zip(data.cam0.t_ns.tolist(), data.cam0.files))
    if not stereo:
        return [(left[t],) for t in stamps.tolist()]
    right = dict(zip(data.cam1.t_ns.tolist(), data.cam1.files))
    return [(left[t], right[t]) for t in stamps.tolist()]


def stereo_stamps(data: EurocDataset, stamps: np.ndarray) -> np.ndarray:
    """``stamps`` without the cam0 frames that have no cam1 image of the same stamp (a pair
    with one image dropped: skipped with a warning; none left: ``DataError``)."""
    both = np.isin(stamps, data.cam1.t_ns)
    if both.all():
        return stamps
    if not both.any():
        raise DataError(data.root, "no cam0 frame has a cam1 image with the same stamp")
    log.warning("%s: %d cam0 frame(s) without a cam1 image of the same stamp (first %d): those "
                "frames are dropped", data.root, int((~both).sum()), int(stamps[~both][0]))
    return stamps[both]


def _read_image_list(csv: Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    stamps, names, nos = [], [], []
    for no, raw in enumerate(read_text_lines(csv), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 2:
            raise DataError(csv, f"expected 'timestamp,filename', found {len(parts)} fields", no)
        try:
            stamps.append(int(parts[0]))
        except ValueError:
            raise DataError(csv, f"timestamp {parts[0]!r} is not an integer (ns)", no) from None
        names.append(parts[1])
        nos.append(no)
    t_ns = np.array(stamps, dtype=np.int64)
    d = np.diff(t_ns)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise DataError(csv, f"{'duplicate' if d[i - 1] == 0 else 'decreasing'} timestamp {t_ns[i]}",
                        nos[i])
    return t_ns, names, np.array(nos, dtype=np.int64)


def read_groundtruth(gt_dir: Path, name: str = "data.csv") -> GroundTruth | None:
    """EuRoC ``data.csv`` (p, q_wxyz[, v, bg, ba]; TUM-VI ``mocap0/data.csv`` is the
    7-column form) or TUM ``groundtruth_tum.txt``; None if absent."""
    csv, tum = gt_dir / name, gt_dir / "groundtruth_tum.txt"
    if csv.is_file():
        table = read_numeric(csv, (7, 16))
        check_increasing(table)
        v = table.values
        has_full = not np.isnan(v[:, 7:]).all() if v.shape[1] > 7 else False
        q = _normalized_quats(v[:, 3:7], table)
        return GroundTruth(table.t_ns, v[:, 0:3].copy(), q,
                           v[:, 7:10].copy() if has_full else None,
                           v[:, 10:13].copy() if has_full else None,
                           v[:, 13:16].copy() if has_full else None)
    if tum.is_file():
        return read_tum(tum)
    return None


def read_tum(path: str | Path) -> GroundTruth:
    """TUM trajectory ``t[s] tx ty tz qx qy qz qw`` as a ``GroundTruth``."""
    table = read_numeric(path, 7, delimiter=None, time_in_seconds=True)
    check_increasing(table)
    v = table.values
    q = _normalized_quats(v[:, [6, 3, 4, 5]], table)
    return GroundTruth(table.t_ns, v[:, 0:3].copy(), q)


def _normalized_quats(q: np.ndarray, table) -> np.ndarray:
    n = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(n - 1.0) > 1e-2)
    if bad.size:
        raise DataError(table.path, f"quaternion norm {n[bad[0]]:.4f} is not 1",
                        int(table.lines[bad[0]]))
    return q / n[:, None]


def image_exists(path: str | Path) -> bool:
    """Whether :func:`read_image` finds something to read at ``path`` (a file, or a
    reference with ``read_gray()``), without decoding it."""
    return hasattr(path, "read_gray") or Path(path).is_file()


def read_image(path: str | Path, calib: CameraCalib | None = None) -> np.ndarray:
    """Grayscale uint8 image (H, W); ``DataError`` if missing or unreadable, or (with
    ``calib``) not of the camera's calibrated resolution. Accepts any reference with a
    ``read_gray()`` method as well (``vio.io.bag.BagFrame``)."""
    if hasattr(path, "read_gray"):
        img = path.read_gray()
    else:
        path = Path(path)
        img = read_png_gray8(path) if path.suffix.lower() == ".png" else None   # vio.io.png: 2.5x faster
        if img is None:
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
        if img is None:
            raise DataError(path, "image missing or unreadable")
    return img if calib is None else calib.check_resolution(img, path)
