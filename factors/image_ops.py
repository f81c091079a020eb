"""Image sampling for the direct (photometric) terms: bilinear intensity and gradient,
image pyramids, and a smooth analytic texture for exact derivative checks.

Pixel convention: integer coordinates are pixel centres; ``u`` is the column
(x, rightwards) and ``v`` the row (y, downwards), as in DSO. All samplers share one
interface, ``sample(u, v) -> (I, gx, gy, valid)`` with arrays of the broadcast shape
of ``u`` and ``v``: intensity, its derivatives d I / d u and d I / d v (intensity
units per pixel), and a validity mask. Invalid samples hold finite garbage (zeros)
and must be masked by the caller; a sampler never raises for out-of-image points.

Pure numpy (no cv2): ``factors/`` is the math layer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from factors.jit import njit

GradientMode = Literal["central", "exact"]


class ImageSampler(Protocol):
    """What the photometric residuals need from an image."""

    width: int
    height: int

    def sample(self, u: np.ndarray, v: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...


def central_gradient(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients (gx, gy) of a (H, W) image, zero on the border rows/cols
    (the gradient planes of :func:`_gradient_stack`, as views)."""
    stack = _gradient_stack(np.ascontiguousarray(img, dtype=np.float64))
    return stack[..., 1], stack[..., 2]


@njit
def _gradient_stack(img):
    """(H, W, 3) [I, gx, gy] of a float64 (H, W) image, gx = (I[u+1] - I[u-1]) / 2 and
    gy likewise, zero on the border columns / rows; one pass (np.stack of separate planes
    cost ~2 ms per 752x480 image, 10 per keyframe)."""
    H, W = img.shape
    out = np.empty((H, W, 3))   # every element written below (zeroing first: +0.2 ms)
    for v in range(H):
        for u in range(W):
            out[v, u, 0] = img[v, u]
            out[v, u, 1] = 0.5 * (img[v, u + 1] - img[v, u - 1]) if 0 < u < W - 1 else 0.0
            out[v, u, 2] = 0.5 * (img[v + 1, u] - img[v - 1, u]) if 0 < v < H - 1 else 0.0
    return out


@dataclass(frozen=True, eq=False)
class BilinearImage:
    """A grid image sampled bilinearly.

    ``gradient="central"`` (DSO): the gradient is the bilinear interpolation of the
    central-difference gradient images. It is smooth in (u, v) but is *not* the
    derivative of the interpolated intensity, so numeric derivatives of the residual
    disagree with it at the O(texture curvature) level. ``gradient="exact"``: the
    gradient is the derivative of the bilinear interpolant itself, exact inside each
    pixel cell and discontinuous across cell boundaries (use it for Jacobian checks
    at states away from cell boundaries).

    Valid samples satisfy ``1 <= u < W - 2`` and ``1 <= v < H - 2`` so that all four
    corners and their central differences exist.
    """

    image: np.ndarray
    gradient: GradientMode = "central"
    _stack: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        img = np.asarray(self.image, dtype=np.float64)
        if img.ndim != 2 or min(img.shape) < 4:
            raise ValueError(f"BilinearImage needs a (H, W) image with H, W >= 4, got {img.shape}")
        img = np.ascontiguousarray(img)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "_stack", _gradient_stack(img))

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    def sample(self, u: np.ndarray, v: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        if u.shape != v.shape:
            u, v = np.broadcast_arrays(u, v)
        w = self.width
        valid = (u >= 1.0) & (u < w - 2.0) & (v >= 1.0) & (v < self.height - 2.0)
        all_valid = bool(valid.all())
        if not all_valid:
            u = np.where(valid, u, 1.0)
            v = np.where(valid, v, 1.0)
        u0 = u.astype(np.intp)  # == floor on the valid range (u >= 1)
        v0 = v.astype(np.intp)
        fx = (u - u0)[..., None]
        fy = (v - v0)[..., None]
        flat = self._stack.reshape(-1, 3)
        i00 = v0 * w + u0
        c00, c10 = flat[i00], flat[i00 + 1]
        c01, c11 = flat[i00 + w], flat[i00 + w + 1]
        top = c00 + fx * (c10 - c00)
        bot = c01 + fx * (c11 - c01)
        out = top + fy * (bot - top)
        I = out[..., 0]
        if self.gradient == "exact":
            fy0 = fy[..., 0]
            gx = (1.0 - fy0) * (c10[..., 0] - c00[..., 0]) + fy0 * (c11[..., 0] - c01[..., 0])
            gy = bot[..., 0] - top[..., 0]
        else:
            gx, gy = out[..., 1], out[..., 2]
        if not all_valid:
            I, gx, gy = (np.where(valid, a, 0.0) for a in (I, gx, gy))
        return I, gx, gy, valid


@dataclass(frozen=True)
class SmoothTexture:
    """A smooth analytic intensity field (sum of sinusoids and Gaussian blobs).

    ``__call__(x, y) -> (I, dI/dx, dI/dy)`` in whatever planar coordinates the caller
    uses (pixels for an image, metres on a textured plane). Build with ``random``.
    """

    freqs: np.ndarray     # (S, 2) cycles per unit
    phases: np.ndarray    # (S,)
    amps: np.ndarray      # (S,)
    centers: np.ndarray   # (G, 2)
    widths: np.ndarray    # (G,)
    gains: np.ndarray     # (G,)
    offset: float = 128.0

    @staticmethod
    def random(rng: np.random.Generator, extent: float, n_sin: int = 6, n_blobs: int = 40,
               wavelength: tuple[float, float] = (0.08, 0.4), contrast: float = 60.0,
               width: tuple[float, float] = (0.01, 0.04)) -> "SmoothTexture":
        """Random texture over ``[0, extent]^2``; sinusoid wavelengths and Gaussian blob
        widths (std) are fractions of ``extent``."""
        lam = rng.uniform(*wavelength, n_sin) * extent
        ang = rng.uniform(0, np.pi, n_sin)
        freqs = np.stack([np.cos(ang), np.sin(ang)], 1) / lam[:, None]
        return SmoothTexture(
            freqs=freqs, phases=rng.uniform(0, 2 * np.pi, n_sin),
            amps=rng.uniform(0.3, 1.0, n_sin) * contrast / n_sin * 2.0,
            centers=rng.uniform(-0.1, 1.1, (n_blobs, 2)) * extent,
            widths=rng.uniform(*width, n_blobs) * extent,
            gains=rng.uniform(-1.0, 1.0, n_blobs) * contrast)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)[..., None]
        y = np.asarray(y, dtype=np.float64)[..., None]
        arg = 2 * np.pi * (self.freqs[:, 0] * x + self.freqs[:, 1] * y) + self.phases
        s, c = np.sin(arg), np.cos(arg)
        I = self.offset + (self.amps * s).sum(-1)
        gx = (self.amps * c * 2 * np.pi * self.freqs[:, 0]).sum(-1)
        gy = (self.amps * c * 2 * np.pi * self.freqs[:, 1]).sum(-1)
        dx = x - self.centers[:, 0]
        dy = y - self.centers[:, 1]
        e = self.gains * np.exp(-(dx * dx + dy * dy) / (2 * self.widths ** 2))
        I = I + e.sum(-1)
        gx = gx - (e * dx / self.widths ** 2).sum(-1)
        gy = gy - (e * dy / self.widths ** 2).sum(-1)
        return I, gx, gy

    def grid(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """The intensity on the grid ``ys x xs``, (len(ys), len(xs)): the same field as
        ``__call__``, evaluated separably (each sinusoid by the angle-sum identity, each
        blob as a product of 1-D Gaussians), two matrix products instead of a per-pixel sum."""
        x = np.asarray(xs, dtype=np.float64)[None, :]
        y = np.asarray(ys, dtype=np.float64)[:, None]
        ax = 2 * np.pi * self.freqs[:, 0][:, None] * x                  # (S, W)
        ay = 2 * np.pi * self.freqs[:, 1] * y + self.phases             # (H, S)
        I = (np.sin(ay) * self.amps) @ np.cos(ax) + (np.cos(ay) * self.amps) @ np.sin(ax)
        two_w2 = 2 * self.widths ** 2
        gx = np.exp(-(x - self.centers[:, 0][:, None]) ** 2 / two_w2[:, None])   # (G, W)
        gy = np.exp(-(y - self.centers[:, 1]) ** 2 / two_w2) * self.gains        # (H, G)
        return self.offset + I + gy @ gx


@dataclass(frozen=True)
class AnalyticImage:
    """An image given by a smooth function of pixel coordinates, with its exact gradient.

    Used for derivative checks: residuals built on it are C-infinity in the state.
    Validity mirrors ``BilinearImage`` (same margins) so masks behave the same.
    """

    texture: SmoothTexture
    width: int
    height: int

    def sample(self, u: np.ndarray, v: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
        valid = (u >= 1.0) & (u < self.width - 2.0) & (v >= 1.0) & (v < self.height - 2.0)
        I, gx, gy = self.texture(u, v)
        return (np.where(valid, I, 0.0), np.where(valid, gx, 0.0),
                np.where(valid, gy, 0.0), valid)

    def render(self) -> np.ndarray:
        """The function sampled at every pixel centre, (H, W) float64."""
        return self.texture.grid(np.arange(self.width, dtype=np.float64),
                                 np.arange(self.height, dtype=np.float64))


def downsample2(img: np.ndarray) -> np.ndarray:
    """Halve an image by 2x2 block averaging (odd trailing row/column dropped)."""
    img = np.asarray(img, dtype=np.float64)
    h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
    a = img[:h, :w]
    return 0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2])


def pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    """``levels`` images, level 0 the input (as float64), each next one half the size.

    Level-l pixel ``(u_l, v_l)`` sees level-0 ``((u_l + 0.5) 2^l - 0.5, ...)``; see
    ``scale_intrinsics`` and ``scale_pixels``.
    """
    if levels < 1:
        raise ValueError(f"pyramid needs levels >= 1, got {levels}")
    out = [np.asarray(img, dtype=np.float64)]
    for _ in range(levels - 1):
        if min(out[-1].shape) < 8:
            raise ValueError(f"image {img.shape} too small for {levels} pyramid levels")
        out.append(downsample2(out[-1]))
    return out


def scale_intrinsics(fx: float, fy: float, cx: float, cy: float, level: int
                     ) -> tuple[float, float, float, float]:
    """Pinhole intrinsics of pyramid level ``level`` (pixel-centre convention)."""
    s = 0.5 ** level
    return fx * s, fy * s, (cx + 0.5) * s - 0.5, (cy + 0.5) * s - 0.5


def scale_pixels(uv: np.ndarray, level: int) -> np.ndarray:
    """Level-0 pixel coordinates (..., 2) to pyramid level ``level``."""
    return (np.asarray(uv, dtype=np.float64) + 0.5) * 0.5 ** level - 0.5
