"""The image stage: a ``FramePacket`` with images -> the same packet with features.

Wraps the KLT front end (``vio.frontend``): loads the images lazily, predicts the
LK search from the gyro rotation since the previous frame, and attaches cam0
features with their cam1 matches (``FeatureFrame.right_uv``) for the backend. With
``FrontendConfig.stereo_at = "keyframe"`` and a keyframe policy it decides the keyframes
itself (``FramePacket.keyframe``) and decodes and matches cam1 at those frames only.
"""

from __future__ import annotations

import dataclasses
import functools
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from vio.frontend import Frontend
from vio.frontend.camera import camera_rotation
from vio.frontend.config import FrontendConfig
from vio.errors import DataError
from vio.imu import rotate
from vio.io.euroc import image_exists, read_image
from vio.io.types import CameraCalib, ImuData
from vio.keyframes import KeyframePolicy
from vio.sync import FramePacket, carry_imu

if TYPE_CHECKING:
    from vio.backend.config import KeyframeConfig


def blank_image(img: np.ndarray, min_std: float) -> bool:
    """Whether ``img`` (gray, uint8) shows nothing: the standard deviation of every 4th
    pixel of every 4th row under ``min_std`` gray levels (black, saturated, a covered
    lens; real EuRoC frames 53-83). ``min_std`` 0: never."""
    return min_std > 0 and float(img[::4, ::4].std()) < min_std


def drop_blank(pkt: FramePacket, min_std: float) -> FramePacket:
    """``pkt`` (its cam0 image decoded, ``images[0]``) marked ``dropped``, its images let
    go, when that image shows nothing (:func:`blank_image`); else ``pkt``."""
    if not blank_image(pkt.images[0], min_std):
        return pkt
    where = pkt.image_files[0] if pkt.image_files else f"cam0 image at t={pkt.t_ns} ns"
    return dataclasses.replace(pkt, images=(), dropped=f"{where}: the image shows nothing "
                                                      f"(intensity spread under {min_std:g} gray levels)")


def gyro_rotation(imu: ImuData) -> np.ndarray:
    """Body rotation ``R_b(t0)_b(t1)`` (3, 3) over a packet's IMU segment (raw gyro,
    midpoint rule); bias-free, which is ample for an LK initial guess."""
    return rotate(gtsam.Rot3(), imu.t_ns, 0.5 * (imu.gyro[1:] + imu.gyro[:-1])).matrix()


class ImageStage:
    """Adds ``FeatureFrame`` observations to image packets (mono or stereo).

    ``keyframes``: the pipeline's keyframe policy. With it and
    ``FrontendConfig.stereo_at = "keyframe"`` (stereo) the stage applies the policy to
    its own features and marks every packet's ``keyframe``; cam1 is decoded and matched
    at keyframes, and at every frame of the first ``every_frame_s`` seconds (the stereo
    initialization's window, which aligns every frame). Real MH_01 stereo: 95 keyframes
    in 320 frames."""

    def __init__(self, cam0: CameraCalib, cam1: CameraCalib | None,
                 cfg: FrontendConfig | None = None, keyframes: KeyframeConfig | None = None,
                 every_frame_s: float = 0.0) -> None:
        self.cam0 = cam0
        self.stereo = cam1 is not None
        self._calibs = (cam0,) if cam1 is None else (cam0, cam1)
        self.frontend = Frontend(cam0, cam1, cfg)
        self._T_b_c = cam0.T_b_c.matrix()
        self._first = True
        self._skipped: list[FramePacket] = []   # dropped frames since the last tracked one
        self._pool: ThreadPoolExecutor | None = None
        at_keyframes = self.stereo and self.frontend.cfg.stereo_at == "keyframe" and keyframes is not None
        self._policy = KeyframePolicy(keyframes, cam0.intrinsics[0]) if at_keyframes else None
        self._every_frame_ns = int(every_frame_s * 1e9)
        self._t_first: int | None = None

    def load(self, pkt: FramePacket) -> FramePacket:
        """``pkt`` with its images decoded (``vio.overlap``'s worker runs this a packet
        ahead, in a thread, while the previous packet is tracked); an image that does not
        decode, or a cam0 image that shows nothing (:func:`blank_image`), marks the frame
        ``dropped`` (``Pipeline.process`` carries its IMU over).
        With a keyframe policy cam1 is only checked to exist here: ``_finish`` decodes it
        where it is matched (a cam1 file that exists but does not decode drops the frame
        there)."""
        if pkt.dropped or not (pkt.images or pkt.image_files):
            return pkt
        if not pkt.images:
            files = pkt.image_files[:2 if self.stereo else 1]
            lazy = self._policy is not None and len(files) > 1
            try:
                images = tuple(read_image(p) for p in (files[:1] if lazy else files))
                if lazy and not image_exists(files[1]):
                    raise DataError(files[1], "image missing or unreadable")
            except DataError as exc:
                return dataclasses.replace(pkt, dropped=str(exc))
            for path, img, calib in zip(files, images, self._calibs):
                calib.check_resolution(img, path)
            pkt = dataclasses.replace(pkt, images=images)
        return drop_blank(pkt, self.frontend.cfg.min_image_std)

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
            self._skipped.append(pkt)
            return pkt, None, None
        imgs = pkt.images
        if not imgs:
            raise ValueError(f"frame {pkt.stamp_ns}: no image to track")
        # the interval since the last tracked frame, as the pipeline carries it (its IMU
        # and gaps joined; the packet itself goes on unchanged)
        since = functools.reduce(carry_imu, [*self._skipped, pkt])
        self._skipped = []
        R = None if self._first else camera_rotation(gyro_rotation(since.imu), self._T_b_c)
        self._first = False
        mono = self.frontend.track(pkt.t_ns, imgs[0], R)
        if not self.stereo:
            return pkt, mono, None
        if self._policy is None:
            return pkt, mono, imgs[1] if len(imgs) > 1 else None
        pkt = dataclasses.replace(pkt, keyframe=self._decide(since, mono))
        if self._t_first is None:
            self._t_first = pkt.t_ns
        if pkt.keyframe or pkt.t_ns - self._t_first < self._every_frame_ns:
            return pkt, mono, imgs[1] if len(imgs) > 1 else pkt.image_files[1]
        return pkt, mono, None

    def _decide(self, pkt: FramePacket, mono) -> bool:
        """The keyframe policy on this frame's tracks; ``pkt`` carries the IMU of its dropped
        predecessors (``Pipeline.step``: a frame where the IMU resumes is one too)."""
        kf = pkt.imu_resumed or self._policy.due(pkt.t_ns, mono.ids, mono.uv)
        if kf:
            self._policy.reset(pkt.t_ns, mono.ids, mono.uv)
        return kf

    def _finish(self, pkt: FramePacket, mono, img1) -> FramePacket:
        if mono is None:
            return dataclasses.replace(pkt, features=None, images=())
        if img1 is not None and not isinstance(img1, np.ndarray):   # decoded here (load: lazy)
            try:
                img1 = read_image(img1, self._calibs[1])
            except DataError as exc:
                self.frontend.match(mono, None)
                return dataclasses.replace(pkt, features=None, images=(), dropped=str(exc))
        tf = self.frontend.match(mono, img1)
        fr = tf.to_feature_frame(0)
        if self.stereo:
            fr = dataclasses.replace(fr, right_uv=np.asarray(tf.right_uv, float).copy(),
                                     right_velocity=np.asarray(tf.right_velocity, float).copy(),
                                     right_row=np.asarray(tf.right_px[:, 1], float).copy())
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
