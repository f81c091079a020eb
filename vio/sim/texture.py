"""Procedural surface textures with real structure, and their mip pyramids.

Each surface gets a unique gray texture (float32, 0..255) at ``texels_per_m``:
multi-octave smooth noise (blobs for direct photometric methods), many
anti-aliased shapes at sizes from 3 cm to 45 cm (rectangles, discs, triangles,
checker patches, strokes: corners and edges for Shi-Tomasi/KLT), tile joints on
floor and ceiling, faint fine grain, and a slight blur to band-limit it.

Texel ``(row j, col i)`` of level 0 is centred at ``(u, v) = ((i + 0.5), (j + 0.5)) /
texels_per_m`` metres; level ``l`` comes from ``cv2.pyrDown`` (texel ``i`` of level
``l`` sits at level-0 texel ``i * 2**l``). The atlas packs every level of every
surface into one flat array for the numba renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.sim.scene import Scene

MIP_LEVELS = 7
_SHIFT = 4  # cv2 fixed-point bits for sub-texel shape coordinates


@dataclass(frozen=True)
class TextureAtlas:
    """``data`` (M,) float32 texels; ``table`` (n_surfaces, MIP_LEVELS, 3) int64 rows
    ``(offset, width, height)`` into ``data`` (row-major); ``texels_per_m`` level-0 density."""

    data: np.ndarray
    table: np.ndarray
    texels_per_m: float

    def level(self, sid: int, lvl: int = 0) -> np.ndarray:
        """Texture image (h, w) of surface ``sid`` at mip level ``lvl`` (a view)."""
        off, w, h = (int(x) for x in self.table[sid, lvl])
        return self.data[off:off + w * h].reshape(h, w)


def _noise(rng: np.random.Generator, w: int, h: int, cell_px: float) -> np.ndarray:
    """Smooth zero-mean unit-ish noise (h, w) with features about ``cell_px`` wide."""
    gw, gh = int(np.ceil(w / cell_px)) + 3, int(np.ceil(h / cell_px)) + 3
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int(gw * cell_px), int(gh * cell_px)), interpolation=cv2.INTER_CUBIC)
    return big[int(cell_px):int(cell_px) + h, int(cell_px):int(cell_px) + w]


def _pts(p: np.ndarray) -> np.ndarray:
    return np.round(p * (1 << _SHIFT)).astype(np.int32)


def _draw_shape(img: np.ndarray, rng: np.random.Generator, size: float, color: int) -> None:
    """One anti-aliased shape of about ``size`` texels at a random place of ``img``."""
    h, w = img.shape
    c = rng.uniform([0, 0], [w, h])
    kind = rng.choice(5, p=[0.33, 0.22, 0.15, 0.12, 0.18])
    ang = rng.uniform(0, np.pi)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    aa = cv2.LINE_AA
    if kind == 0:  # rotated rectangle (often axis aligned, like posters)
        if rng.random() < 0.5:
            rot = np.eye(2)
        half = np.array([size, size * rng.uniform(0.3, 1.0)]) / 2
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half
        cv2.fillConvexPoly(img, _pts(c + corners @ rot.T), color, aa, _SHIFT)
    elif kind == 1:  # ellipse / disc
        axes = (max(1, int(size / 2)), max(1, int(size / 2 * rng.uniform(0.5, 1.0))))
        cv2.ellipse(img, (int(c[0]), int(c[1])), axes, float(np.rad2deg(ang)), 0, 360, color, -1, aa)
    elif kind == 2:  # triangle
        tri = c + rng.uniform(-size / 2, size / 2, (3, 2))
        cv2.fillConvexPoly(img, _pts(tri), color, aa, _SHIFT)
    elif kind == 3:  # 2x2 checker patch: X-corners
        q = size / 2
        other = 255 - color
        for k, (dx, dy) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
            sq = np.array([[0, 0], [q, 0], [q, q], [0, q]]) + [dx * q - q, dy * q - q]
            cv2.fillConvexPoly(img, _pts(c + sq @ rot.T), color if k % 2 == 0 else other, aa, _SHIFT)
    else:  # stroke
        d = rot[:, 0] * size
        thick = int(np.clip(size / 12, 1, 4))
        cv2.line(img, tuple(_pts(c - d / 2)), tuple(_pts(c + d / 2)), color, thick, aa, _SHIFT)


def make_texture(rng: np.random.Generator, size_m: tuple[float, float], density: float,
                 tiles: bool = False) -> np.ndarray:
    """Texture (h, w) float32 in [8, 247] for a ``size_m = (u, v)`` metre surface."""
    w = max(4, int(np.ceil(size_m[0] * density)))
    h = max(4, int(np.ceil(size_m[1] * density)))
    base = rng.uniform(80, 170) + 28 * _noise(rng, w, h, 1.2 * density)
    base += 16 * _noise(rng, w, h, 0.35 * density) + 8 * _noise(rng, w, h, 0.1 * density)
    img = np.clip(base, 0, 255).astype(np.uint8)
    area = size_m[0] * size_m[1]
    sizes = np.sort(np.exp(rng.uniform(np.log(0.03), np.log(0.45), int(28 * area) + 4)))[::-1]
    for s in sizes:
        _draw_shape(img, rng, s * density, int(rng.integers(0, 256)))
    if tiles:
        step = 0.6 * density
        for x in np.arange(rng.uniform(0, step), w, step):
            cv2.line(img, (int(x), 0), (int(x), h - 1), 40, max(1, int(density / 80)))
        for y in np.arange(rng.uniform(0, step), h, step):
            cv2.line(img, (0, int(y)), (w - 1, int(y)), 40, max(1, int(density / 80)))
    out = img.astype(np.float32) + 5 * _noise(rng, w, h, max(1.5, 0.03 * density))
    out = cv2.GaussianBlur(out, (0, 0), 0.7)
    return np.clip(out, 8, 247)


def build_textures(scene: Scene, texels_per_m: float, seed: int) -> TextureAtlas:
    """One texture and mip pyramid per surface of ``scene`` (deterministic for ``seed``)."""
    chunks, table, offset = [], np.zeros((scene.n_surfaces, MIP_LEVELS, 3), np.int64), 0
    for sid in range(scene.n_surfaces):
        rng = np.random.default_rng([seed, 3, sid])
        tiles = scene.names[sid] in ("floor", "ceiling")
        img = make_texture(rng, scene.surface_extent(sid), texels_per_m, tiles)
        for lvl in range(MIP_LEVELS):
            if lvl > 0 and min(img.shape) >= 2:
                img = cv2.pyrDown(img)
            h, w = img.shape
            table[sid, lvl] = (offset, w, h)
            chunks.append(img.ravel())
            offset += w * h
    return TextureAtlas(np.concatenate(chunks).astype(np.float32), table, float(texels_per_m))
