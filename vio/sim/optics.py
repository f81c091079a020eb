"""What a real camera adds to a rendered frame: lens distortion and motion blur.

``DistortedView(calib)``: the renderer is a pinhole ray caster, so a distorted image is
rendered as a larger pinhole image (the same focal lengths, the principal point moved so
that every distorted pixel's undistorted ray falls inside it) and resampled through the
distortion: output pixel ``(u, v)`` (OpenCV pixel centres) takes the pinhole image at
``K_v [undistort(u, v), 1]`` (bilinear). The textures are mip-mapped for the pinhole
footprint, so the resampling adds no aliasing where the lens magnifies (the centre of a
barrel lens) and blurs slightly where it shrinks (the corners), as a real lens.

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
    ``virtual``: the pinhole camera to render (same pose and focal lengths)."""

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

    def __call__(self, radiance: np.ndarray) -> np.ndarray:
        """The distorted image (H, W) float32 of a ``virtual`` render (Hv, Wv)."""
        return cv2.remap(radiance, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
