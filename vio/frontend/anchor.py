"""Track positions aligned to each track's first image by an affine patch warp.

A KLT step matches a translation-only window from one frame to the next. As the view
changes, the patch around a point deforms (perspective: scale, shear, rotation), and
the best translation of a deformed window is not the point's position: against a
render's scene the tracked position leaves its point by 0.55 px (median) after 8-15
frames and 1.16 px after 64 (``benchmarks/bench_klt_drift.py``), the same when each track
is re-tracked from its own first image (stop 66). Here each track keeps the patch of its
first observation (its *anchor*: ``P`` x ``P`` grey levels of the preprocessed image
around that pixel) and each frame fits

    r(x) = I(c + A x) - (g T(x) + o),   x on the template's grid (px from its centre),

over the centre ``c`` (2, px), the 2x2 affine map ``A`` and a gain / offset ``(g, o)``
(an exposure change) by inverse-compositional Gauss-Newton (Baker & Matthews, "Lucas-
Kanade 20 Years On", part 1, section 3.2; the gain and offset as two more additive
parameters), pixels at the sensor's limits left out. It starts at the frame's LK position
and the track's previous ``A, g, o``. The template's centre is the first observation, so
``c`` is where that same point lies now (to first order in the patch's deformation),
whatever the chain of LK steps did: 0.09 px median after 32-63 frames on the same render
(0.22 px with the real lens, 8-ms blur and exposure changes; benchmarks/README.md, stop 67).

An alignment that leaves the image, does not settle, moves more than ``max_shift_px``
from LK's answer, ends with an implausible ``A`` or gain, or matches worse than
``min_zncc`` (zero-mean normalised cross-correlation of the warped patch and the
template) keeps LK's position and takes a new anchor there: the track goes on, and its
drift restarts from that frame.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from factors.jit import njit, njit_inline

OK, OUTSIDE, FAILED = 0, 1, 2      # status codes of :func:`realign`
# grey levels at or beyond these take no part in the fit: a saturated pixel stays at 255
# whatever the gain (real V1_01: 10 % of the pixels; a 10 % brighter frame drove the
# alignment's 90th percentile error from 0.10 to 0.35 px before they were left out)
CLIP_LO, CLIP_HI = 1.0, 254.0


@dataclass(frozen=True)
class Anchors:
    """Per-track anchor state, rows aligned with the tracker's tracks.

    ``templ`` (N, P + 2, P + 2) float32 grey levels around the anchor pixel (the
    template and a 1-px ring for its gradient); ``grad`` (N, P, P, 2) float64 the
    template's gradient; ``normals`` (N, 8, 8) float64 the Gauss-Newton normal matrix at
    unit gain (lower triangle; both fixed for the anchor's life, the inverse compositional
    form's saving); ``warp`` (N, 6) float64: ``A`` row-major (a11, a12, a21, a22), gain,
    offset; ``valid`` (N,) bool: the template lay wholly inside its image (an anchor near
    the border waits for a frame where it does)."""

    templ: np.ndarray
    grad: np.ndarray
    normals: np.ndarray
    warp: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return int(self.valid.shape[0])

    def take(self, idx: np.ndarray) -> "Anchors":
        """The rows ``idx`` (K,) int."""
        return Anchors(*(getattr(self, f.name)[idx] for f in fields(self)))

    def put(self, rows: np.ndarray, other: "Anchors") -> "Anchors":
        """A copy with ``rows`` (bool (N,) or int (K,)) replaced by ``other``'s rows."""
        out = []
        for f in fields(self):
            a = getattr(self, f.name).copy()
            a[rows] = getattr(other, f.name)
            out.append(a)
        return Anchors(*out)

    @staticmethod
    def stack(parts: list["Anchors"]) -> "Anchors":
        """Rows of ``parts`` one after another."""
        return Anchors(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Anchors)))


def new_anchors(img: np.ndarray, px: np.ndarray, patch: int) -> Anchors:
    """Anchors at pixels ``px`` (N, 2) of ``img`` (H, W) uint8: identity warp, unit gain."""
    n = len(px)
    templ = np.empty((n, patch + 2, patch + 2), dtype=np.float32)
    grad = np.empty((n, patch, patch, 2))
    normals = np.zeros((n, 8, 8))
    valid = np.empty(n, dtype=np.bool_)
    _templates(img, np.ascontiguousarray(px, dtype=np.float64), templ, valid)
    _all_normals(templ, valid, grad, normals)
    warp = np.zeros((n, 6))
    warp[:, 0] = warp[:, 3] = warp[:, 4] = 1.0
    return Anchors(templ, grad, normals, warp, valid)


def realign(img: np.ndarray, px: np.ndarray, anchors: Anchors, max_iter: int,
            max_shift_px: float, min_zncc: float) -> tuple[np.ndarray, Anchors, np.ndarray]:
    """Align every track's anchor into ``img`` (H, W) uint8 from LK's pixels ``px`` (N, 2).

    Returns (pixels (N, 2): the aligned centres where status is OK, else ``px``; the
    anchors for the next frame: updated warps, new anchors taken at ``px`` where the
    alignment failed or the template was not valid; status (N,) int8: OK / OUTSIDE /
    FAILED, -1 for a template that was not valid)."""
    px = np.ascontiguousarray(px, dtype=np.float64)
    out = px.copy()
    warp = anchors.warp.copy()
    status = np.full(len(px), -1, dtype=np.int8)
    _align_all(img, anchors.templ, anchors.grad, anchors.normals, anchors.valid, out, warp,
               status, int(max_iter), float(max_shift_px), float(min_zncc))
    kept = Anchors(anchors.templ, anchors.grad, anchors.normals, warp, anchors.valid)
    redo = status != OK
    if not redo.any():
        return out, kept, status
    return out, kept.put(redo, new_anchors(img, px[redo], anchors.templ.shape[1] - 2)), status


@njit_inline
def _sample(img, x, y):
    """Bilinear grey level of ``img`` at (x, y); the caller keeps 0 <= x < W-1, 0 <= y < H-1."""
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    a = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    b = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return a * (1.0 - fy) + b * fy


@njit
def _templates(img, px, templ, valid):
    """Fill ``templ`` (N, P + 2, P + 2) by bilinear sampling around ``px`` (N, 2) (the
    template and a 1-px ring for its gradient); ``valid`` (N,) False where the window
    leaves the image (those templates are left zero)."""
    h, w = img.shape
    half = templ.shape[1] // 2
    for k in range(px.shape[0]):
        x0, y0 = px[k, 0] - half, px[k, 1] - half
        valid[k] = x0 >= 0.0 and y0 >= 0.0 and x0 + 2 * half < w - 1 and y0 + 2 * half < h - 1
        for i in range(templ.shape[1]):
            for j in range(templ.shape[2]):
                templ[k, i, j] = _sample(img, x0 + j, y0 + i) if valid[k] else 0.0


@njit
def _all_normals(templ, valid, grad, normals):
    """:func:`_template_normals` of each valid template, into ``grad`` and ``normals``."""
    for k in range(templ.shape[0]):
        if valid[k]:
            _template_normals(templ[k], grad[k], normals[k])


@njit
def _align_all(img, templ, grad, normals, valid, c, warp, status, max_iter, max_shift, min_zncc):
    """:func:`_align_one` for each valid row; ``c`` (N, 2) and ``warp`` (N, 6) in place."""
    for k in range(c.shape[0]):
        if valid[k]:
            status[k] = _align_one(img, templ[k], grad[k], normals[k], c[k], warp[k],
                                   max_iter, max_shift, min_zncc)


@njit
def _template_normals(t, G, Hg):
    """The template's gradient ``G`` (P, P, 2) (central differences) and the normal
    matrix ``Hg`` (8, 8, lower triangle) of the Jacobian rows ``[G dW/dp, T, 1]`` at unit
    gain; :func:`_align_one` scales the geometric block by the gain."""
    n = G.shape[0]
    half = n // 2
    Hg[:] = 0.0
    J = np.empty(8)
    for i in range(n):
        dy = float(i - half)
        for j in range(n):
            dx = float(j - half)
            gx = 0.5 * (t[i + 1, j + 2] - t[i + 1, j])
            gy = 0.5 * (t[i + 2, j + 1] - t[i, j + 1])
            G[i, j, 0], G[i, j, 1] = gx, gy
            if _clipped(t[i + 1, j + 1]):
                continue
            J[0], J[1], J[2], J[3], J[4], J[5] = gx, gy, gx * dx, gx * dy, gy * dx, gy * dy
            J[6], J[7] = t[i + 1, j + 1], 1.0
            for a in range(8):
                for e in range(a + 1):
                    Hg[a, e] += J[a] * J[e]


@njit
def _align_one(img, t, G, Hg, c, warp, max_iter, max_shift, min_zncc):
    """Inverse-compositional Gauss-Newton (Baker & Matthews, part 1, section 3.2) on the
    8 parameters p = (c, A, g, o) of the module docstring: each step fits the template's
    own warp ``x -> dc + (1 + D) x`` and gain / offset increments to the residual, then
    composes ``c + A x <- c + A (1 + D)^-1 (x - dc)``, ``g += dg``, ``o += do``. Writes the
    result into ``c`` (2,) and ``warp`` (6,) when it is accepted. Returns the status."""
    h, w = img.shape
    half = G.shape[0] // 2
    p = np.empty(8)
    p[0], p[1] = c[0], c[1]
    p[2:] = warp
    H = np.empty((8, 8))
    b = np.empty(8)
    d = np.empty(8)
    moved = 1.0
    for _ in range(max_iter):
        if not _inside(p, half, w, h):
            return OUTSIDE
        _steepest_descent(img, t, G, p, b)
        g = p[6]
        for a in range(8):              # the Jacobian's geometric columns carry the gain
            sa = g if a < 6 else 1.0
            b[a] *= sa
            for e in range(a + 1):
                H[a, e] = Hg[a, e] * sa * (g if e < 6 else 1.0)
        if not _solve_spd(H, b, d) or not _compose(p, d):
            return FAILED
        moved = d[0] * d[0] + d[1] * d[1]       # _compose leaves the centre's step in d[:2]
        if moved < 0.01 * 0.01 and abs(d[2]) + abs(d[3]) + abs(d[4]) + abs(d[5]) < 2e-3:
            break
    if moved > 0.05 * 0.05 or (p[0] - c[0]) ** 2 + (p[1] - c[1]) ** 2 > max_shift * max_shift:
        return FAILED
    if not (0.5 < p[2] * p[5] - p[3] * p[4] < 2.0) or not (0.3 < p[6] < 3.0):
        return FAILED
    if not _inside(p, half, w, h):
        return OUTSIDE
    if _zncc(img, t, p) < min_zncc:
        return FAILED
    c[0], c[1] = p[0], p[1]
    warp[:] = p[2:]
    return OK


@njit_inline
def _steepest_descent(img, t, G, p, b):
    """``b`` (8,) = sum over the template of [G dW/dp, T, 1] r at unit gain, r the residual
    of the module docstring under ``p``; clipped pixels left out."""
    n = G.shape[0]
    half = n // 2
    b[:] = 0.0
    for i in range(n):
        dy = float(i - half)
        for j in range(n):
            dx = float(j - half)
            tv = t[i + 1, j + 1]
            iv = _sample(img, p[0] + p[2] * dx + p[3] * dy, p[1] + p[4] * dx + p[5] * dy)
            if _clipped(tv) or _clipped(iv):
                continue
            r = iv - (p[6] * tv + p[7])
            gx, gy = G[i, j, 0] * r, G[i, j, 1] * r
            b[0] += gx
            b[1] += gy
            b[2] += gx * dx
            b[3] += gx * dy
            b[4] += gy * dx
            b[5] += gy * dy
            b[6] += tv * r
            b[7] += r


@njit_inline
def _compose(p, d):
    """``p <- p o d^-1`` for the warp, ``+ d`` for gain and offset (see :func:`_align_one`);
    ``d[:2]`` becomes the centre's move in the image. False for a near-singular ``1 + D``."""
    m11, m12, m21, m22 = 1.0 + d[2], d[3], d[4], 1.0 + d[5]
    det = m11 * m22 - m12 * m21
    if abs(det) < 0.1:
        return False
    i11, i12, i21, i22 = m22 / det, -m12 / det, -m21 / det, m11 / det    # (1 + D)^-1
    n11, n12 = p[2] * i11 + p[3] * i21, p[2] * i12 + p[3] * i22
    n21, n22 = p[4] * i11 + p[5] * i21, p[4] * i12 + p[5] * i22
    sx, sy = n11 * d[0] + n12 * d[1], n21 * d[0] + n22 * d[1]
    p[0], p[1], p[2], p[3], p[4], p[5] = p[0] - sx, p[1] - sy, n11, n12, n21, n22
    p[6], p[7] = p[6] + d[6], p[7] + d[7]
    d[0], d[1] = sx, sy
    return True


@njit_inline
def _clipped(v):
    """A grey level at the sensor's limits, where the affine brightness model fails."""
    return v <= CLIP_LO or v >= CLIP_HI


@njit_inline
def _inside(p, half, w, h):
    """Whether the patch warped by ``p`` (c, A, ...) lies where bilinear sampling may read:
    its four corners (an affine map's extremes) in [0, W - 1) x [0, H - 1)."""
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            u = p[0] + (p[2] * sx + p[3] * sy) * half
            v = p[1] + (p[4] * sx + p[5] * sy) * half
            if not (0.0 <= u < w - 1.0 and 0.0 <= v < h - 1.0):
                return False
    return True


@njit
def _zncc(img, t, p):
    """Zero-mean normalised cross-correlation of the template and the patch warped by
    ``p`` (the caller checked the patch lies inside the image)."""
    m = t.shape[0] - 2
    half = m // 2
    n = m * m
    sa = sb = saa = sbb = sab = 0.0
    for i in range(m):
        for j in range(m):
            dx, dy = float(j - half), float(i - half)
            a = _sample(img, p[0] + p[2] * dx + p[3] * dy, p[1] + p[4] * dx + p[5] * dy)
            bb = t[i + 1, j + 1]
            sa += a
            sb += bb
            saa += a * a
            sbb += bb * bb
            sab += a * bb
    va, vb = saa - sa * sa / n, sbb - sb * sb / n
    if va <= 1e-9 or vb <= 1e-9:
        return 0.0
    return (sab - sa * sb / n) / np.sqrt(va * vb)


@njit
def _solve_spd(H, b, x):
    """Solve H x = b for the symmetric positive definite ``H`` (n, n) whose lower triangle
    is filled (Cholesky, in place on that triangle). False when not positive definite."""
    n = b.shape[0]
    for j in range(n):
        s = H[j, j]
        for k in range(j):
            s -= H[j, k] * H[j, k]
        if s <= 1e-12 * (1.0 + abs(H[j, j])):
            return False
        H[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            s = H[i, j]
            for k in range(j):
                s -= H[i, k] * H[j, k]
            H[i, j] = s / H[j, j]
    for i in range(n):              # L y = b
        s = b[i]
        for k in range(i):
            s -= H[i, k] * x[k]
        x[i] = s / H[i, i]
    for i in range(n - 1, -1, -1):  # L^T x = y
        s = x[i]
        for k in range(i + 1, n):
            s -= H[k, i] * x[k]
        x[i] = s / H[i, i]
    return True
