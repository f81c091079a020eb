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
        self.frontend = Frontend(cam0, cam1, cfg)
        self._T_b_c = cam0.T_b_c.matrix()
        self._first = True
        self._pool: ThreadPoolExecutor | None = None

    def load(self, pkt: FramePacket) -> FramePacket:
        """``pkt`` with its images decoded (``vio.overlap``'s worker runs this a packet
        ahead, in a thread, while the previous packet is tracked)."""
        if pkt.images or not pkt.image_files:
            return pkt
        files = pkt.image_files[:2 if self.stereo else 1]
        return dataclasses.replace(pkt, images=tuple(read_image(p) for p in files))

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
        imgs = self.load(pkt).images
        if not imgs:
            raise ValueError(f"frame {pkt.stamp_ns}: no image to track")
        R = None if self._first else camera_rotation(gyro_rotation(pkt.imu), self._T_b_c)
        self._first = False
        img1 = imgs[1] if self.stereo and len(imgs) > 1 else None
        return pkt, self.frontend.track(pkt.t_ns, imgs[0], R), img1

    def _finish(self, pkt: FramePacket, mono, img1: np.ndarray | None) -> FramePacket:
        tf = self.frontend.match(mono, img1)
        fr = tf.to_feature_frame(0)
        if self.stereo:
            fr = dataclasses.replace(fr, right_uv=np.asarray(tf.right_uv, float).copy(),
                                     right_velocity=np.asarray(tf.right_velocity, float).copy())
        # images decoded from files (``load``) stay here: a pair is ~0.7 MB to send back
        return dataclasses.replace(pkt, features=fr, images=() if pkt.image_files else pkt.images)
