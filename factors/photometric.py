"""Direct photometric residuals (DSO / Stereo DSO) with exact Jacobians in GTSAM conventions.

Residual of one pattern pixel p of a point hosted in frame i, observed in frame j
(seed 000, f_m with DSO's affine brightness model):

    r = (I_j[p'] - b_j) - s (I_i[p] - b_i),      s = (t_j e^{a_j}) / (t_i e^{a_i}),
    p' = pi(K_j, q),   q = R_ji f + rho t_ji   (= rho * p_cj, DSO's scaled warp),

with f = K_i^{-1} [u, v, 1] (z = 1), rho the inverse depth (1/m) of the host pixel,
T_ji = T_cj_ci = T_c_b T_w_bj^{-1} T_w_bi T_b_c. Working with the scaled point q keeps
the warp finite for far points (rho -> 0); d p'/d rho = dpi/dq t_ji is the seed's
(t1 z' - x' t3) / z'^2 term. Every pattern pixel uses the centre's inverse depth (DSO).

Pose Jacobians (GTSAM retract T Exp(xi), xi = [omega, v]), with q_b = rho * p_b:
    dq/dxi_j = R_c_b [ [q_bj]x, -rho I ],       q_bj = R_b_c q + rho t_b_c,
    dq/dxi_i = R_cj_bi [ -[q_bi]x, rho I ],     q_bi = R_b_c f + rho t_b_c.
Affine: each frame's brightness is one 2-vector key [a, b] (five keys per temporal
factor rather than seven with scalar keys), with dr/d[a_j, b_j] = [-s h, -1] and
dr/d[a_i, b_i] = [s h, s], h = I_i[p] - b_i. The static stereo factor has keys
(rho, [a, b] of the right image relative to the left) and a fixed T_c1_c0.

Weights (seed W_m and DSO), frozen at the linearization point (IRLS):
    W = lambda * c^2 / (c^2 + |grad I_i(p)|^2) / (2 sigma_I^2 + (dr/drho)^2 V),
then Huber with threshold k on the whitened residual e = sqrt(W) r, weight
min(1, k / |e|), per residual (GTSAM's Robust noise model would weight the whole
8-vector at once). The callback returns sqrt(W w_huber) * (r, J); the noise model is
Unit. The Jacobians are exact for the raw residual; the weights are constants of each
linearization, so GTSAM's error is the IRLS surrogate 0.5 sum W w_huber r^2. Pass
V > 0 only when rho is *not* a variable (tracking), or its uncertainty counts twice.

Rolling shutter (``Shutter``, seed 004's row time): row y is exposed y * line_time after
row 0, the state's time; to first order in that time the host point is moved back to its
row 0 along the host camera's twist (``host_points``) and the target image is sampled at
q_s = q - s (omega_j x q + rho v_j), s = line_time * row(q); the Jacobians carry the chain
rule through q_s and s (the shared suite checks them on a 48-ms readout).

Invalid rows (target pixel outside the image, q_z <= 1e-6, host pattern pixel outside
its image) give zero residual and zero Jacobian rows; nothing here raises for them.

Granularity: one factor per (point, host, target) here; ``factors.photometric_point``
has one factor per point over all its targets (used by ``vio.direct``). A factor per
host-target pair with
N points would make GTSAM treat its 8N x (16 + N) Jacobian as one dense block over all
N inverse depths (dense N x N fill, O(N^3) elimination), destroying the sparsity that
lets inverse depths be eliminated cheaply. The price is one Python callback per
(point, target), ~100-170 us each (benchmarks/bench_photometric.py), dominated by numpy
call overhead on 8-element arrays. The math below is vectorized over points and
pattern pixels, so tracking (``vio.direct.trackframe``) evaluates hundreds of points
in one call (~2 us per point).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.image_ops import ImageSampler
from factors.photometric_shutter import Shutter, cross, rolled_bearings, target_row_s
from factors.photometric_warp import pixel_row_s

PATTERN = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]],
                   dtype=np.float64)
"""DSO's 8-pixel residual pattern (staticPattern[8]), offsets (du, dv) in pixels."""

MIN_Z = 1e-6


@dataclass(frozen=True)
class Pinhole:
    """Pinhole intrinsics (pixels) of an undistorted image."""

    fx: float
    fy: float
    cx: float
    cy: float

    @staticmethod
    def from_K(K: np.ndarray) -> "Pinhole":
        K = np.asarray(K, dtype=float)
        return Pinhole(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) to bearings (..., 3) with z = 1."""
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy,
                         np.ones(uv.shape[:-1])], axis=-1)

    def project(self, q: np.ndarray) -> np.ndarray:
        """Points (..., 3) (any positive scale) to pixels (..., 2)."""
        q = np.asarray(q, dtype=np.float64)
        return np.stack([self.fx * q[..., 0] / q[..., 2] + self.cx,
                         self.fy * q[..., 1] / q[..., 2] + self.cy], axis=-1)


@dataclass(frozen=True, eq=False)
class HostPatch:
    """Constants of N points in their host image (P pattern pixels each).

    ``uv`` (N, 2) centre pixels; ``bearing`` (N, P, 3) K^-1 [u, v, 1] of each pattern
    pixel; ``intensity`` (N, P) I_i[p]; ``grad_sq`` (N, P) |grad I_i[p]|^2;
    ``valid`` (N, P) host pixel inside the host image.
    """

    uv: np.ndarray
    bearing: np.ndarray
    intensity: np.ndarray
    grad_sq: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def subset(self, idx: np.ndarray) -> "HostPatch":
        return HostPatch(self.uv[idx], self.bearing[idx], self.intensity[idx],
                         self.grad_sq[idx], self.valid[idx])


def make_host_patch(host: ImageSampler, uv: np.ndarray, K: Pinhole,
                    pattern: np.ndarray = PATTERN) -> HostPatch:
    """Sample the host image at every pattern pixel of the points ``uv`` (N, 2)."""
    uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
    pix = uv[:, None, :] + pattern[None, :, :]
    I, gx, gy, valid = host.sample(pix[..., 0], pix[..., 1])
    return HostPatch(uv, K.unproject(pix), I, gx * gx + gy * gy, valid)


@dataclass(frozen=True)
class PhotometricParams:
    """Weighting of a photometric term.

    ``sigma_I`` intensity noise std (intensity units); ``grad_c`` DSO's gradient-weight
    constant c (intensity/pixel); ``huber_k`` Huber threshold on the whitened residual
    (None: plain least squares); ``weight`` a global factor (lambda of the static
    stereo term in E = E_d + lambda E_s); ``exposure_ratio`` t_j / t_i.
    """

    sigma_I: float = 4.0
    grad_c: float = 50.0
    huber_k: float | None = 1.345
    weight: float = 1.0
    exposure_ratio: float = 1.0


@dataclass(frozen=True, eq=False)
class PhotoEval:
    """Raw residuals and Jacobians of N points x P pattern pixels.

    ``r`` (N, P); ``valid`` (N, P); ``J`` maps a variable name to (N, P, d):
    ``pose_i``/``pose_j`` (6), ``rho`` (1), ``ab_i``/``ab_j`` (2) for the temporal term,
    ``rho`` and ``ab`` for the stereo term. ``dr_drho`` (N, P); ``uv`` (N, P, 2) target
    pixels.
    """

    r: np.ndarray
    valid: np.ndarray
    J: dict
    dr_drho: np.ndarray
    uv: np.ndarray


def host_points(host: HostPatch, rho: np.ndarray, shutter: Shutter | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """The scaled host points rho p_ci (N, P, 3) in the row-0 host camera and their
    derivative in rho (N, 1, 3): the bearing f without a shutter; with one, the point seen
    at row time s_h (its centre row's) moved back to row 0, f + s_h (omega_h x f) + rho s_h v_h."""
    if shutter is None or shutter.line_time_s == 0.0:
        return host.bearing, np.zeros((len(rho), 1, 3))
    f, sv = rolled_bearings(host.bearing, pixel_row_s(shutter.line_time_s, host.uv, shutter.host_rows),
                            shutter.host)
    return f + rho[:, None, None] * sv[:, None, :], sv[:, None, :]


def _warp(host: HostPatch, rho: np.ndarray, R: np.ndarray, t: np.ndarray, K: Pinhole,
          target: ImageSampler, shutter: Shutter | None = None):
    """Scaled warp: (q (N, P, 3), target pixels, intensity, dr/dq (N, P, 3), valid,
    dr/drho (N, P), host points ``host_points``), zero where invalid. q = R f + rho t is
    the point in the row-0 target camera; with a ``shutter`` the image is sampled at
    q_s = q - s (omega_j x q + rho v_j), s = line_time * (row of q), and dr/dq is the
    chain rule through q_s and s."""
    f, sv = host_points(host, rho, shutter)
    rr = rho[:, None, None]
    q = f @ R.T + rr * t
    z = q[..., 2]
    front = z > MIN_Z
    zs = np.where(front, z, 1.0)
    rolling = shutter is not None and shutter.line_time_s != 0.0
    if rolling:
        w, v = np.asarray(shutter.target[:3], float), np.asarray(shutter.target[3:], float)
        s, ds_dx, ds_dy = target_row_s(shutter, K, q, zs)
        a = cross(np.broadcast_to(w, q.shape), q, np.empty(q.shape)) + rr * v
        qs = q - s * a
        front &= qs[..., 2] > MIN_Z
        zs = np.where(front, qs[..., 2], 1.0)
    else:
        qs = q
    u = K.fx * qs[..., 0] / zs + K.cx
    v_px = K.fy * qs[..., 1] / zs + K.cy
    I, gx, gy, inside = target.sample(u, v_px)
    valid = front & inside & host.valid
    gu = np.where(valid, gx * K.fx / zs, 0.0)
    gv = np.where(valid, gy * K.fy / zs, 0.0)
    drdq = np.stack([gu, gv, -(gu * qs[..., 0] + gv * qs[..., 1]) / zs], axis=-1)
    if not rolling:
        return q, np.stack([u, v_px], -1), I, drdq, valid, drdq @ t, f
    # dq_s/dq = I - s [omega]x - a (ds/dq)^T, ds/dq = ds/dx d(q0/z)/dq + ds/dy d(q1/z)/dq
    # (without a lens line_time fy [0, 1/z, -y/z^2]); rho enters q_s directly (-s rho v)
    # and through q (t + R sv)
    zq = np.where(valid, z, 1.0)
    da = np.sum(drdq * a, -1)
    drdrho = -s[..., 0] * (drdq @ v)
    drdq = drdq - s * cross(drdq, np.broadcast_to(w, q.shape), np.empty(q.shape))
    kx, ky = ds_dx / zq, ds_dy / zq
    drdq[..., 0] -= da * kx
    drdq[..., 1] -= da * ky
    drdq[..., 2] += da * (kx * q[..., 0] + ky * q[..., 1]) / zq
    drdrho = drdrho + drdq @ t + np.sum((drdq @ R) * sv, -1)
    return q, np.stack([u, v_px], -1), I, drdq, valid, drdrho, f


def _affine(host: HostPatch, I: np.ndarray, valid: np.ndarray, ab_i: np.ndarray,
            ab_j: np.ndarray, exposure_ratio: float):
    """Residual and the affine Jacobians (N, P, 2) for [a_i, b_i] and [a_j, b_j]."""
    s = exposure_ratio * np.exp(ab_j[0] - ab_i[0])
    h = np.where(valid, s * (host.intensity - ab_i[1]), 0.0)
    r = np.where(valid, I - ab_j[1], 0.0) - h
    one = valid.astype(np.float64)
    J_ab_i = np.stack([h, s * one], axis=-1)
    J_ab_j = np.stack([-h, -one], axis=-1)
    return r, J_ab_i, J_ab_j


def temporal_eval(T_w_bi: gtsam.Pose3, T_w_bj: gtsam.Pose3, rho: np.ndarray, ab_i: np.ndarray,
                  ab_j: np.ndarray, host: HostPatch, target: ImageSampler, K_j: Pinhole,
                  T_b_c: gtsam.Pose3, exposure_ratio: float = 1.0,
                  shutter: Shutter | None = None) -> PhotoEval:
    """Temporal residual (host keyframe i -> target frame j) of N points, rho (N,);
    ``shutter``: both images' rolling shutter (cam0 twists of frames i and j)."""
    rho = np.asarray(rho, dtype=np.float64).reshape(-1)
    T_bj_bi = T_w_bj.between(T_w_bi)
    T_ji = T_b_c.inverse().compose(T_bj_bi).compose(T_b_c)
    R_ji, t_ji = T_ji.rotation().matrix(), T_ji.translation()
    R_b_c, t_b_c = T_b_c.rotation().matrix(), T_b_c.translation()
    q, uv, I, drdq, valid, dr_drho, f = _warp(host, rho, R_ji, t_ji, K_j, target, shutter)
    r, J_ab_i, J_ab_j = _affine(host, I, valid, np.asarray(ab_i, float),
                                np.asarray(ab_j, float), exposure_ratio)
    rr = rho[:, None, None]
    g_b = drdq @ R_b_c.T                       # dr/dq R_c_b  (row vectors)
    q_bj = q @ R_b_c.T + rr * t_b_c
    J_pj = np.empty(r.shape + (6,))
    cross(g_b, q_bj, J_pj[..., :3])
    np.multiply(-rr, g_b, out=J_pj[..., 3:])
    h = g_b @ T_bj_bi.rotation().matrix()      # dr/dq R_c_b R_bj_bi
    q_bi = f @ R_b_c.T + rr * t_b_c
    J_pi = np.empty(r.shape + (6,))
    cross(q_bi, h, J_pi[..., :3])             # -(h x q_bi)
    np.multiply(rr, h, out=J_pi[..., 3:])
    J = {"pose_i": J_pi, "pose_j": J_pj, "rho": dr_drho[..., None],
         "ab_i": J_ab_i, "ab_j": J_ab_j}
    return PhotoEval(r, valid, J, dr_drho, uv)


def stereo_eval(rho: np.ndarray, ab: np.ndarray, host: HostPatch, target: ImageSampler,
                K_r: Pinhole, T_r_l: gtsam.Pose3, exposure_ratio: float = 1.0,
                shutter: Shutter | None = None) -> PhotoEval:
    """Static stereo residual (left host -> right target at one time), rho (N,).

    ``ab`` = [a, b] of the right image relative to the left (left affine is [0, 0]);
    ``T_r_l`` = T_c1_c0 is a fixed constant; ``shutter``: the left (host) and right
    (target) cameras' twists of the one frame.
    """
    rho = np.asarray(rho, dtype=np.float64).reshape(-1)
    R, t = T_r_l.rotation().matrix(), T_r_l.translation()
    _, uv, I, drdq, valid, dr_drho, _ = _warp(host, rho, R, t, K_r, target, shutter)
    r, _, J_ab = _affine(host, I, valid, np.zeros(2), np.asarray(ab, float), exposure_ratio)
    return PhotoEval(r, valid, {"rho": dr_drho[..., None], "ab": J_ab}, dr_drho, uv)


def sqrt_weights(ev: PhotoEval, host: HostPatch, params: PhotometricParams,
                 idepth_var: np.ndarray | float = 0.0) -> np.ndarray:
    """sqrt of W * w_huber per residual (N, P); zero where invalid (see module doc)."""
    c2 = params.grad_c ** 2
    V = np.asarray(idepth_var, dtype=np.float64).reshape(-1, 1) if np.ndim(idepth_var) else idepth_var
    W = params.weight * (c2 / (c2 + host.grad_sq)) / (2 * params.sigma_I ** 2 + ev.dr_drho ** 2 * V)
    sw = np.sqrt(W)
    if params.huber_k is not None:
        e = np.abs(sw * ev.r)
        sw = sw * np.sqrt(np.where(e > params.huber_k, params.huber_k / np.maximum(e, 1e-300), 1.0))
    return np.where(ev.valid, sw, 0.0)


def _rows(ev: PhotoEval, sw: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, list]:
    """Weighted residual (N*P,) and Jacobian blocks (N*P, d), in ``names`` order."""
    r = (sw * ev.r).reshape(-1)
    jacs = [(sw[..., None] * ev.J[n]).reshape(r.shape[0], -1) for n in names]
    return r, jacs


def temporal_residual_fn(host: HostPatch, target: ImageSampler, K_j: Pinhole, T_b_c: gtsam.Pose3,
                         params: PhotometricParams, idepth_var: float = 0.0,
                         shutter: Shutter | None = None) -> Callable:
    """The residual function of a temporal factor over keys
    ``[T_w_bi (pose3), T_w_bj (pose3), rho (1), ab_i (2), ab_j (2)]`` (``factors.adapter``
    convention), for a single point (``len(host) == 1``): 8 weighted rows."""
    if len(host) != 1:
        raise ValueError(f"one factor per point: host patch has {len(host)} points")
    names = ("pose_i", "pose_j", "rho", "ab_i", "ab_j")

    def fn(args: list) -> tuple[np.ndarray, list]:
        T_i, T_j, rho, ab_i, ab_j = args
        ev = temporal_eval(T_i, T_j, rho, ab_i, ab_j, host, target, K_j, T_b_c,
                           params.exposure_ratio, shutter)
        return _rows(ev, sqrt_weights(ev, host, params, idepth_var), names)

    return fn


def stereo_residual_fn(host: HostPatch, target: ImageSampler, K_r: Pinhole, T_r_l: gtsam.Pose3,
                       params: PhotometricParams, idepth_var: float = 0.0,
                       shutter: Shutter | None = None) -> Callable:
    """Residual function of a static stereo factor over keys ``[rho (1), ab_r (2)]``."""
    if len(host) != 1:
        raise ValueError(f"one factor per point: host patch has {len(host)} points")

    def fn(args: list) -> tuple[np.ndarray, list]:
        rho, ab = args
        ev = stereo_eval(rho, ab, host, target, K_r, T_r_l, params.exposure_ratio, shutter)
        return _rows(ev, sqrt_weights(ev, host, params, idepth_var), ("rho", "ab"))

    return fn


def temporal_factor(keys: Sequence[int], host: HostPatch, target: ImageSampler, K_j: Pinhole,
                    T_b_c: gtsam.Pose3, params: PhotometricParams = PhotometricParams(),
                    idepth_var: float = 0.0, health: FactorHealth | None = None,
                    shutter: Shutter | None = None) -> gtsam.CustomFactor:
    """Temporal photometric factor of one point; keys = (T_w_bi, T_w_bj, rho, ab_i, ab_j),
    host and target keyframes distinct. Unit noise model: weights are inside (module doc)."""
    fn = temporal_residual_fn(host, target, K_j, T_b_c, params, idepth_var, shutter)
    m = host.bearing.shape[1]
    return custom_factor(gtsam.noiseModel.Unit.Create(m), keys, ["pose3", "pose3", 1, 2, 2],
                         fn, health)


def stereo_factor(keys: Sequence[int], host: HostPatch, target: ImageSampler, K_r: Pinhole,
                  T_r_l: gtsam.Pose3, params: PhotometricParams = PhotometricParams(),
                  idepth_var: float = 0.0, health: FactorHealth | None = None,
                  shutter: Shutter | None = None) -> gtsam.CustomFactor:
    """Static stereo factor of one point; keys = (rho, ab_right). Set ``params.weight`` to
    lambda for E = E_d + lambda E_s."""
    fn = stereo_residual_fn(host, target, K_r, T_r_l, params, idepth_var, shutter)
    m = host.bearing.shape[1]
    return custom_factor(gtsam.noiseModel.Unit.Create(m), keys, [1, 2], fn, health)
