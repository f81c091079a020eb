"""DSO-style selection of high-gradient pixels spread over the image.

Per ``block`` x ``block`` region the gradient-magnitude median plus ``grad_offset``
is the local threshold (smoothed over the 3x3 neighbouring blocks, as DSO's
PixelSelector). The image is cut into cells of ``pot`` pixels; each cell keeps its
strongest pixel above threshold. Where a 2-pot cell got nothing, its strongest pixel
above ``level_factor`` x threshold is taken, and likewise for 4-pot cells with
``level_factor^2`` (DSO's three levels, which fill weakly textured regions with
sparser points). ``pot`` is searched so the count is close to ``n_points``.
DSO's random-direction dot product is replaced by the plain gradient magnitude.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.image_ops import central_gradient
from vio.direct.config import SelectConfig


@dataclass(frozen=True, eq=False)
class SelectedPoints:
    """Selected pixels: ``uv`` (N, 2) float (column, row), ``grad`` (N,) gradient
    magnitude (intensity/pixel), ``level`` (N,) 0/1/2 = found at cell size pot, 2 pot, 4 pot;
    ``pot`` the cell size used."""

    uv: np.ndarray
    grad: np.ndarray
    level: np.ndarray
    pot: int

    def __len__(self) -> int:
        return int(self.uv.shape[0])


def gradient_threshold(grad: np.ndarray, block: int, offset: float) -> np.ndarray:
    """Per-pixel threshold: 3x3-block-smoothed median of ``grad`` over ``block``-sized blocks + offset."""
    h, w = grad.shape
    nby, nbx = -(-h // block), -(-w // block)
    pad = np.full((nby * block, nbx * block), np.nan)
    pad[:h, :w] = grad
    blocks = pad.reshape(nby, block, nbx, block).transpose(0, 2, 1, 3).reshape(nby, nbx, -1)
    srt = np.sort(blocks, axis=-1)                  # NaN (padding) sorts last
    n = np.maximum((~np.isnan(blocks)).sum(-1), 1)
    lo = np.take_along_axis(srt, ((n - 1) // 2)[..., None], -1)[..., 0]
    hi = np.take_along_axis(srt, (n // 2)[..., None], -1)[..., 0]
    med = 0.5 * (lo + hi) + offset                  # = nanmedian, without its overhead
    p = np.pad(med, 1, mode="edge")
    smooth = sum(p[i:i + nby, j:j + nbx] for i in range(3) for j in range(3)) / 9.0
    return np.repeat(np.repeat(smooth, block, 0), block, 1)[:h, :w]


def _best_per_cell(score: np.ndarray, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel index of the max-score pixel of every cell (-1 where all scores < 0),
    and a per-cell map of that choice (ny, nx)."""
    h, w = score.shape
    ny, nx = -(-h // cell), -(-w // cell)
    pad = np.full((ny * cell, nx * cell), -1.0)
    pad[:h, :w] = score
    cells = pad.reshape(ny, cell, nx, cell).transpose(0, 2, 1, 3).reshape(ny, nx, -1)
    arg = np.argmax(cells, axis=-1)
    best = np.take_along_axis(cells, arg[..., None], -1)[..., 0]
    cy, cx = np.divmod(arg, cell)
    rows = np.arange(ny)[:, None] * cell + cy
    cols = np.arange(nx)[None, :] * cell + cx
    idx = np.where(best >= 0, rows * w + cols, -1)
    return idx, best >= 0


def _select_with_pot(grad: np.ndarray, thr: np.ndarray, pot: int, cfg: SelectConfig):
    h, w = grad.shape
    chosen, levels = [], []
    taken = np.zeros((h, w), bool)
    for lev in range(cfg.levels):
        cell = pot * 2 ** lev
        score = np.where(grad > thr * cfg.level_factor ** lev, grad, -1.0)
        idx, found = _best_per_cell(score, cell)
        # skip cells that already hold a point from a finer level (DSO: take the
        # coarse candidate only where the finer levels found nothing)
        ny, nx = idx.shape
        tk = np.zeros((ny * cell, nx * cell), bool)
        tk[:h, :w] = taken
        occupied = tk.reshape(ny, cell, nx, cell).any(axis=(1, 3))
        new = idx[found & ~occupied]
        chosen.append(new)
        levels.append(np.full(new.shape, lev))
        taken.flat[new] = True
    idx = np.concatenate(chosen)
    return idx, np.concatenate(levels)


def select_points(image: np.ndarray, config: SelectConfig = SelectConfig()) -> SelectedPoints:
    """Select about ``config.n_points`` well-spread high-gradient pixels of a (H, W) image."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 2 * config.border + 8:
        raise ValueError(f"select_points needs a (H, W) grey image larger than the border, got {img.shape}")
    gx, gy = central_gradient(img)
    grad = np.hypot(gx, gy)
    thr = gradient_threshold(grad, config.block, config.grad_offset)
    b = config.border
    grad_in = grad.copy()
    grad_in[:b], grad_in[-b:], grad_in[:, :b], grad_in[:, -b:] = 0, 0, 0, 0
    area = (img.shape[0] - 2 * b) * (img.shape[1] - 2 * b)
    pot = int(np.clip(round(np.sqrt(area / config.n_points)), 1, 64))
    best = None
    for _ in range(8):  # a few secant-like steps on pot (count ~ 1 / pot^2)
        idx, lev = _select_with_pot(grad_in, thr, pot, config)
        if best is None or abs(len(idx) - config.n_points) < abs(len(best[0]) - config.n_points):
            best = (idx, lev, pot)
        if len(idx) == 0:
            new_pot = max(1, pot // 2)
        else:
            new_pot = int(np.clip(round(pot * np.sqrt(len(idx) / config.n_points)), 1, 64))
        if new_pot == pot or abs(len(idx) - config.n_points) <= 0.1 * config.n_points:
            break
        pot = new_pot
    idx, lev, pot = best
    if len(idx) > config.n_points:  # trim the weakest surplus, keeping the spread roughly uniform
        keep = np.sort(np.argsort(-grad.flat[idx], kind="stable")[:config.n_points])
        idx, lev = idx[keep], lev[keep]
    v, u = np.divmod(idx, img.shape[1])
    return SelectedPoints(np.stack([u, v], 1).astype(np.float64), grad.flat[idx], lev, pot)
