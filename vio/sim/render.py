"""Ray-casting renderer (numba), EuRoC-like cameras, projection and exposure helpers.

Images are undistorted pinhole renders: pixel ``(x, y)`` (integer = pixel centre)
looks along ``R_w_c [(x - cx)/fx, (y - cy)/fy, 1]``. Each image row has its own
camera pose ``T_w_c`` (rolling shutter; repeat one pose for a global shutter), or each
pixel one of a table of poses (``pose_of``: a rolling shutter seen through a lens, whose
sensor rows are curves in this pinhole image, ``vio.sim.optics.DistortedView.sensor_row``).
Textures are sampled trilinearly from the mip pyramid at the level that matches
the pixel footprint on the surface, which keeps the images free of aliasing shimmer.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numba import njit, prange

from vio.conventions import pose_from_matrix
from vio.io.types import CameraCalib
from vio.sim.scene import EPS_T, Scene
from vio.sim.texture import TextureAtlas

# EuRoC V1_01 cam0/cam1 (MT9V034 on the VI-Sensor): T_BS and pinhole intrinsics
EUROC_T_BS = {
    "cam0": [[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
             [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
             [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
             [0.0, 0.0, 0.0, 1.0]],
    "cam1": [[0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
             [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
             [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
             [0.0, 0.0, 0.0, 1.0]],
}
EUROC_INTRINSICS = {"cam0": (458.654, 457.296, 367.215, 248.375),
                    "cam1": (457.587, 456.134, 379.999, 255.238)}
MIN_COS = 0.1  # footprint clamp at grazing incidence


def sim_camera(name: str, scale: float = 1.0, rate_hz: float = 20.0,
               line_time_s: float = 0.0) -> CameraCalib:
    """EuRoC ``cam0``/``cam1`` calibration with zero distortion, resolution and
    intrinsics scaled by ``scale`` (pixel-centre convention)."""
    fx, fy, cx, cy = EUROC_INTRINSICS[name]
    res = (max(8, round(752 * scale)), max(8, round(480 * scale)))
    k = (fx * scale, fy * scale, (cx + 0.5) * scale - 0.5, (cy + 0.5) * scale - 0.5)
    return CameraCalib(pose_from_matrix(np.array(EUROC_T_BS[name])), k, "radial-tangential",
                       (0.0, 0.0, 0.0, 0.0), res, rate_hz, line_time_s, name)


def project_point(calib: CameraCalib, T_w_c: gtsam.Pose3, p_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N,2) and camera z-depths (N,) of world points ``p_w`` (N,3) (pinhole)."""
    M = T_w_c.inverse().matrix()
    p_c = np.atleast_2d(p_w) @ M[:3, :3].T + M[:3, 3]
    fx, fy, cx, cy = calib.intrinsics
    z = p_c[:, 2]
    return np.stack([fx * p_c[:, 0] / z + cx, fy * p_c[:, 1] / z + cy], -1), z


def pixel_rays(calib: CameraCalib, T_w_c: gtsam.Pose3, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World origins (N,3) and unit directions (N,3) of the rays through pixels ``uv`` (N,2)."""
    fx, fy, cx, cy = calib.intrinsics
    uv = np.atleast_2d(np.asarray(uv, float))
    d_c = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], -1)
    d_c /= np.linalg.norm(d_c, axis=1, keepdims=True)
    M = T_w_c.matrix()
    return np.broadcast_to(M[:3, 3], d_c.shape).copy(), d_c @ M[:3, :3].T


@njit(cache=True, fastmath=True, inline="always")
def _comp(x: float, y: float, z: float, a: int) -> float:
    return x if a == 0 else (y if a == 1 else z)


@njit(cache=True, fastmath=True)
def _intersect(ox, oy, oz, dx, dy, dz, rects, cyls):
    """Nearest hit of a unit ray: (t, surface id or -1, u, v, |cos incidence|)."""
    best, sid, bu, bv, bcos = np.inf, -1, 0.0, 0.0, 1.0
    for i in range(rects.shape[0]):
        ax = int(rects[i, 0])
        da = _comp(dx, dy, dz, ax)
        if da * rects[i, 2] >= 0.0:
            continue
        t = (rects[i, 1] - _comp(ox, oy, oz, ax)) / da
        if t <= EPS_T or t >= best:
            continue
        ua, va = int(rects[i, 3]), int(rects[i, 6])
        u = _comp(ox, oy, oz, ua) + t * _comp(dx, dy, dz, ua)
        v = _comp(ox, oy, oz, va) + t * _comp(dx, dy, dz, va)
        if u < rects[i, 4] or u > rects[i, 5] or v < rects[i, 7] or v > rects[i, 8]:
            continue
        best, sid, bu, bv, bcos = t, i, u - rects[i, 4], v - rects[i, 7], abs(da)
    for k in range(cyls.shape[0]):
        cx, cy, r = cyls[k, 0], cyls[k, 1], cyls[k, 2]
        a = dx * dx + dy * dy
        if a < 1e-18:
            continue
        b = (ox - cx) * dx + (oy - cy) * dy
        disc = b * b - a * ((ox - cx) ** 2 + (oy - cy) ** 2 - r * r)
        if disc < 0.0:
            continue
        t = (-b - math.sqrt(disc)) / a
        if t <= EPS_T or t >= best:
            continue
        z = oz + t * dz
        if z < cyls[k, 3] or z > cyls[k, 4]:
            continue
        nx, ny = (ox + t * dx - cx) / r, (oy + t * dy - cy) / r
        best, sid = t, rects.shape[0] + k
        bu, bv, bcos = r * (math.atan2(ny, nx) + math.pi), z - cyls[k, 3], abs(dx * nx + dy * ny)
    return best, sid, bu, bv, bcos


@njit(cache=True, fastmath=True)
def _bilinear(tex, off, w, h, x, y):
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0, y0 = min(int(x), w - 2) if w > 1 else 0, min(int(y), h - 2) if h > 1 else 0
    fx, fy = x - x0, y - y0
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    a = tex[off + y0 * w + x0] * (1 - fx) + tex[off + y0 * w + x1] * fx
    b = tex[off + y1 * w + x0] * (1 - fx) + tex[off + y1 * w + x1] * fx
    return a * (1 - fy) + b * fy


@njit(cache=True, fastmath=True)
def _sample(tex, table, sid, u, v, lvl, density):
    """Trilinear texture value at (u, v) metres, mip level ``lvl`` (float)."""
    nl = table.shape[1]
    if lvl <= 0.0:  # magnification: level 0 only
        return _bilinear(tex, table[sid, 0, 0], table[sid, 0, 1], table[sid, 0, 2],
                         u * density - 0.5, v * density - 0.5)
    lvl = min(lvl, nl - 1.0)
    l0 = min(int(lvl), nl - 2)
    f = lvl - l0
    out = 0.0
    for k in range(2):
        off, w, h = table[sid, l0 + k, 0], table[sid, l0 + k, 1], table[sid, l0 + k, 2]
        s = 1.0 / (1 << (l0 + k))
        val = _bilinear(tex, off, w, h, (u * density - 0.5) * s, (v * density - 0.5) * s)
        out += val * (f if k == 1 else 1.0 - f)
    return out


@njit(cache=True, fastmath=True, parallel=True)
def _render_kernel(R_rows, p_rows, pose_of, K, width, rects, cyls, tex, table, density, img, depth):
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    for r in prange(img.shape[0]):
        yc = (r - cy) / fy
        for x in range(width):
            i = pose_of[r, x]
            R = R_rows[i]
            ox, oy, oz = p_rows[i, 0], p_rows[i, 1], p_rows[i, 2]
            xc = (x - cx) / fx
            n = math.sqrt(xc * xc + yc * yc + 1.0)
            a, b, c = xc / n, yc / n, 1.0 / n
            dx = R[0, 0] * a + R[0, 1] * b + R[0, 2] * c
            dy = R[1, 0] * a + R[1, 1] * b + R[1, 2] * c
            dz = R[2, 0] * a + R[2, 1] * b + R[2, 2] * c
            t, sid, u, v, cs = _intersect(ox, oy, oz, dx, dy, dz, rects, cyls)
            if sid < 0:
                img[r, x] = 0.0
                depth[r, x] = np.inf
                continue
            foot = t * c / fx / max(cs, MIN_COS) * density  # texels per pixel
            lvl = math.log2(max(foot, 1e-6))
            img[r, x] = _sample(tex, table, sid, u, v, lvl, density)
            depth[r, x] = t * c


def render(scene: Scene, atlas: TextureAtlas, calib: CameraCalib, R_w_c: np.ndarray,
           p_w_c: np.ndarray, pose_of: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render one image with per-row (or per-pixel) camera poses.

    ``R_w_c`` (N,3,3) and ``p_w_c`` (N,3): camera-in-world poses; without ``pose_of`` one
    per row (N = image height H), else pixel (y, x) is seen from pose ``pose_of[y, x]``
    ((H, W) integers in [0, N)). Returns ``(image, depth)``, both (H, W) float32: radiance
    0..255 before exposure and noise, and camera z-depth in metres (``inf`` where nothing
    is hit).
    """
    w, h = calib.resolution
    R = np.ascontiguousarray(R_w_c, dtype=np.float64)
    p = np.ascontiguousarray(p_w_c, dtype=np.float64)
    n = h if pose_of is None else len(R)
    if R.shape != (n, 3, 3) or p.shape != (n, 3):
        raise ValueError(f"render: need poses of shape ({n},3,3)/({n},3), got {R.shape}/{p.shape}")
    if pose_of is None:
        pose_of = np.broadcast_to(np.arange(h, dtype=np.int64)[:, None], (h, w))
    elif pose_of.shape != (h, w) or pose_of.min() < 0 or pose_of.max() >= n:
        raise ValueError(f"render: pose_of must be ({h},{w}) indices in [0,{n}), got {pose_of.shape}")
    pose_of = np.ascontiguousarray(pose_of, dtype=np.int64)
    img = np.empty((h, w), np.float32)
    depth = np.empty((h, w), np.float32)
    _render_kernel(R, p, pose_of, np.asarray(calib.intrinsics, float), w, scene.rects, scene.cyls,
                   atlas.data, atlas.table, atlas.texels_per_m, img, depth)
    return img, depth


def camera_row_poses(R_w_b: np.ndarray, p_w_b: np.ndarray, T_b_c: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses ``T_w_c = T_w_b T_b_c`` for stacked body poses (N,3,3), (N,3)."""
    M = T_b_c.matrix()
    return R_w_b @ M[:3, :3], p_w_b + R_w_b @ M[:3, 3]


def exposure_sequence(mode: str, t_s: np.ndarray, log_gain_amp: float, bias_amp: float,
                      period_s: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Affine brightness ``(a, b)`` per frame time ``t_s`` (N,): zeros for ``"none"``,
    a random sum of sinusoids for ``"smooth"``, piecewise constant (a new random value
    every ``period_s / 2``) for ``"step"``; ``|a| <= log_gain_amp``, ``|b| <= bias_amp``."""
    t = np.asarray(t_s, float)
    if mode == "none":
        return np.zeros_like(t), np.zeros_like(t)
    if mode == "smooth":
        out = []
        for amp in (log_gain_amp, bias_amp):
            w = rng.dirichlet([1.0, 1.0]) * amp
            f = rng.uniform(0.6, 1.4, 2) / period_s
            ph = rng.uniform(0, 2 * np.pi, 2)
            out.append(np.sin(np.outer(t, 2 * np.pi * f) + ph) @ w)
        return out[0], out[1]
    if mode == "step":
        k = np.floor((t - t.min()) / (period_s / 2)).astype(int) if t.size else t.astype(int)
        n = int(k.max()) + 1 if t.size else 0
        a = rng.uniform(-1, 1, n) * log_gain_amp
        b = rng.uniform(-1, 1, n) * bias_amp
        if n:
            a[0] = b[0] = 0.0  # start at the nominal exposure
        return a[k], b[k]
    raise ValueError(f"exposure mode {mode!r} not in ('none', 'smooth', 'step')")


def photometric(radiance: np.ndarray, a: float, b: float, noise_sigma: float,
                rng: np.random.Generator) -> np.ndarray:
    """``clip(round(exp(a) * I + b + noise))`` as uint8 (noise Gaussian, gray levels)."""
    img = np.exp(a) * radiance.astype(np.float32) + np.float32(b)
    if noise_sigma > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
