"""CLAHE for 8-bit grayscale images: OpenCV's ``createCLAHE(clip, tiles).apply``, bit for bit.

Reference: OpenCV ``modules/imgproc/src/clahe.cpp`` (CLAHE_Impl::apply,
CLAHE_CalcLut_Body<uchar, 256, 0>, CLAHE_Interpolation_Body<uchar, 0>) and
``copyMakeBorder`` (BORDER_REFLECT_101). Identical output checked against OpenCV 5.0
on x86-64 (tests/test_clahe.py).

OpenCV's steps, all reproduced. Grid (tx, ty) tiles. When W % tx or H % ty is nonzero,
the histograms are taken on the image padded REFLECT_101 at the right by tx - W % tx
columns and at the bottom by ty - H % ty rows (so by a whole tx or ty when only the
other side is not divisible); tile size (tw, th) = padded size / grid. Per tile: its
256-bin histogram; when clip > 0, each bin above limit = max(1, int(clip * tw * th /
256)) (float64) is cut to it, the cut total split into total // 256 for every bin and
the remainder r one each to bins 0, s, 2s, ... (s = max(256 // r, 1)) while any is
left; LUT[v] = cvRound(float32(cumsum[v]) * float32(255 / (tw * th))), float32
product, rounded half to even. Each pixel (x, y) of the unpadded image mixes the LUTs
of its 4 nearest tile centres: txf = float32(x) * float32(1 / tw) - 0.5, tx1 =
floor(txf), xa = txf - tx1, xa1 = 1 - xa (float32; likewise ty1, ya, ya1 along y),
tile indices clamped to the grid, out = cvRound((L11[v] * xa1 + L12[v] * xa) * ya1 +
(L21[v] * xa1 + L22[v] * xa) * ya): float32, this order, no fused multiply-adds.

Where the time goes (EuRoC 752x480, 8x8 tiles, one thread): OpenCV 1.1-1.3 ms, here
0.37 ms. Histograms (0.12 ms) count into 4 interleaved copies per tile, so equal
neighbouring pixels do not wait on each other's increment, with unsigned indices (no
negative-index fix-ups; 0.15 ms with them). LUTs and their packing: ~0.05 ms. The 4
LUT bytes a pixel needs are packed into one uint32 per (cell between tile centres,
value): the interpolation (0.19 ms) looks up one word per pixel in a scalar loop, then
mixes the row in a loop LLVM vectorises. LLVM emits no vector gathers for this CPU
(Rocket Lake), so a fused per-pixel loop stays scalar (0.9 ms); the mix in int32, not
the int64 Numba widens small integers to, vectorises twice as wide (0.33 -> 0.24 ms);
unsigned lookup indices 0.24 -> 0.19 ms.

Units: pixels; images (H, W) uint8, row-major, x = column, y = row.
"""

from __future__ import annotations

import cv2
import numpy as np

from factors.jit import njit, njit_inline

_BINS = 256
_COPIES = 4          # interleaved histogram copies per tile


class Clahe:
    """Contrast-limited adaptive histogram equalisation with OpenCV's exact output.

    ``clip_limit``: OpenCV's clipLimit (<= 0: no clipping); ``tiles``: the grid
    (tiles_x, tiles_y) >= 1, OpenCV's tileGridSize. Keeps working buffers between
    calls: use one instance per thread."""

    def __init__(self, clip_limit: float = 3.0, tiles: tuple[int, int] = (8, 8)) -> None:
        tiles_x, tiles_y = (int(t) for t in tiles)
        if tiles_x < 1 or tiles_y < 1:
            raise ValueError(f"Clahe: tiles must be >= 1, got {tiles}")
        self.clip_limit = float(clip_limit)
        self.tiles = (tiles_x, tiles_y)
        self._hist = np.empty((tiles_y, tiles_x * _COPIES * _BINS), dtype=np.int32)
        self._lut = np.empty((tiles_y, tiles_x, _BINS), dtype=np.uint8)
        self._packed = np.empty((tiles_y + 1, (tiles_x + 1) * _BINS), dtype=np.uint32)
        self._shape: tuple[int, ...] = ()
        self._layout: tuple = ()

    def apply(self, img: np.ndarray) -> np.ndarray:
        """The equalised image (H, W) uint8 of ``img`` (H, W) uint8, H, W >= 1: identical
        to ``cv2.createCLAHE(clip_limit, tiles).apply(img)``. A new array each call."""
        img = np.asarray(img)
        if img.ndim != 2 or img.dtype != np.uint8 or img.size == 0:
            raise ValueError(f"Clahe.apply: expected a non-empty uint8 (H, W) image, got "
                             f"{img.dtype} {img.shape}")
        img = np.ascontiguousarray(img)
        if not img.flags.writeable:   # Numba types a read-only array apart: one compiled version
            img = img.copy()
        if img.shape != self._shape:
            self._layout = self._make_layout(*img.shape)
            self._shape = img.shape
        padded, limit, scale, col_off, col_w, row_off, row_w, row_buf = self._layout
        src = img
        if padded.size:
            ph, pw = padded.shape
            src = cv2.copyMakeBorder(img, 0, ph - img.shape[0], 0, pw - img.shape[1],
                                     cv2.BORDER_REFLECT_101, dst=padded)
        out = np.empty_like(img)
        _clahe(src, img, limit, scale, col_off, col_w, row_off, row_w, self._hist, self._lut,
               self._packed, row_buf, out)
        return out

    def _make_layout(self, h: int, w: int) -> tuple:
        """Per image size: the padded-image buffer ((0, 0) when no padding), the integer
        clip limit, the float32 LUT scale, the per-column and per-row tables of
        :func:`_axis_tables` and a (W,) int32 row buffer."""
        tiles_x, tiles_y = self.tiles
        ph, pw = h, w
        if w % tiles_x or h % tiles_y:
            ph, pw = h + tiles_y - h % tiles_y, w + tiles_x - w % tiles_x
        padded = np.empty((ph, pw) if (ph, pw) != (h, w) else (0, 0), dtype=np.uint8)
        tw, th = pw // tiles_x, ph // tiles_y
        area = tw * th
        limit = max(int(self.clip_limit * area / _BINS), 1) if self.clip_limit > 0.0 else 0
        scale = np.float32(_BINS - 1) / np.float32(area)
        col_off, col_w = _axis_tables(w, tw, tiles_x, _BINS)
        row_off, row_w = _axis_tables(h, th, tiles_y, (tiles_x + 1) * _BINS)
        return (padded, limit, scale, col_off, col_w, row_off, row_w,
                np.empty(w, dtype=np.int32))


def _axis_tables(n: int, size: int, tiles: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Interpolation tables along one axis of ``n`` pixels, tiles of ``size`` px: (n,)
    uint32 offsets (cell between tile centres, floor(t) + 1 in 0..tiles, times
    ``stride``) and (2, n) float32 weights (far tile, near tile), as OpenCV computes
    them in float32."""
    t = np.arange(n, dtype=np.float32) * (np.float32(1.0) / np.float32(size)) - np.float32(0.5)
    t1 = np.floor(t)
    far = (t - t1).astype(np.float32)
    near = (np.float32(1.0) - far).astype(np.float32)
    cell = np.clip(t1.astype(np.int64) + 1, 0, tiles)
    return (cell * stride).astype(np.uint32), np.stack([far, near])


@njit
def _clahe(src, img, limit, scale, col_off, col_w, row_off, row_w, hist, lut, packed,
           row_buf, out):
    """Histograms of ``src`` (the padded image), tile LUTs, packed LUT quadruples, then
    the interpolation of ``img`` into ``out`` (shapes: :class:`Clahe`)."""
    tiles_y, tiles_x = lut.shape[0], lut.shape[1]
    _histograms(src, src.shape[1] // tiles_x, src.shape[0] // tiles_y, hist)
    counts = np.empty(_BINS, dtype=np.int32)
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            _tile_lut(hist[ty, tx * _COPIES * _BINS:(tx + 1) * _COPIES * _BINS], limit,
                      scale, counts, lut[ty, tx])
    _pack(lut, packed)
    packed32 = packed.reshape(-1).view(np.int32)
    for y in range(img.shape[0]):
        base = row_off[y]
        pix = img[y]
        for x in range(img.shape[1]):       # scalar lookups (no vector gathers)...
            row_buf[x] = packed32[base + col_off[x] + np.uint32(pix[x])]
        _mix_row(row_buf, col_w[0], col_w[1], row_w[0, y], row_w[1, y], out[y])


@njit
def _histograms(src, tw, th, hist):
    """256-bin histograms (tiles_y, tiles_x * _COPIES * 256) of the tiles of ``src``,
    tile (ty, tx) at hist[ty, (tx * _COPIES + c) * 256 + v], c = column % _COPIES
    within the tile (the copies are summed by :func:`_tile_lut`)."""
    hist[:] = 0
    tiles_x = hist.shape[1] // (_COPIES * _BINS)
    n4 = tw // _COPIES * _COPIES
    for y in range(src.shape[0]):
        row = src[y]
        for tx in range(tiles_x):
            h = hist[y // th, tx * _COPIES * _BINS:(tx + 1) * _COPIES * _BINS]
            seg = row[tx * tw:(tx + 1) * tw]
            for x in range(0, n4, _COPIES):   # unsigned indices: no wraparound checks
                h[np.uint32(seg[x])] += 1
                h[np.uint32(_BINS) + np.uint32(seg[x + 1])] += 1
                h[np.uint32(2 * _BINS) + np.uint32(seg[x + 2])] += 1
                h[np.uint32(3 * _BINS) + np.uint32(seg[x + 3])] += 1
            for x in range(n4, tw):
                h[np.uint32(seg[x])] += 1


@njit
def _tile_lut(hist, limit, scale, counts, lut):
    """LUT (256,) uint8 of one tile from its ``_COPIES`` histograms (``_COPIES * 256``,):
    clipped at ``limit`` and redistributed (limit > 0), cumulated, times ``scale``,
    rounded half to even; ``counts`` (256,) int32 scratch."""
    for v in range(_BINS):
        counts[v] = hist[v] + hist[_BINS + v] + hist[2 * _BINS + v] + hist[3 * _BINS + v]
    if limit > 0:
        clipped = 0
        for v in range(_BINS):
            if counts[v] > limit:
                clipped += counts[v] - limit
                counts[v] = limit
        batch = clipped // _BINS
        residual = clipped - batch * _BINS
        for v in range(_BINS):
            counts[v] += batch
        if residual > 0:
            step = max(_BINS // residual, 1)
            for v in range(0, _BINS, step):
                if residual == 0:
                    break
                counts[v] += 1
                residual -= 1
    total = 0
    for v in range(_BINS):
        total += counts[v]
        lut[v] = _saturate_u8(np.float32(total) * scale)


@njit_inline
def _saturate_u8(v):
    """saturate_cast<uchar> of a float32: cvRound (half to even), clamped to 0..255."""
    return np.uint8(min(max(np.rint(v), np.float32(0.0)), np.float32(255.0)))


@njit
def _pack(lut, packed):
    """packed[cy, cx * 256 + v] for every cell between tile centres (cy in 0..tiles_y,
    cx in 0..tiles_x): the bytes L(y1, x1)[v], L(y1, x2)[v], L(y2, x1)[v], L(y2, x2)[v]
    of its 4 tiles (indices clamped to the grid), lowest byte first."""
    tiles_y, tiles_x = lut.shape[0], lut.shape[1]
    for cy in range(tiles_y + 1):
        y1, y2 = max(cy - 1, 0), min(cy, tiles_y - 1)
        for cx in range(tiles_x + 1):
            x1, x2 = max(cx - 1, 0), min(cx, tiles_x - 1)
            a, b, c, d = lut[y1, x1], lut[y1, x2], lut[y2, x1], lut[y2, x2]
            dst = packed[cy, cx * _BINS:(cx + 1) * _BINS]
            for v in range(_BINS):
                dst[v] = (np.uint32(a[v]) | (np.uint32(b[v]) << 8) | (np.uint32(c[v]) << 16)
                          | (np.uint32(d[v]) << 24))


@njit
def _mix_row(words, xa, xa1, ya, ya1, dst):
    """...and the vectorised mix: dst[x] = cvRound((L11 * xa1 + L12 * xa) * ya1 + (L21 *
    xa1 + L22 * xa) * ya), float32, L.. the bytes of ``words[x]`` (int32, :func:`_pack`).
    No clamp (saturate_cast's costs 0.02 ms): the weights are convex up to float32
    rounding, so 0 <= res <= 255 * (1 + ~1e-6) < 255.5."""
    m = np.int32(0xFF)
    for x in range(dst.shape[0]):
        p = words[x]
        l11 = np.float32(np.int32(p & m))
        l12 = np.float32(np.int32((p >> np.int32(8)) & m))
        l21 = np.float32(np.int32((p >> np.int32(16)) & m))
        l22 = np.float32(np.int32((p >> np.int32(24)) & m))
        res = (l11 * xa1[x] + l12 * xa[x]) * ya1 + (l21 * xa1[x] + l22 * xa[x]) * ya
        dst[x] = np.uint8(np.rint(res))
