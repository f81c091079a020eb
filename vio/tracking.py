"""The image stage: a ``FramePacket`` with images -> the same packet with features.

Wraps the KLT front end (``vio.frontend``): loads the images lazily, predicts the
LK search from the gyro rotation since the previous frame, and attaches cam0
features with their cam1 matches (``FeatureFrame.right_uv``) for the backend.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import Future, ThreadPoolExecutor

import gtsam
import numpy as np

from vio.frontend import Frontend
from vio.frontend.camera import camera_rotation
from vio.frontend.config import FrontendConfig
from vio.errors import DataError
from vio.imu import concat
from vio.io.euroc import read_image
from vio.io.types import CameraCalib, ImuData
from vio.sync import FramePacket


def gyro_rotation(imu: ImuData) -> np.ndarray:
    """Body rotation ``R_b(t0)_b(t1)`` (3, 3) over a packet's IMU segment (raw gyro,
    midpoint rule); bias-free, which is ample for an LK initial guess."""
    R = gtsam.Rot3()
    dt = np.diff(imu.t_ns) * 1e-9
    w = 0.5 * (imu.gyro[1:] + imu.gyro[:-1])
    for k in range(dt.shape[0]):
        R = R.compose(gtsam.Rot3.Expmap(w[k] * dt[k]))
    return R.matrix()


class ImageStage:
    """Adds ``FeatureFrame`` observations to image packets (mono or stereo)."""

    def __init__(self, cam0: CameraCalib, cam1: CameraCalib | None,
                 cfg: FrontendConfig | None = None) -> None:
        self.cam0 = cam0
        self.stereo = cam1 is not None
        self._calibs = (cam0,) if cam1 is None else (cam0, cam1)
        self.frontend = Frontend(cam0, cam1, cfg)
        self._T_b_c = cam0.T_b_c.matrix()
        self._first = True
        self._skipped: list[ImuData] = []   # IMU of dropped frames since the last tracked one
        self._pool: ThreadPoolExecutor | None = None

    def load(self, pkt: FramePacket) -> FramePacket:
        """``pkt`` with its images decoded (``vio.overlap``'s worker runs this a packet
        ahead, in a thread, while the previous packet is tracked); an image that does not
        decode marks the frame ``dropped`` (``Pipeline.process`` carries its IMU over)."""
        if pkt.images or not pkt.image_files or pkt.dropped:
            return pkt
        files = pkt.image_files[:2 if self.stereo else 1]
        try:
            images = tuple(read_image(p) for p in files)
        except DataError as exc:
            return dataclasses.replace(pkt, dropped=str(exc))
        for path, img, calib in zip(files, images, self._calibs):
            calib.check_resolution(img, path)
        return dataclasses.replace(pkt, images=images)

    def __call__(self, pkt: FramePacket) -> FramePacket:
        return self._finish(*self._track(pkt))

    def submit(self, pkt: FramePacket) -> Future:
        """``self(pkt)`` as a future: cam0 is tracked now, the stereo match runs in this
        stage's own thread (OpenCV releases the GIL), so frame k is matched while frame
        k+1 is tracked. Results are those of ``self(pkt)``; resolve them in order."""
        args = self._track(pkt)
        if not self.stereo:
            fut: Future = Future()
            fut.set_result(self._finish(*args))
            return fut
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="stereo")
        return self._pool.submit(self._finish, *args)

    def _track(self, pkt: FramePacket) -> tuple:
        pkt = self.load(pkt)
        if pkt.dropped:   # the next frame tracks from the last one tracked, rotation included
            self._skipped.append(pkt.imu)
            return pkt, None, None
        imgs = pkt.images
        if not imgs:
            raise ValueError(f"frame {pkt.stamp_ns}: no image to track")
        imu = concat([*self._skipped, pkt.imu]) if self._skipped else pkt.imu
        self._skipped = []
        R = None if self._first else camera_rotation(gyro_rotation(imu), self._T_b_c)
        self._first = False
        img1 = imgs[1] if self.stereo and len(imgs) > 1 else None
        return pkt, self.frontend.track(pkt.t_ns, imgs[0], R), img1

    def _finish(self, pkt: FramePacket, mono, img1: np.ndarray | None) -> FramePacket:
        if mono is None:
            return dataclasses.replace(pkt, features=None, images=())
        tf = self.frontend.match(mono, img1)
        fr = tf.to_feature_frame(0)
        if self.stereo:
            fr = dataclasses.replace(fr, right_uv=np.asarray(tf.right_uv, float).copy(),
                                     right_velocity=np.asarray(tf.right_velocity, float).copy())
        # images decoded from files (``load``) stay here: a pair is ~0.7 MB to send back
        return dataclasses.replace(pkt, features=fr, images=() if pkt.image_files else pkt.images)


def warm_up() -> None:
    """Load the image stage's compiled kernels (PNG decoding, CLAHE, Shi-Tomasi and the
    rest, from Numba's disk cache: ~0.3 s at a worker's first frame) by tracking a small
    synthetic stereo pair through a throw-away front end. ``vio.overlap.prestart``'s
    worker runs this while the main process is still starting up; nothing is kept."""
    import cv2
    from vio.io.png import decode_png_gray8
    rng = np.random.default_rng(0)
    w, h = 192, 144
    tex = cv2.GaussianBlur(rng.integers(0, 256, (h + 8, w + 16)).astype(np.uint8), (5, 5), 1.5)
    img = decode_png_gray8(cv2.imencode(".png", tex)[1].tobytes())
    if img is None:
        img = tex
    cam0 = CameraCalib(gtsam.Pose3(), (150.0, 150.0, w / 2, h / 2), "radial-tangential",
                       (-0.28, 0.07, 0.0, 0.0), (w, h))
    cam1 = dataclasses.replace(cam0, T_b_c=gtsam.Pose3(gtsam.Rot3(), np.array([0.11, 0.0, 0.0])),
                               name="cam1")
    fe = Frontend(cam0, cam1, FrontendConfig())
    for k in range(3):     # a first frame, then tracked ones (temporal LK, new detections)
        left = np.ascontiguousarray(img[4:4 + h, 8 + k:8 + k + w])
        fe.match(fe.track(k * 50_000_000, left, None if k == 0 else np.eye(3)),
                 np.ascontiguousarray(img[4:4 + h, 2 + k:2 + k + w]))
