"""Per-keyframe image data of the direct mode: undistorted stereo images, the selected
candidate points with their epipolar inverse depths, and the right image's affine
brightness relative to the left.

Frames: ``uv`` are undistorted pinhole pixels of cam0 (pixel-centre convention);
``idepth`` (1/m) and ``idepth_var`` (1/m^2) are in the cam0 frame of the keyframe;
``ab_right`` = [a, b] with I_right ~ e^a I_left + b at matching pixels.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import gtsam
import numpy as np

from factors.image_ops import BilinearImage, pyramid
from factors.photometric import PATTERN, Pinhole
from factors.photometric_warp import row_model
from vio.direct.config import DirectConfig
from vio.direct.epipolar import epipolar_search, undistort_pinhole
from vio.direct.photocal import PhotometricCalibration
from vio.direct.select import select_points
from vio.direct.trackframe import TrackingReference, make_reference
from vio.io.euroc import read_image
from vio.io.types import CameraCalib


def _sensor_rows(calib: CameraCalib) -> np.ndarray | None:
    """``calib``'s sensor-row model, None without a lens (no distortion coefficients)."""
    if not calib.has_lens:
        return None
    return row_model(calib.intrinsics, calib.distortion_model, calib.distortion)


@dataclass(eq=False)
class StereoRig:
    """The fixed stereo geometry: pinhole intrinsics of both cameras, ``T_b_c`` of
    cam0 (body <- cam0) and ``T_c1_c0`` (cam1 <- cam0), the distortion to remove, and
    each camera's photometric calibration (``vio.direct.photocal``; identity: none).
    ``rows0``, ``rows1``: each camera's sensor-row model (``factors.photometric_warp.
    row_model``) where its lens bends the sensor rows in the undistorted image, for a
    rolling shutter's row times; None without a lens (the pinhole row is the sensor row)."""

    cam0: CameraCalib
    cam1: CameraCalib
    photo0: PhotometricCalibration = field(default_factory=PhotometricCalibration)
    photo1: PhotometricCalibration = field(default_factory=PhotometricCalibration)
    K0: Pinhole = field(init=False)
    K1: Pinhole = field(init=False)
    T_b_c: gtsam.Pose3 = field(init=False)
    T_c1_c0: gtsam.Pose3 = field(init=False)
    rows0: np.ndarray | None = field(init=False)
    rows1: np.ndarray | None = field(init=False)

    def __post_init__(self) -> None:
        self.K0 = Pinhole(*self.cam0.intrinsics)
        self.K1 = Pinhole(*self.cam1.intrinsics)
        self.T_b_c = self.cam0.T_b_c
        self.T_c1_c0 = self.cam1.T_b_c.between(self.cam0.T_b_c)
        self.rows0, self.rows1 = _sensor_rows(self.cam0), _sensor_rows(self.cam1)

    def undistort(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Both images as undistorted pinhole float64 images (no-op without distortion),
        photometrically corrected first when a calibration is set."""
        return self.undistort_one(left, 0), self.undistort_one(right, 1)

    def undistort_one(self, image: np.ndarray, cam: int) -> np.ndarray:
        """``undistort`` of camera ``cam``'s (0: left, 1: right) image alone."""
        photo, calib = (self.photo0, self.cam0) if cam == 0 else (self.photo1, self.cam1)
        if not photo.identity:
            image = photo.apply(image)
        return undistort_pinhole(image, calib.K, calib.distortion, calib.distortion_model)


@dataclass(frozen=True, eq=False)
class KeyframePoints:
    """The candidate points of a keyframe (module docstring): ``uv`` (N, 2), ``idepth``
    (N,), ``idepth_var`` (N,), the right image's ``ab_right``, the number of selected
    pixels before the depth checks ``n_selected``, TrackFrame's reference of the
    points (``ref``, its affine a placeholder; None when tracking is off), the
    undistorted right image ``right``, the candidates the stereo search did not place,
    ``uv_rest`` (K, 2), and how many of the points lead ``uv`` with stereo depths,
    ``n_stereo`` (None: all; the rest were placed by ``vio.direct.temporal``)."""

    right: BilinearImage
    uv: np.ndarray
    idepth: np.ndarray
    idepth_var: np.ndarray
    ab_right: np.ndarray
    n_selected: int
    ref: TrackingReference | None = None
    uv_rest: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    n_stereo: int | None = None


@dataclass(eq=False)
class KeyframeData:
    """Images and candidate points of one keyframe ``k`` (see module docstring). The
    points may still be under construction in the keyframe worker thread
    (``build_keyframe(..., background=True)``): reading ``uv``, ``idepth``,
    ``idepth_var``, ``ab_right``, ``n_selected`` or ``right`` (the right image, read and
    undistorted there too) waits for them (and re-raises an error of their construction)."""

    k: int
    t_ns: int
    K: Pinhole
    image: np.ndarray
    left: BilinearImage
    _points: KeyframePoints | Future | None
    in_graph: bool = False
    _ref: TrackingReference | None = None
    _pyr: tuple[BilinearImage, ...] = ()

    @property
    def points(self) -> KeyframePoints:
        """The candidate points (waits for the worker thread if they are not ready)."""
        if isinstance(self._points, Future):
            self._points = self._points.result()
        return self._points

    right = property(lambda self: self.points.right)
    uv = property(lambda self: self.points.uv)
    idepth = property(lambda self: self.points.idepth)
    idepth_var = property(lambda self: self.points.idepth_var)
    ab_right = property(lambda self: self.points.ab_right)
    n_selected = property(lambda self: self.points.n_selected)

    @property
    def n_stereo(self) -> int:
        """How many of the points (the first ones) have stereo depths."""
        n = self.points.n_stereo
        return len(self.uv) if n is None else n

    def add_points(self, uv: np.ndarray, idepth: np.ndarray, idepth_var: np.ndarray) -> None:
        """Append the points placed after construction (``vio.direct.temporal``, once):
        (K, 2) pixels, (K,) inverse depths and variances; no candidate is left unplaced.
        TrackFrame's reference is rebuilt from all points at its next use."""
        p = self.points
        self._points = dataclasses.replace(
            p, uv=np.concatenate([p.uv, uv]), idepth=np.concatenate([p.idepth, idepth]),
            idepth_var=np.concatenate([p.idepth_var, idepth_var]), ref=None,
            uv_rest=np.zeros((0, 2)), n_stereo=self.n_stereo)
        self._ref = None

    def pyramid(self, levels: int) -> tuple[BilinearImage, ...]:
        """The left image's pyramid (``vio.direct.trackframe.image_pyramid``; level 0 is
        ``left``), built once: TrackFrame samples it as the new frame, then as the
        reference when this keyframe is tracked against."""
        if len(self._pyr) < levels:
            self._pyr = (self.left,) + tuple(BilinearImage(im) for im in pyramid(self.image, levels)[1:])
        return self._pyr[:levels]

    def release_pyramid(self) -> None:
        """Drop the coarse levels (~3 MB at 752 x 480) once TrackFrame no longer needs
        them (``pyramid`` rebuilds them if asked again)."""
        self._pyr = ()

    def reference(self, ab: np.ndarray, cfg: DirectConfig) -> TrackingReference:
        """TrackFrame reference of this keyframe (built once) with its affine ``ab``."""
        if self._ref is None:
            self._ref = self.points.ref
        if self._ref is None or self._ref.levels != cfg.track.levels:
            self._ref = make_reference(self.pyramid(cfg.track.levels), self.uv, self.idepth, self.K,
                                       self.idepth_var, tuple(ab), cfg.track)
        return TrackingReference(self._ref.K, self._ref.patches, self._ref.idepth,
                                 self._ref.idepth_var, np.asarray(ab, float))


def right_affine(left: BilinearImage, right: BilinearImage, uv: np.ndarray, uv_match: np.ndarray,
                 offs: np.ndarray) -> np.ndarray:
    """[a, b] of I_right ~ e^a I_left + b from the pattern intensities of matched points
    (least squares; [log(std ratio), mean offset] fallback with fewer than 10 matches)."""
    if len(uv) >= 10:
        il = left.sample(uv[:, None, 0] + PATTERN[:, 0], uv[:, None, 1] + PATTERN[:, 1])
        ir = right.sample(uv_match[:, None, 0] + offs[:, 0], uv_match[:, None, 1] + offs[:, 1])
        ok = il[3] & ir[3]
        x, y = il[0][ok], ir[0][ok]
        if x.size >= 40 and np.var(x) > 1e-6:
            slope = np.cov(x, y, bias=True)[0, 1] / np.var(x)
            if 0.2 < slope < 5.0:
                return np.array([np.log(slope), y.mean() - slope * x.mean()])
    sl = _std_ratio(left, right)
    return np.array([np.log(sl), right.image.mean() - sl * left.image.mean()])


def _std_ratio(left: BilinearImage, right: BilinearImage) -> float:
    """Ratio of the right image's intensity standard deviation to the left's (each at least
    1e-3): the gain guess of the depth search and ``right_affine``'s fallback. OpenCV's
    standard deviation: 0.2 instead of numpy's 0.6 ms at 752x480."""
    sd = [max(float(cv2.meanStdDev(im.image)[1][0, 0]), 1e-3) for im in (right, left)]
    return sd[0] / sd[1]


# one worker: the points of a keyframe are built while the main thread runs the
# keyframe's smoother update (their first reader is the next frame); the kernels release
# the GIL (factors.jit), so the two overlap on two cores
_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vio-keyframe")


def build_keyframe(k: int, t_ns: int, left_raw: np.ndarray, right_raw: np.ndarray | str | Path,
                   rig: StereoRig, cfg: DirectConfig, background: bool = False) -> KeyframeData:
    """Undistort, select ``cfg.select.n_points`` candidates, search their depths along the
    epipolar lines in the right image (seed eq. 4.1/4.2) and keep those that pass the
    search checks and ``cfg.points`` depth range; estimate the right image's affine.
    ``right_raw``: the right image or its file. ``background``: the points and the right
    image are built in a worker thread (same result, read through ``KeyframeData``'s
    properties); the left image and its pyramid are built here."""
    left_img = rig.undistort_one(left_raw, 0)
    kd = KeyframeData(k, t_ns, rig.K0, left_img, BilinearImage(left_img), None)
    pyr = kd.pyramid(cfg.track.levels) if cfg.track.enabled else (kd.left,)   # TrackFrame uses it meanwhile
    kd._points = _WORKER.submit(_points, pyr, right_raw, rig, cfg) if background else _points(pyr, right_raw, rig, cfg)
    return kd


def _points(pyr: tuple[BilinearImage, ...], right_raw: np.ndarray | str | Path, rig: StereoRig,
            cfg: DirectConfig) -> KeyframePoints:
    """The candidate points of the undistorted pair (left image's pyramid ``pyr``, right
    image or its file ``right_raw``) and their TrackFrame reference (``build_keyframe``)."""
    L = pyr[0]
    raw = (read_image(right_raw, rig.cam1) if isinstance(right_raw, (str, Path))
           else rig.cam1.check_resolution(right_raw, "cam1 image"))
    R = BilinearImage(rig.undistort_one(raw, 1))
    sel = select_points(L.image, cfg.select, (L._stack[..., 1], L._stack[..., 2]))
    gain = np.log(_std_ratio(L, R))
    ep = epipolar_search(L, R, sel.uv, rig.K0, rig.K1, rig.T_c1_c0, cfg.epipolar, (gain, 0.0))
    pc = cfg.points
    ok = ep.ok & (ep.idepth >= 1.0 / pc.max_depth_m) & (ep.idepth <= 1.0 / pc.min_depth_m)
    Rm = rig.T_c1_c0.rotation().matrix()
    offs = PATTERN @ (rig.K1.K @ Rm @ np.linalg.inv(rig.K0.K))[:2, :2].T
    ab_r = right_affine(L, R, sel.uv[ok], ep.uv_match[ok], offs)
    uv, idepth, var = sel.uv[ok], ep.idepth[ok], ep.variance[ok]
    ref = make_reference(pyr, uv, idepth, rig.K0, var, (0.0, 0.0), cfg.track) if cfg.track.enabled else None
    return KeyframePoints(R, uv, idepth, var, ab_r, len(sel), ref, sel.uv[~ok])
