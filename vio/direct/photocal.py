"""Photometric calibration of the direct modes' images (DSO's ``PhotometricUndistorter``).

A camera maps irradiance B to a pixel value I = G(V(x) B) (response G, vignetting V).
With a calibration the direct modes work on ``B' = G^-1(I) / V(x)`` instead of I, so the
photometric residuals compare irradiances; the per-keyframe affine brightness [a, b]
then only absorbs exposure changes. Without one (EuRoC ships none), the affine model
absorbs response and exposure together, and an optional radial vignetting model
V(r) = 1 + v1 r^2 + v2 r^4 (r = distance to the image centre over the half diagonal)
can be configured.

Files (DSO / TUM mono-VO format), looked up next to each camera's ``data.csv`` unless
``PhotoCalConfig`` names them:

* ``pcalib.txt``: G^-1 as 256 whitespace-separated values (irradiance of pixel values
  0..255), monotone increasing; rescaled to [0, 255];
* ``vignette.png``: V at every raw pixel (8 or 16 bit), rescaled to max 1.

Corrections apply to the raw (distorted) image, before undistortion: V is measured in
raw pixel coordinates. Pixels clipped by the sensor stay recognisable: values 0 and
255 keep mapping to the ends of the range before the vignetting division.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.errors import ConfigError

MIN_VIGNETTE = 0.1
"""Vignetting factors below this (image corners of a wide lens) are clamped: dividing by
them would amplify the noise beyond any use."""


@dataclass(frozen=True)
class PhotoCalConfig:
    """Photometric calibration of the direct modes (module docstring). ``pcalib`` /
    ``vignette``: files for cam0 (cam1 reads the same names from its own folder);
    empty: ``pcalib.txt`` / ``vignette.png`` next to each camera's ``data.csv`` when
    present. ``vignette_poly`` (v1, v2): the radial model used when no vignette file
    exists ((0, 0): none). ``use_files``: False ignores any file."""

    pcalib: str = ""
    vignette: str = ""
    vignette_poly: tuple[float, float] = (0.0, 0.0)
    use_files: bool = True

    def __post_init__(self) -> None:
        if len(self.vignette_poly) != 2:
            raise ValueError("PhotoCalConfig: vignette_poly needs two coefficients (v1, v2)")


@dataclass(frozen=True, eq=False)
class PhotometricCalibration:
    """``inv_response`` (256,) G^-1 in [0, 255] or None (identity); ``vignette`` (H, W)
    in (0, 1] or None; ``source`` says where they came from (for the log)."""

    inv_response: np.ndarray | None = None
    vignette: np.ndarray | None = None
    source: str = "none"

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Irradiance image (float64) of a raw (H, W) uint8 image."""
        img = np.asarray(image)
        if self.inv_response is not None:
            out = self.inv_response[np.clip(img, 0, 255).astype(np.intp)]
        else:
            out = img.astype(np.float64)
        if self.vignette is not None:
            if self.vignette.shape != out.shape:
                raise ValueError(f"vignette {self.vignette.shape} does not match image {out.shape}")
            out = out / self.vignette
        return out

    @property
    def identity(self) -> bool:
        return self.inv_response is None and self.vignette is None


def read_pcalib(path: Path) -> np.ndarray:
    """G^-1 (256,) from a DSO ``pcalib.txt``, rescaled to [0, 255]; errors name the file."""
    try:
        vals = np.array([float(x) for x in Path(path).read_text().split()])
    except ValueError as exc:
        raise ConfigError(f"{path}: line 1: not a list of numbers ({exc})") from None
    if vals.shape != (256,):
        raise ConfigError(f"{path}: line 1: expected 256 values of G^-1, got {vals.size}")
    if not np.all(np.diff(vals) > 0):
        raise ConfigError(f"{path}: line 1: the inverse response must increase strictly")
    return 255.0 * (vals - vals[0]) / (vals[-1] - vals[0])


def read_vignette(path: Path) -> np.ndarray:
    """V (H, W) from a vignette image (8/16 bit), rescaled to max 1, clamped at
    ``MIN_VIGNETTE``."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ConfigError(f"{path}: not a single-channel image")
    v = img.astype(np.float64)
    if v.max() <= 0:
        raise ConfigError(f"{path}: the vignette image is all zero")
    return np.maximum(v / v.max(), MIN_VIGNETTE)


def radial_vignette(shape: tuple[int, int], v1: float, v2: float) -> np.ndarray:
    """V(r) = 1 + v1 r^2 + v2 r^4 over an (H, W) image (r: distance to the centre over
    the half diagonal), rescaled to max 1 and clamped at ``MIN_VIGNETTE``."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2) / (0.25 * (w * w + h * h))
    v = 1.0 + v1 * r2 + v2 * r2 * r2
    if v.min() <= 0:
        raise ConfigError(f"vignette_poly ({v1}, {v2}) is not positive over the image")
    return np.maximum(v / v.max(), MIN_VIGNETTE)


def load_calibration(cam_dir: Path | None, shape: tuple[int, int], cfg: PhotoCalConfig,
                     cam0: bool = True) -> PhotometricCalibration:
    """The calibration of one camera: files named by ``cfg`` (cam0) or found in
    ``cam_dir``, else the radial model, else the identity."""
    def find(named: str, default: str) -> Path | None:
        if not cfg.use_files:
            return None
        if named and cam0:
            p = Path(named)
            if not p.exists():
                raise ConfigError(f"{p}: photometric calibration file not found")
            return p
        p = cam_dir / (Path(named).name if named else default) if cam_dir is not None else None
        return p if p is not None and p.exists() else None

    pc, vg = find(cfg.pcalib, "pcalib.txt"), find(cfg.vignette, "vignette.png")
    inv = read_pcalib(pc) if pc is not None else None
    if vg is not None:
        vig = read_vignette(vg)
    elif any(cfg.vignette_poly):
        vig = radial_vignette(shape, *cfg.vignette_poly)
    else:
        vig = None
    src = ", ".join([str(p) for p in (pc, vg) if p is not None]
                    + (["radial vignetting model"] if vg is None and vig is not None else [])) or "none"
    return PhotometricCalibration(inv, vig, src)
