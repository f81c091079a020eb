"""What a real camera adds to a rendered frame: lens distortion and motion blur.

``DistortedView(calib)``: the renderer is a pinhole ray caster, so a distorted image is
rendered as a larger pinhole image (the same focal lengths, the principal point moved so
that every distorted pixel's undistorted ray falls inside it) and resampled through the
distortion: output pixel ``(u, v)`` (OpenCV pixel centres) takes the pinhole image at
``K_v [undistort(u, v), 1]`` (bilinear). The textures are mip-mapped for the pinhole
footprint, so the resampling adds no aliasing where the lens magnifies (the centre of a
barrel lens) and blurs slightly where it shrinks (the corners), as a real lens. With a
rolling shutter the sensor's rows are exposed one after the other, and a sensor row is a
curve in the pinhole image (up to ~50 rows from a straight one at the corners of a k1 =
-0.28 lens): ``sensor_row`` gives each pinhole pixel the sensor row it lands on, whose
time the renderer gives it (``vio.sim.render.render``'s ``pose_of``).

``FlightOptics``: the distortion switch, and the exposure duration rendered as motion
blur (``blur_s``, the mean of ``blur_samples`` renders at poses spread evenly over the
exposure, centred on the frame's exposure time).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from vio.frontend.camera import Camera
from vio.io.types import CameraCalib

__all__ = ["FlightOptics", "DistortedView", "blur_offsets"]


@dataclass(frozen=True)
class FlightOptics:
    """``distortion``: render through the source's own camera calibrations (EuRoC:
    radial-tangential, k1 = -0.28) instead of undistorted pinhole cameras; ``blur_s``:
    exposure duration (s) rendered as motion blur, 0 = a sharp instant;
    ``blur_samples``: renders averaged over it."""

    distortion: bool = False
    blur_s: float = 0.0
    blur_samples: int = 5

    def __post_init__(self) -> None:
        if not (0.0 <= self.blur_s < 0.05) or self.blur_samples < 2:
            raise ValueError(f"FlightOptics: need 0 <= blur_s < 0.05 s and blur_samples >= 2, got "
                             f"{self.blur_s}, {self.blur_samples}")


def blur_offsets(optics: FlightOptics) -> np.ndarray:
    """Time offsets (K,) s of the renders averaged into one frame, centred on 0."""
    if optics.blur_s <= 0.0:
        return np.zeros(1)
    return (np.arange(optics.blur_samples) / (optics.blur_samples - 1) - 0.5) * optics.blur_s


class DistortedView:
    """A pinhole render resampled through ``calib``'s distortion (see module docstring).
    ``virtual``: the pinhole camera to render (same pose and focal lengths);
    ``sensor_row`` (Hv, Wv) int64: the sensor row (0..H-1, nearest, clipped) that each
    pixel of the ``virtual`` image lands on through the lens."""

    def __init__(self, calib: CameraCalib) -> None:
        cam = Camera(calib)
        w, h = calib.resolution
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        xy = cam.undistort_px(np.column_stack([u.ravel(), v.ravel()]))      # normalized
        fx, fy = cam.fx, cam.fy
        lo = np.floor(xy.min(axis=0) * (fx, fy)) - 2.0
        hi = np.ceil(xy.max(axis=0) * (fx, fy)) + 2.0
        cx, cy = -lo
        size = (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
        self.virtual = replace(calib, intrinsics=(fx, fy, float(cx), float(cy)), resolution=size,
                               distortion=(0.0, 0.0, 0.0, 0.0), line_time_s=0.0)
        self.map_x = (xy[:, 0] * fx + cx).reshape(h, w).astype(np.float32)
        self.map_y = (xy[:, 1] * fy + cy).reshape(h, w).astype(np.float32)
        wv, hv = size
        xv, yv = np.meshgrid(np.arange(wv, dtype=np.float64), np.arange(hv, dtype=np.float64))
        raw = cam.project_normalized(np.column_stack([(xv.ravel() - cx) / fx, (yv.ravel() - cy) / fy]))
        self.sensor_row = np.clip(np.rint(raw[:, 1]), 0, h - 1).astype(np.int64).reshape(hv, wv)

    def __call__(self, radiance: np.ndarray) -> np.ndarray:
        """The distorted image (H, W) float32 of a ``virtual`` render (Hv, Wv)."""
        return cv2.remap(radiance, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
