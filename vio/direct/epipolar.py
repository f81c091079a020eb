"""Inverse depth of host pixels by epipolar line search in a second image (seed eq. 4.1, 4.2).

For a host pixel with bearing f = K0^-1 [u, v, 1], the target point at inverse depth
rho is q(rho) = R f + rho t (T_c1_c0 = [R | t], scaled form), and its pixels between
``idepth_min`` and ``idepth_max`` form a segment of the epipolar line. The segment is
sampled every ``step_px`` pixels; the cost of a sample is the SSD over DSO's 8-pixel
pattern (seed eq. 4.1; the pattern offsets are mapped by the 2x2 block of
K1 R K0^-1 as in DSO). The best sample is refined by Gauss-Newton on the position
along the line, then triangulated with the seed's cross-product relation
[p_best]x (d1 R f + t) = 0, divided by d1 so it is linear in rho = 1 / d1:
    [p]x R f + rho [p]x t = 0   =>   rho = -(c . e) / (e . e),  c = [p]x R f, e = [p]x t
(least squares over the three rows of the seed's system; stable for far points).

Variance (DSO/LSD): the match error along the line is
    sigma_px^2 = (0.2 + 0.2 (a + b) / a)^2 + 2 sigma_I^2 P / sum_p (g_p . l)^2,
a, b the host-gradient energy along / across the line direction l (DSO's
errorInPixel: large when the gradient is orthogonal to the line) and the second term
the photometric disparity error (LSD-SLAM) from the target gradient along l. Then
V = sigma_px^2 / |d x / d rho|^2 with d x / d rho = d pi / d q t (pixels per 1/m).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import gtsam
import numpy as np
from numba import njit

from factors.image_ops import BilinearImage, ImageSampler
from factors.photometric import PATTERN, Pinhole, make_host_patch
from vio.direct.config import EpipolarConfig


@dataclass(frozen=True, eq=False)
class EpipolarResult:
    """Per point (N,): ``idepth`` (1/m, in the host camera), ``variance`` (1/m^2),
    ``sigma_px`` the match error along the line (pixels) behind ``variance``,
    ``quality`` (second-best / best SSD; inf when unique), ``energy`` best SSD per
    pattern pixel after refinement, ``uv_match`` (N, 2) matched pixel in the target,
    ``ok`` passed every check (interior minimum inside the image, quality, energy,
    positive finite depth)."""

    idepth: np.ndarray
    variance: np.ndarray
    sigma_px: np.ndarray
    quality: np.ndarray
    energy: np.ndarray
    uv_match: np.ndarray
    ok: np.ndarray

    def __len__(self) -> int:
        return int(self.idepth.shape[0])


def _as_sampler(img: np.ndarray | ImageSampler) -> ImageSampler:
    return img if hasattr(img, "sample") else BilinearImage(np.asarray(img, dtype=np.float64))


def _line_geometry(f: np.ndarray, R: np.ndarray, t: np.ndarray, K1: Pinhole, cfg: EpipolarConfig):
    """Segment start (N, 2), unit direction (N, 2), length (N,) and a validity mask."""
    qinf = f @ R.T
    lo = np.full(len(f), cfg.idepth_min)
    hi = np.full(len(f), cfg.idepth_max)
    if abs(t[2]) > 1e-12:  # keep q_z > 0 on the whole range (point in front of camera 1)
        lim = (1e-3 - qinf[:, 2]) / t[2]
        if t[2] < 0:
            hi = np.minimum(hi, lim)
        else:
            lo = np.maximum(lo, lim)
    ok = (hi > lo) & (qinf[:, 2] + lo * t[2] > 0)
    lo = np.where(ok, lo, cfg.idepth_min)
    hi = np.where(ok, hi, cfg.idepth_max)
    q0 = qinf + lo[:, None] * t
    q1 = qinf + hi[:, None] * t
    q0[:, 2] = np.where(ok, q0[:, 2], 1.0)
    q1[:, 2] = np.where(ok, q1[:, 2], 1.0)
    x0, x1 = K1.project(q0), K1.project(q1)
    d = x1 - x0
    length = np.linalg.norm(d, axis=1)
    ok &= length > 1e-6
    return x0, d / np.maximum(length, 1e-12)[:, None], length, ok


@njit(cache=True, nogil=True)
def _search_kernel(stack, x0, l, length, ok, offs, ref, step, S, zero_mean):
    """Per point: best sample index along the segment (interior minimum only), its SSD
    and the second best SSD beyond +-2 px (numba; see ``_discrete_search``)."""
    n, P = ref.shape
    h, w = stack.shape[0], stack.shape[1]
    k_best = np.zeros(n, np.int64)
    best = np.full(n, np.inf)
    second = np.full(n, np.inf)
    e = np.empty(S)
    d = np.empty(P)
    for i in range(n):
        if not ok[i]:
            continue
        for j in range(S):
            e[j] = np.inf
            sj = j * step
            if sj > length[i] + 1e-9:
                continue
            cu = x0[i, 0] + sj * l[i, 0]
            cv = x0[i, 1] + sj * l[i, 1]
            good = True
            mean = 0.0
            for k in range(P):
                u = cu + offs[k, 0]
                v = cv + offs[k, 1]
                if not (u >= 1.0 and u < w - 2.0 and v >= 1.0 and v < h - 2.0):
                    good = False
                    break
                u0, v0 = int(u), int(v)
                fx, fy = u - u0, v - v0
                top = stack[v0, u0, 0] + fx * (stack[v0, u0 + 1, 0] - stack[v0, u0, 0])
                bot = stack[v0 + 1, u0, 0] + fx * (stack[v0 + 1, u0 + 1, 0] - stack[v0 + 1, u0, 0])
                d[k] = top + fy * (bot - top) - ref[i, k]
                mean += d[k]
            if not good:
                continue
            mean = mean / P if zero_mean else 0.0
            ssd = 0.0
            for k in range(P):
                ssd += (d[k] - mean) ** 2
            e[j] = ssd
        kb = 0
        for j in range(S):
            if e[j] < e[kb]:
                kb = j
        if kb == 0 or kb == S - 1 or not np.isfinite(e[kb - 1]) or not np.isfinite(e[kb + 1]):
            continue      # the true match may lie outside the searched segment
        k_best[i] = kb
        best[i] = e[kb]
        for j in range(S):
            if abs(j - kb) * step > 2.0 and e[j] < second[i]:
                second[i] = e[j]
    return k_best, best, second


def _discrete_search(target, x0, l, length, ok, offs, ref, cfg):
    """Best sample position s (N,), its SSD and quality (second best beyond +-2 px / best)."""
    S = int(min(cfg.max_steps, np.ceil(length[ok].max() / cfg.step_px) + 1)) if ok.any() else 1
    stack = getattr(target, "_stack", None)
    if stack is None:
        raise TypeError("epipolar_search: the target image must be an array or a BilinearImage")
    k, best, second = _search_kernel(stack, np.ascontiguousarray(x0), np.ascontiguousarray(l), length,
                                     ok, np.ascontiguousarray(offs), np.ascontiguousarray(ref),
                                     float(cfg.step_px), S, bool(cfg.zero_mean))
    fin = np.isfinite(best)
    quality = np.where(fin, second / np.where(fin, np.maximum(best, 1e-9), 1.0), 0.0)
    return k * cfg.step_px, best, quality


def _refine(target, x0, l, s, offs, ref, cfg):
    """Gauss-Newton on the position s along the line (N,), each step clamped to half a
    step; a step is kept only where the pattern stays inside and the SSD decreases.
    Returns s and the SSD there."""
    stack = getattr(target, "_stack", None)
    if stack is None:
        raise TypeError("epipolar_search: the target image must be an array or a BilinearImage")
    if ref.shape[1] != 8:
        raise ValueError(f"epipolar refinement assumes DSO's 8-pixel pattern, got {ref.shape[1]}")
    return _refine_kernel(stack, np.ascontiguousarray(x0), np.ascontiguousarray(l), np.ascontiguousarray(s),
                          np.ascontiguousarray(offs), np.ascontiguousarray(ref), float(cfg.step_px),
                          int(cfg.gn_iters), bool(cfg.zero_mean))


@njit(cache=True, nogil=True)
def _sum8(a):
    """Sum of 8 values in numpy's pairwise order (bit-identical to ``a.sum(-1)``)."""
    return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]))


@njit(cache=True, nogil=True)
def _bilinear(stack, u0, v0, fx, fy, c):
    """Channel ``c`` of ``stack`` (H, W, 3) at (u0 + fx, v0 + fy) (``BilinearImage.sample``)."""
    top = stack[v0, u0, c] + fx * (stack[v0, u0 + 1, c] - stack[v0, u0, c])
    bot = stack[v0 + 1, u0, c] + fx * (stack[v0 + 1, u0 + 1, c] - stack[v0 + 1, u0, c])
    return top + fy * (bot - top)


@njit(cache=True, nogil=True)
def _cost8(stack, cu, cv, offs, ref, zero_mean, diff, gx, gy):
    """SSD of the 8-pixel pattern centred at (cu, cv) against ``ref`` (8,) (zero-mean
    difference when asked), filling ``diff``, ``gx``, ``gy`` (8,); invalid samples read
    as 0 (``BilinearImage.sample``). Returns (SSD, all samples valid)."""
    h, w = stack.shape[0], stack.shape[1]
    ok = True
    for k in range(8):
        u, v = cu + offs[k, 0], cv + offs[k, 1]
        if u >= 1.0 and u < w - 2.0 and v >= 1.0 and v < h - 2.0:
            u0, v0 = int(u), int(v)
            fx, fy = u - u0, v - v0
            diff[k] = _bilinear(stack, u0, v0, fx, fy, 0)
            gx[k] = _bilinear(stack, u0, v0, fx, fy, 1)
            gy[k] = _bilinear(stack, u0, v0, fx, fy, 2)
        else:
            ok = False
            diff[k], gx[k], gy[k] = 0.0, 0.0, 0.0
        diff[k] = diff[k] - ref[k]
    if zero_mean:
        m = _sum8(diff) / 8.0
        for k in range(8):
            diff[k] = diff[k] - m
    sq = np.empty(8)
    for k in range(8):
        sq[k] = diff[k] * diff[k]
    return _sum8(sq), ok


@njit(cache=True, nogil=True)
def _refine_kernel(stack, x0, l, s, offs, ref, step, iters, zero_mean):
    """``_refine`` per point (the arithmetic of its former numpy form, bit for bit)."""
    n = s.shape[0]
    s_out, best = s.copy(), np.empty(n)
    diff, gx, gy, jl, tmp = np.empty(8), np.empty(8), np.empty(8), np.empty(8), np.empty(8)
    for i in range(n):
        si = s_out[i]
        be, _ = _cost8(stack, x0[i, 0] + si * l[i, 0], x0[i, 1] + si * l[i, 1], offs, ref[i], zero_mean, diff, gx, gy)
        for _ in range(iters):
            _cost8(stack, x0[i, 0] + si * l[i, 0], x0[i, 1] + si * l[i, 1], offs, ref[i], zero_mean, diff, gx, gy)
            for k in range(8):
                jl[k] = gx[k] * l[i, 0] + gy[k] * l[i, 1]
            if zero_mean:
                m = _sum8(jl) / 8.0
                for k in range(8):
                    jl[k] = jl[k] - m
            for k in range(8):
                tmp[k] = jl[k] * jl[k]
            H = _sum8(tmp)
            for k in range(8):
                tmp[k] = jl[k] * diff[k]
            ds = min(max(-_sum8(tmp) / max(H, 1e-9), -0.5 * step), 0.5 * step)
            s_new = si + ds
            e_new, v_new = _cost8(stack, x0[i, 0] + s_new * l[i, 0], x0[i, 1] + s_new * l[i, 1], offs,
                                  ref[i], zero_mean, diff, gx, gy)
            if v_new and e_new < be:
                si, be = s_new, e_new
        s_out[i], best[i] = si, be
    return s_out, best


def _triangulate(f: np.ndarray, uv1: np.ndarray, R: np.ndarray, t: np.ndarray, K1: Pinhole):
    """rho from [p]x (R f + rho t) = 0 in least squares (module docstring)."""
    p = K1.unproject(uv1)
    c = np.cross(p, f @ R.T)
    e = np.cross(p, np.broadcast_to(t, p.shape))
    ee = (e * e).sum(1)
    return -(c * e).sum(1) / np.maximum(ee, 1e-300), ee > 1e-18


def _variance(host_g: np.ndarray, tgt_g: np.ndarray, l: np.ndarray, rho: np.ndarray, f, R, t,
              K1: Pinhole, sigma_I: float) -> tuple[np.ndarray, np.ndarray]:
    """(V, sigma_px): V = sigma_px^2 / |dx/drho|^2 (module docstring); host_g, tgt_g (N, P, 2)."""
    along = (host_g * l[:, None, :]).sum(-1)
    across = host_g[..., 0] * l[:, None, 1] - host_g[..., 1] * l[:, None, 0]
    a, b = (along ** 2).sum(-1), (across ** 2).sum(-1)
    geo = 0.2 + 0.2 * (a + b) / np.maximum(a, 1e-9)
    gl = (tgt_g * l[:, None, :]).sum(-1)
    photo2 = 2 * sigma_I ** 2 * gl.shape[1] / np.maximum((gl ** 2).sum(-1), 1e-9)
    q = f @ R.T + rho[:, None] * t
    z = np.where(np.abs(q[:, 2]) > 1e-9, q[:, 2], 1e-9)
    dx = K1.fx * (t[0] * z - q[:, 0] * t[2]) / z ** 2   # seed: (t1 z' - x' t3) / z'^2
    dy = K1.fy * (t[1] * z - q[:, 1] * t[2]) / z ** 2
    s2 = geo ** 2 + photo2
    return s2 / np.maximum(dx * dx + dy * dy, 1e-18), np.sqrt(s2)


def epipolar_search(left: np.ndarray | ImageSampler, right: np.ndarray | ImageSampler,
                    uv: np.ndarray, K0: Pinhole, K1: Pinhole, T_c1_c0: gtsam.Pose3,
                    config: EpipolarConfig = EpipolarConfig(),
                    ab_right: tuple[float, float] = (0.0, 0.0)) -> EpipolarResult:
    """Search the inverse depth of the host pixels ``uv`` (N, 2) of image ``left`` in ``right``.

    Images are undistorted pinhole images ((H, W) arrays or ``ImageSampler``s); they need
    not be rectified. ``T_c1_c0`` maps host-camera points into the target camera.
    ``ab_right`` = [a, b]: the target's brightness is e^a I + b (ignored with zero_mean
    except for the gain).
    """
    cfg = config
    L, Rimg = _as_sampler(left), _as_sampler(right)
    uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
    R, t = T_c1_c0.rotation().matrix(), T_c1_c0.translation()
    host = make_host_patch(L, uv, K0)
    f = K0.unproject(uv)
    ref = np.exp(ab_right[0]) * host.intensity + ab_right[1]
    offs = PATTERN @ (K1.K @ R @ np.linalg.inv(K0.K))[:2, :2].T
    x0, l, length, ok = _line_geometry(f, R, t, K1, cfg)
    ok &= host.valid.all(1)
    s_int, best, quality = _discrete_search(Rimg, x0, l, length, ok, offs, ref, cfg)
    ok &= np.isfinite(best)
    s_best, e_ref = _refine(Rimg, x0, l, np.where(ok, s_int, 0.0), offs, ref, cfg)
    uv1 = x0 + s_best[:, None] * l
    rho, tri_ok = _triangulate(f, uv1, R, t, K1)
    P = PATTERN.shape[0]
    energy = e_ref / P
    _, tgx, tgy, _ = Rimg.sample(uv1[:, None, 0] + offs[:, 0], uv1[:, None, 1] + offs[:, 1])
    _, hgx, hgy, _ = L.sample(uv[:, None, 0] + PATTERN[:, 0], uv[:, None, 1] + PATTERN[:, 1])
    V, sigma_px = _variance(np.stack([hgx, hgy], -1), np.stack([tgx, tgy], -1), l, rho, f, R, t, K1, cfg.sigma_I)
    ok &= tri_ok & (quality >= cfg.min_quality) & (energy <= cfg.max_energy)
    ok &= np.isfinite(rho) & (rho > 0) & np.isfinite(V)
    return EpipolarResult(rho, V, sigma_px, quality, energy, uv1, ok)


def undistort_pinhole(image: np.ndarray, K: np.ndarray, distortion: tuple[float, ...],
                      model: str = "radial-tangential") -> np.ndarray:
    """Undistort a (H, W) image to the pinhole camera with the same ``K`` (float64 output).

    ``model``: ``"radial-tangential"`` (k1, k2, p1, p2), ``"equidistant"`` (k1..k4) or
    ``"none"``. Pixels mapped from outside the source are 0. The remap tables are
    computed once per camera and image size (``_undistort_maps``).
    """
    import cv2  # the pipeline layer may use cv2; factors/ may not

    img = np.asarray(image)
    if model == "none" or not any(distortion):
        return img.astype(np.float64)
    h, w = img.shape[:2]
    m1, m2 = _undistort_maps(tuple(np.asarray(K, float).ravel()), tuple(float(d) for d in distortion),
                             model, w, h)
    return cv2.remap(img.astype(np.float32), m1, m2, cv2.INTER_LINEAR).astype(np.float64)


@lru_cache(maxsize=8)
def _undistort_maps(K: tuple, distortion: tuple, model: str, w: int, h: int):
    """cv2 remap tables (float32) of :func:`undistort_pinhole`."""
    import cv2

    Km, d = np.array(K).reshape(3, 3), np.array(distortion)
    if model == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(Km, d, np.eye(3), Km, (w, h), cv2.CV_32FC1)
    if model == "radial-tangential":
        return cv2.initUndistortRectifyMap(Km, d, None, Km, (w, h), cv2.CV_32FC1)
    raise ValueError(f"undistort_pinhole: unknown distortion model {model!r}")
