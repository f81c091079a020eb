"""Shi-Tomasi corners as OpenCV's ``goodFeaturesToTrack``, in one pass, without its images.

Reference: OpenCV ``modules/imgproc/src/featureselect.cpp`` (goodFeaturesToTrack,
``useHarrisDetector=false``, ``gradientSize=3``), ``corner.cpp`` (cornerMinEigenVal ->
cornerEigenValsVecs, calcMinEigenVal), ``box_filter.simd.hpp`` (RowSum, ColumnSum,
BlockSum) and ``thresh.cpp`` (THRESH_TOZERO). Same corners in the same order, bit for
bit (checked against OpenCV 5.0 on x86-64, tests/test_corners.py).

OpenCV's steps, all reproduced: gradients dx, dy = Sobel 3x3 to float32 with scale
1 / (4 * block_size * 255), BORDER_REFLECT_101 (here ``cv2.Sobel`` itself); products
dx*dx, dx*dy, dy*dy in float32; their block_size x block_size sums (BORDER_REFLECT_101)
in float64, rounded to float32; lambda = (a + c) - sqrt((a - c)^2 + b^2) with
a = Sxx / 2, b = Sxy, c = Syy / 2, float32, no fused multiply-add; maxVal = max lambda
over mask != 0 (minMaxLoc with the mask); lambda <= float32(maxVal * quality) -> 0; a
candidate is a pixel 1 <= x < W - 1, 1 <= y < H - 1 with mask != 0, lambda != 0 and
lambda == the 3x3 maximum (dilate) of the zeroed responses; candidates sorted by lambda
descending, equal values by address descending (row-major: the lower, then the further
right first: greaterThanPtr compares the pointers); then greedily kept unless a kept
one in the 3x3 grid cells of side cvRound(min_distance) around its own is at squared
distance < min_distance^2; stop at ``n`` (0: no limit; no distance test when
min_distance < 1).

The float64 block sums round (the Sobel outputs carry float32 residues, |dx| ~ 1e-10
where the integer derivative is 0, next to values ~0.1), so their order matters: a
direct 3x3 sum differs from OpenCV's in the last float32 bit at up to ~0.1 % of pixels.
OpenCV sums each window of a row left to right (block_size <= 5; a running sum along
the row above that), then keeps a running column sum from the top of the image: add
the newest row sum, output, subtract the oldest. That running sum cannot start midway,
so it runs over every column and every row down to the last one next to a free pixel.

Where the work is saved: no whole-image eigenvalue, threshold, dilate and candidate
images are built. One pass down the image keeps rings of 3 rows; the eigenvalues are
computed on rows next to a free pixel only (whole rows: a vectorised row costs less
than picking its needed pixels); the 3x3 maxima and the candidates follow one row
behind, and only candidates go to the sort. With a threshold >= 0 (maxVal >= 0: always
in practice) a zeroed neighbour cannot beat a candidate, so the dilate test runs on the
raw values and the running maximum bounds the threshold from below; the candidates
kept are a superset, cut at the final threshold. The tracker's own calls on EuRoC
MH_01 (752x480, 1/3 of the pixels free on average, single thread): 1.7 ms against
OpenCV's 4.8 ms, or 2.75 ms when glibc keeps freed memory instead of returning it (the
rest is page faults on OpenCV's ~10 MB of per-call images).

Units: pixels; (x, y) = (column, row) of integer pixels, no sub-pixel refinement.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np

from factors.jit import njit

_local = threading.local()
_NO_IMAGE = np.zeros((0, 0), dtype=np.float32)


def good_features(img: np.ndarray, mask: np.ndarray | None, n: int, quality_level: float,
                  min_distance: float, block_size: int) -> np.ndarray:
    """Up to ``n`` Shi-Tomasi corners (k, 2) float64 pixel (x, y), strongest first.

    ``img`` (H, W) uint8; ``mask`` (H, W) uint8, nonzero = a corner may lie there (None:
    everywhere); ``n`` >= 0 the most corners (0: no limit, as OpenCV); ``quality_level``
    > 0 the fraction of the strongest response (within the mask) a corner needs;
    ``min_distance`` >= 0 px between corners; ``block_size`` >= 1 the covariance window.
    Same corners in the same order as ``cv2.goodFeaturesToTrack(img, n, quality_level,
    min_distance, mask=mask, blockSize=block_size)`` (which returns None for none).
    """
    img = np.asarray(img)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"good_features: expected a uint8 (H, W) image, got "
                         f"{img.dtype} {img.shape}")
    if not (quality_level > 0 and min_distance >= 0 and n >= 0 and block_size >= 1):
        raise ValueError(f"good_features: need quality_level > 0, min_distance >= 0, n >= 0, "
                         f"block_size >= 1; got {quality_level}, {min_distance}, {n}, {block_size}")
    h, w = img.shape
    if mask is None:
        free = np.full((h, w), 255, dtype=np.uint8)
    else:
        free = np.asarray(mask)
        if free.shape != img.shape or free.dtype != np.uint8:
            raise ValueError(f"good_features: mask must be uint8 {img.shape}, got "
                             f"{free.dtype} {free.shape}")
    if h == 0 or w == 0:
        return np.zeros((0, 2))
    if h >= 1 << 15 or w >= 1 << 16:
        raise ValueError(f"good_features: image {w}x{h} too large (x, y are packed in 16 bits)")
    dx, dy = _gradients(img, int(block_size))
    keys, max_val = _scan(dx, dy, np.ascontiguousarray(free), int(block_size),
                          float(quality_level), _NO_IMAGE)
    thresh = np.float32(max_val * float(quality_level))   # threshold() casts it to float
    if thresh >= 0:
        keys = keys[(keys >> 32) > thresh.view(np.int32)]
    else:    # every free response < 0 (and quality_level > 1 for any corner): rare, literal
        keys = _candidates(cv2.cornerMinEigenVal(img, int(block_size), ksize=3), free, thresh)
    keys.sort()
    cell = int(round(float(min_distance))) if min_distance >= 1 else 0   # cvRound: half to even
    return _select(keys, w, h, int(n), float(min_distance) ** 2, cell)


def _candidates(eig: np.ndarray, free: np.ndarray, thresh: np.float32) -> np.ndarray:
    """OpenCV's candidates, literally, as keys like ``_peaks_row``'s: free pixels
    1 <= x < W - 1, 1 <= y < H - 1 whose THRESH_TOZERO response (at ``thresh``) is
    nonzero and equals its 3x3 dilate. For a threshold < 0, which ``_scan`` leaves out."""
    zeroed = np.where(eig > thresh, eig, np.float32(0.0)).astype(np.float32)
    peak = (zeroed != 0) & (zeroed == cv2.dilate(zeroed, None)) & (free != 0)
    peak[[0, -1], :] = False
    peak[:, [0, -1]] = False
    y, x = np.nonzero(peak)
    bits = zeroed[y, x].view(np.int32).astype(np.int64)
    ordered = bits ^ ((bits >> 31) & 0x7FFFFFFF)
    return (ordered << 32) | (y.astype(np.int64) << 16) | x


def _gradients(img: np.ndarray, block_size: int) -> tuple[np.ndarray, np.ndarray]:
    """cornerEigenValsVecs' gradients dx, dy (H, W) float32: Sobel 3x3, scale
    1 / ((1 << (3 - 1)) * block_size * 255), BORDER_DEFAULT = REFLECT_101. Written into
    two arrays kept per thread (fresh 1.4 MB arrays cost ~0.3 ms of page faults
    whenever the allocator hands out new pages); valid until the thread's next call."""
    h, w = img.shape
    bufs = getattr(_local, "gradients", None)
    if bufs is None or bufs[0].shape != (h, w):
        bufs = (np.empty((h, w), dtype=np.float32), np.empty((h, w), dtype=np.float32))
        _local.gradients = bufs
    scale = 1.0 / (4 * block_size * 255.0)
    for (ox, oy), out in zip(((1, 0), (0, 1)), bufs):
        cv2.Sobel(img, cv2.CV_32F, ox, oy, dst=out, ksize=3, scale=scale,
                  borderType=cv2.BORDER_REFLECT_101)
    return bufs


@njit
def _reflect101(i, n):
    """OpenCV's borderInterpolate for BORDER_REFLECT_101 (gfedcb|abcdefgh|gfedcba)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * n - 2 - i
    return i


@njit
def _product_row(gx, gy, a, pxx, pxy, pyy):
    """Gradient products gx*gx, gx*gy, gy*gy (W + k - 1,) float32 of one image row,
    bordered (REFLECT_101) by ``a`` = k // 2 columns on the left, k - 1 - a on the right.
    One loop per product (few arrays per loop: LLVM vectorises them)."""
    w = gx.shape[0]
    qxx, qxy, qyy = pxx[a:a + w], pxy[a:a + w], pyy[a:a + w]   # index from 0: no wraparound
    for x in range(w):
        qxx[x] = gx[x] * gx[x]
    for x in range(w):
        qxy[x] = gx[x] * gy[x]
    for x in range(w):
        qyy[x] = gy[x] * gy[x]
    for i in range(pxx.shape[0] - w):
        j = i if i < a else i + w        # bordered column left / right of the row
        src = a + _reflect101(j - a, w)
        pxx[j] = pxx[src]
        pxy[j] = pxy[src]
        pyy[j] = pyy[src]


@njit
def _row_sums(p, k, out):
    """Float64 sums (W,) of ``k`` consecutive products of ``p`` in OpenCV's order: for
    k <= 5 each window left to right, for larger k a running sum along the row (add the
    entering product minus the leaving one; RowSum)."""
    w = out.shape[0]
    if k <= 5:
        for x in range(w):
            r = np.float64(p[x])
            for i in range(1, k):
                r += np.float64(p[x + i])
            out[x] = r
    else:
        r = 0.0
        for i in range(k):
            r += np.float64(p[i])
        out[0] = r
        for x in range(w - 1):
            r += np.float64(p[x + k]) - np.float64(p[x])
            out[x + 1] = r


@njit
def _box_step(p_new, p_old, k, col, out, r_new, r_old):
    """One output row of one channel's block sum, as ColumnSum: s = col + row sum of
    ``p_new`` is the block sum (to ``out`` as float32), then col = s - row sum of
    ``p_old`` (the product row k rows up; its row sum is recomputed, bit-identical).
    k = 3 (the usual) in one fused loop; ``r_new``, ``r_old`` (W,) scratch otherwise."""
    w = out.shape[0]
    if k == 3:
        for x in range(w):
            rn = np.float64(p_new[x]) + np.float64(p_new[x + 1]) + np.float64(p_new[x + 2])
            ro = np.float64(p_old[x]) + np.float64(p_old[x + 1]) + np.float64(p_old[x + 2])
            s = col[x] + rn
            out[x] = np.float32(s)
            col[x] = s - ro
    else:
        _row_sums(p_new, k, r_new)
        _row_sums(p_old, k, r_old)
        for x in range(w):
            s = col[x] + r_new[x]
            out[x] = np.float32(s)
            col[x] = s - r_old[x]


@njit
def _ordered(b):
    """Int32 bits of a float32 -> an int ordered as the floats (and back: an involution)."""
    b = np.int64(b)
    return b ^ ((b >> 31) & 0x7FFFFFFF)


@njit
def _eig_row(sxx, sxy, syy, free_row, eig_row, hm):
    """One row of minimum eigenvalues from its block sums (W,) float32 into ``eig_row``,
    as calcMinEigenVal: a = Sxx/2, b = Sxy, c = Syy/2, lambda = (a + c) -
    sqrt((a - c)^2 + b^2), float32 throughout, no FMA; their horizontal 3-max into
    ``hm`` (the row half of the 3x3 dilate; ends unused). Returns the largest value at
    a free pixel as an ``_ordered`` key (-2^31 if none)."""
    w = eig_row.shape[0]
    half = np.float32(0.5)
    for i in range(w):
        a = sxx[i] * half
        b = sxy[i]
        c = syy[i] * half
        t = a - c
        eig_row[i] = (a + c) - np.sqrt(t * t + b * b)
    for x in range(1, w - 1):
        hm[x] = max(eig_row[x - 1], max(eig_row[x], eig_row[x + 1]))
    bits = eig_row.view(np.int32)
    best = np.int64(-(2 ** 31))
    for x in range(w):                  # an integer max: vectorised, unlike a float one
        v = _ordered(bits[x]) if free_row[x] else np.int64(-(2 ** 31))
        best = max(best, v)
    return best


@njit
def _rows_needed(free):
    """(H,) bool: rows holding a free pixel or next to a row that does; the last one
    (-1 if none)."""
    h = free.shape[0]
    has = np.zeros(h + 2, dtype=np.bool_)
    for y in range(h):
        has[y + 1] = free[y].any()
    need = np.empty(h, dtype=np.bool_)
    last = -1
    for y in range(h):
        need[y] = has[y] or has[y + 1] or has[y + 2]
        last = y if need[y] else last
    return need, last


@njit
def _scan(dx, dy, free, k, quality, eig_out):
    """One pass down the image: block sums (block ``k``) of the gradients ``dx``, ``dy``
    (H, W) float32, minimum eigenvalues on the rows holding a free pixel of ``free``
    (H, W) uint8 or next to one (a ring of 3 rows), their maximum over free pixels, and
    the local-maximum candidates. Returns (keys (K,) int64 as ``_peaks_row``, maxVal).
    The computed eigenvalue rows are also copied to ``eig_out`` (H, W) unless it is empty.

    The keys are a superset of OpenCV's candidates when its threshold
    float32(maxVal * quality) is >= 0: then a zeroed neighbour (<= threshold < value)
    cannot beat the centre, so the dilate test is a test on the raw values, and the
    threshold is bounded below by the one of the running maximum. Rows below the last
    needed one are not computed."""
    h, w = dx.shape
    a = k // 2
    need, last = _rows_needed(free)
    prod = np.empty((k, 3, w + k - 1), dtype=np.float32)   # ring of bordered product rows
    col = np.zeros((3, w))
    sums = np.empty((3, w), dtype=np.float32)
    r_new = np.empty(w)
    r_old = np.empty(w)
    eig = np.empty((3, w), dtype=np.float32)                # ring of eigenvalue rows
    hm = np.empty((3, w), dtype=np.float32)                 # their horizontal 3-max
    flag = np.zeros((w + 7) // 8 * 8, dtype=np.uint8)
    keys = np.empty(4096 + w, dtype=np.int64)
    n = 0
    best = np.int64(-(2 ** 31))
    cast = np.zeros(1, dtype=np.int32)
    cast_f = cast.view(np.float32)                 # float32 value of an int32 bit pattern
    for rc in range(last + k if last >= 0 else 0):   # bordered rows; output row rc - k + 1
        sy = _reflect101(rc - a, h)
        p_new = prod[rc % k]
        _product_row(dx[sy], dy[sy], a, p_new[0], p_new[1], p_new[2])
        if rc < k - 1:
            for c in range(3):
                _row_sums(p_new[c], k, r_new)
                col[c] += r_new
            continue
        p_old = prod[(rc + 1) % k]
        for c in range(3):
            _box_step(p_new[c], p_old[c], k, col[c], sums[c], r_new, r_old)
        y = rc - k + 1
        if not need[y]:
            continue
        best = max(best, _eig_row(sums[0], sums[1], sums[2], free[y], eig[y % 3], hm[y % 3]))
        if eig_out.shape[0] > 0:
            eig_out[y] = eig[y % 3]
        yc = y - 1                                 # centre row: its 3 rows are now known
        if 1 <= yc and need[yc - 1] and need[yc]:
            cast[0] = _ordered(best)
            bound = max(np.float32(np.float64(cast_f[0]) * quality), np.float32(0.0))
            if n + w + 8 > keys.shape[0]:          # room for a whole row
                grown = np.empty(2 * keys.shape[0], dtype=np.int64)
                grown[:n] = keys[:n]
                keys = grown
            n = _peaks_row(eig[yc % 3], hm[(yc - 1) % 3], hm[yc % 3], hm[y % 3], free[yc],
                           bound, yc, flag, keys, n)
    cast[0] = _ordered(best)
    return keys[:n], (np.float64(cast_f[0]) if best > -(2 ** 31) else 0.0)


@njit
def _peaks_row(t, h0, h1, h2, fr, bound, y, flag, keys, n):
    """Append to ``keys`` (from ``n``; returns the new count) the pixels 1 <= x < W - 1
    of row ``y`` (values ``t``, free flags ``fr``) with t != 0, t > ``bound`` and t equal
    to the max of the horizontal 3-maxima ``h0``, ``h1``, ``h2`` of rows y-1, y, y+1.
    Key = ``_ordered`` float32 bits << 32 | y << 16 | x: ascending keys = ascending
    value, then ascending row-major address (OpenCV's tie order, reversed). ``flag``
    (W rounded up to 8,) scratch; ``keys`` needs W + 8 free entries."""
    w = t.shape[0]
    zero = np.float32(0.0)
    for x in range(1, w - 1):
        v = t[x]
        peak = v == max(h0[x], max(h1[x], h2[x]))
        flag[x] = (fr[x] != 0) & (v != zero) & (v > bound) & peak
    words = flag.view(np.uint64)                   # scanned 8 pixels at a time
    bits = t.view(np.int32)
    for i in range(words.shape[0]):
        if words[i] != 0:
            for x in range(8 * i, min(8 * i + 8, w)):   # branch-free: write, advance if set
                keys[n] = (_ordered(bits[x]) << 32) | (y << 16) | x
                n += flag[x] != 0
    return n


@njit
def _select(keys, w, h, n, md2, cell):
    """Greedy min-distance selection over the ascending ``keys``, strongest (last) first:
    a corner is kept unless a kept one in the 3x3 grid cells (side ``cell``) around its
    own is at squared distance < md2 (no test when ``cell`` == 0); stops at ``n`` kept
    (0: no limit). Returns (k, 2) float64 (x, y).

    A cell holds at most 3 kept corners (mutual distance >= md > cell - 1 within a
    (cell - 1)-square), so each has 4 slots, unused ones far away, and the 36 distances
    of a 3x3 block are taken without branches; the grid has a ring of empty cells. (For
    integer pixels the grid never misses a corner closer than md: |dx| < md gives
    |dx| <= ceil(md) - 1 <= cvRound(md), at most one cell away.)"""
    total = keys.shape[0]
    cap = total if n == 0 else min(n, total)
    out = np.empty((cap, 2))
    c = cell if cell > 0 else 1 << 16              # no test: one cell, never looked at
    gw = (w + c - 1) // c + 2
    gh = (h + c - 1) // c + 2
    far = -1e9
    gx = np.full(gh * gw * 4, far)                # 4 slots per cell, row-major cells
    gy = np.full(gh * gw * 4, far)
    used = np.zeros(gh * gw, dtype=np.int64)
    cell_x = np.arange(w) // c + 1                 # no integer division per candidate
    cell_y = np.arange(h) // c + 1
    cnt = 0
    for i in range(total - 1, -1, -1):
        if cnt == cap:
            break
        y = (keys[i] >> 16) & 0xFFFF
        x = keys[i] & 0xFFFF
        cx = cell_x[x]
        cy = cell_y[y]
        if cell > 0:
            near = 0
            for yy in range(cy - 1, cy + 2):
                base = np.uint64((yy * gw + cx - 1) * 4)   # cells cx-1..cx+1: contiguous
                for j in range(12):                 # (unsigned index: no wraparound test)
                    ddx = x - gx[base + np.uint64(j)]
                    ddy = y - gy[base + np.uint64(j)]
                    near |= ddx * ddx + ddy * ddy < md2
            if near:
                continue
            slot = used[cy * gw + cx]
            if slot == 4:
                raise RuntimeError("good_features: more than 4 corners in a grid cell")
            gx[(cy * gw + cx) * 4 + slot] = x
            gy[(cy * gw + cx) * 4 + slot] = y
            used[cy * gw + cx] = slot + 1
        out[cnt, 0] = x
        out[cnt, 1] = y
        cnt += 1
    return out[:cnt]
