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

import math
from dataclasses import dataclass

import numpy as np

from factors.image_ops import central_gradient
from factors.jit import njit
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
    smooth = block_threshold(grad, block, offset)
    return np.repeat(np.repeat(smooth, block, 0), block, 1)[:h, :w]


def block_threshold(grad: np.ndarray, block: int, offset: float) -> np.ndarray:
    """The threshold of ``gradient_threshold`` per block, (ceil(H / block), ceil(W / block))."""
    med = _block_medians(np.ascontiguousarray(grad, dtype=np.float64), block) + offset
    nby, nbx = med.shape
    p = np.pad(med, 1, mode="edge")
    return sum(p[i:i + nby, j:j + nbx] for i in range(3) for j in range(3)) / 9.0


@njit
def _block_medians(grad, block):
    """Median of ``grad`` (H, W) over each ``block`` x ``block`` block (clipped at the
    right and bottom edges): the mean of the two middle values of an even count."""
    h, w = grad.shape
    nby, nbx = -(-h // block), -(-w // block)
    med = np.empty((nby, nbx))
    buf = np.empty(block * block)
    tmp = np.empty(block * block)
    counts = np.empty(_BINS, np.int64)
    for by in range(nby):
        for bx in range(nbx):
            y0, x0 = by * block, bx * block
            bh, bw = min(h, y0 + block) - y0, min(w, x0 + block) - x0
            n = bh * bw       # (a counter from 0 typed _ranks' n as a literal too: two versions)
            for y in range(bh):
                for x in range(bw):
                    buf[y * bw + x] = grad[y0 + y, x0 + x]
            lo, hi = _ranks(buf, n, (n - 1) // 2, n // 2, counts, tmp)
            med[by, bx] = 0.5 * (lo + hi)
    return med


_BINS = 64


@njit
def _ranks(buf, n, k0, k1, counts, tmp):
    """The k0-th and k1-th smallest (0-based, k1 - k0 in {0, 1}) of ``buf[:n]``, exactly,
    in O(n): a histogram over [min, max] finds the bins holding those ranks and the
    search narrows to their values (every value of a pass is binned by the same
    expression, so ranks are consistent). ``buf`` is overwritten; ``tmp``: scratch of
    its size. (No sort: np.sort compiled a quicksort, ~1.5 s of the first run, and took
    O(n log n) on skewed blocks that put most values into one bin.)"""
    nb = counts.shape[0]
    src, dst = buf, tmp
    m = n
    while True:
        mn, mx = src[0], src[0]
        for i in range(1, m):
            v = src[i]
            if v < mn:
                mn = v
            elif v > mx:
                mx = v
        if mx == mn:
            return mn, mn
        scale = nb / (mx - mn)
        counts[:] = 0
        for i in range(m):
            counts[min(int((src[i] - mn) * scale), nb - 1)] += 1
        b0, below = 0, 0
        while below + counts[b0] <= k0:
            below += counts[b0]
            b0 += 1
        if k1 > k0 and below + counts[b0] == k1:
            # k0 is the largest value of bin b0, k1 the smallest above it
            lo, hi = mn, mx
            for i in range(m):
                b = min(int((src[i] - mn) * scale), nb - 1)
                if b == b0 and src[i] > lo:
                    lo = src[i]
                elif b > b0 and src[i] < hi:
                    hi = src[i]
            return lo, hi
        k = 0       # both ranks in bin b0 (which cannot hold both the min and the max)
        for i in range(m):
            if min(int((src[i] - mn) * scale), nb - 1) == b0:
                dst[k] = src[i]
                k += 1
        m, k0, k1 = k, k0 - below, k1 - below
        src, dst = dst, src


@njit
def _magnitude(gx, gy):
    """|grad| (H, W) = sqrt(gx^2 + gy^2) per pixel (not ``math.hypot``: its overflow-safe
    libm call made this 4 ms of a 752x480 selection's 11; gradients are far from overflow)."""
    h, w = gx.shape
    out = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            a, b = gx[y, x], gy[y, x]
            out[y, x] = math.sqrt(a * a + b * b)
    return out


@njit
def _select_cells(grad, thr, block, border, pot, factors):
    """DSO's multi-level cell selection (module docstring) for cell size ``pot``, in one
    pass over the (H, W) gradient magnitudes ``grad`` (pixels within ``border`` of the
    edge count as 0). Level l has cells of ``pot 2^l`` px and the threshold ``thr`` (per
    ``block``, ``block_threshold``) times ``factors[l]``; a cell keeps its first (row-major)
    strongest pixel above threshold unless a finer level chose a pixel inside it.
    Returns the flat pixel indices and their levels, level by level, cells row-major."""
    h, w = grad.shape
    L = factors.shape[0]
    ny = np.empty(L, np.int64)
    nx = np.empty(L, np.int64)
    for lev in range(L):
        ny[lev] = -(-h // (pot << lev))
        nx[lev] = -(-w // (pot << lev))
    best = np.full((L, ny[0], nx[0]), -1.0)      # level l uses the [:ny[l], :nx[l]] corner
    arg = np.full((L, ny[0], nx[0]), -1, np.int64)
    col_cell = np.empty((L, w), np.int64)        # cell column of pixel column x, per level
    for lev in range(L):
        for x in range(w):
            col_cell[lev, x] = x // (pot << lev)
    fmin = factors.min()                          # below the loosest level's threshold: no cell
    for y in range(h):
        inner_y = border <= y < h - border
        trow = thr[y // block]
        for x in range(w):
            g = grad[y, x] if inner_y and border <= x < w - border else 0.0
            t = trow[x // block]
            if g <= t * fmin:
                continue
            for lev in range(L):
                if g > t * factors[lev]:
                    cy, cx = y // (pot << lev), col_cell[lev, x]
                    if g > best[lev, cy, cx]:
                        best[lev, cy, cx] = g
                        arg[lev, cy, cx] = y * w + x
    idx = np.empty(L * ny[0] * nx[0], np.int64)
    levs = np.empty(L * ny[0] * nx[0], np.int64)
    taken = np.zeros((L, ny[0], nx[0]), np.bool_)  # a cell holds a point of this or a finer level
    n = 0
    for lev in range(L):
        for cy in range(ny[lev]):
            for cx in range(nx[lev]):
                occupied = False
                if lev > 0:
                    for dy in range(2):
                        for dx in range(2):
                            if 2 * cy + dy < ny[lev - 1] and 2 * cx + dx < nx[lev - 1]:
                                occupied |= taken[lev - 1, 2 * cy + dy, 2 * cx + dx]
                taken[lev, cy, cx] = occupied
                if arg[lev, cy, cx] >= 0 and not occupied:
                    idx[n], levs[n] = arg[lev, cy, cx], lev
                    taken[lev, cy, cx] = True
                    n += 1
    return idx[:n], levs[:n]


def select_points(image: np.ndarray, config: SelectConfig = SelectConfig(),
                  gradients: tuple[np.ndarray, np.ndarray] | None = None) -> SelectedPoints:
    """Select about ``config.n_points`` well-spread high-gradient pixels of a (H, W) image;
    ``gradients`` (gx, gy): its central-difference gradients when already computed
    (``factors.image_ops.central_gradient``, e.g. a ``BilinearImage``'s)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 2 * config.border + 8:
        raise ValueError(f"select_points needs a (H, W) grey image larger than the border, got {img.shape}")
    gx, gy = central_gradient(img) if gradients is None else gradients
    grad = _magnitude(gx, gy)
    thr = block_threshold(grad, config.block, config.grad_offset)
    b = config.border
    area = (img.shape[0] - 2 * b) * (img.shape[1] - 2 * b)
    pot = int(np.clip(round(np.sqrt(area / config.n_points)), 1, 64))
    factors = np.array([config.level_factor ** lev for lev in range(config.levels)])
    best = None
    for _ in range(8):  # a few secant-like steps on pot (count ~ 1 / pot^2)
        idx, lev = _select_cells(grad, thr, config.block, b, pot, factors)
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


def spread(uv: np.ndarray, n: int) -> np.ndarray:
    """Indices of at most ``n`` of the candidates ``uv`` (N, 2), evenly thinned in the
    selection order (which is spatially spread)."""
    if len(uv) <= n:
        return np.arange(len(uv))
    return np.linspace(0, len(uv) - 1, n).round().astype(int)
