"""One photometric factor per point over all its observations (``vio.direct.source``):
the static stereo term at the host (optional) and the temporal terms to M target
keyframes, vectorized over (M, P). Same math, conventions and weighting as
``factors.photometric`` (``temporal_eval`` / ``stereo_eval``, see its module docstring);
the point is rebuilt (remove + add) when it gains a target, like the landmark factor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.image_ops import ImageSampler
from factors.photometric import MIN_Z, HostPatch, PhotoEval, PhotometricParams, Pinhole, sqrt_weights, stereo_eval
from factors.photometric_shutter import cross


@dataclass(frozen=True, eq=False)
class StereoTerm:
    """The static stereo term of a point factor: right image of the host keyframe, its
    intrinsics, the fixed ``T_r_l`` = T_c1_c0 and its weighting (``weight`` = lambda)."""

    target: ImageSampler
    K: Pinhole
    T_r_l: gtsam.Pose3
    params: PhotometricParams


def point_eval(T_w_bi: gtsam.Pose3, rho: float, ab_i: np.ndarray, host: HostPatch,
               targets: Sequence[tuple[gtsam.Pose3, np.ndarray, ImageSampler]], K_j: Pinhole,
               T_b_c: gtsam.Pose3) -> PhotoEval:
    """Temporal residuals of ONE host point (``len(host) == 1``) in M targets
    ``(T_w_bj, ab_j, image)``: arrays (M, P); ``J`` has ``pose_i``, ``rho``, ``ab_i``,
    ``pose_j``, ``ab_j`` of shape (M, P, d) (row m depends only on target m)."""
    M = len(targets)
    R_b_c, t_b_c = T_b_c.rotation().matrix(), T_b_c.translation()
    T_c_b = T_b_c.inverse()
    R_ji, t_ji, R_jb = np.empty((M, 3, 3)), np.empty((M, 3)), np.empty((M, 3, 3))
    for m, (T_w_bj, _, _) in enumerate(targets):
        T_bj_bi = T_w_bj.between(T_w_bi)
        T_ji = T_c_b.compose(T_bj_bi).compose(T_b_c)
        R_ji[m], t_ji[m] = T_ji.rotation().matrix(), T_ji.translation()
        R_jb[m] = T_bj_bi.rotation().matrix()
    f = host.bearing[0]                                     # (P, 3)
    q = np.einsum("pk,mlk->mpl", f, R_ji) + rho * t_ji[:, None, :]
    z = q[..., 2]
    front = z > MIN_Z
    zs = np.where(front, z, 1.0)
    u = K_j.fx * q[..., 0] / zs + K_j.cx
    v = K_j.fy * q[..., 1] / zs + K_j.cy
    P = f.shape[0]
    I, gx, gy = np.empty((M, P)), np.empty((M, P)), np.empty((M, P))
    inside = np.empty((M, P), bool)
    for m, (_, _, img) in enumerate(targets):
        I[m], gx[m], gy[m], inside[m] = img.sample(u[m], v[m])
    valid = front & inside & host.valid
    gu = np.where(valid, gx * K_j.fx / zs, 0.0)
    gv = np.where(valid, gy * K_j.fy / zs, 0.0)
    drdq = np.stack([gu, gv, -(gu * q[..., 0] + gv * q[..., 1]) / zs], axis=-1)
    a_j = np.array([t[1][0] for t in targets])[:, None]
    b_j = np.array([t[1][1] for t in targets])[:, None]
    s = np.exp(a_j - ab_i[0])
    h = np.where(valid, s * (host.intensity - ab_i[1]), 0.0)
    r = np.where(valid, I - b_j, 0.0) - h
    one = valid.astype(np.float64)
    g_b = drdq @ R_b_c.T
    q_bj = q @ R_b_c.T + rho * t_b_c
    J_pj = np.empty((M, P, 6))
    cross(g_b, q_bj, J_pj[..., :3])
    np.multiply(-rho, g_b, out=J_pj[..., 3:])
    hh = np.einsum("mpk,mkl->mpl", g_b, R_jb)
    q_bi = f @ R_b_c.T + rho * t_b_c
    J_pi = np.empty((M, P, 6))
    cross(np.broadcast_to(q_bi, hh.shape), hh, J_pi[..., :3])
    np.multiply(rho, hh, out=J_pi[..., 3:])
    dr_drho = np.einsum("mpk,mk->mp", drdq, t_ji)
    J = {"pose_i": J_pi, "pose_j": J_pj, "rho": dr_drho[..., None],
         "ab_i": np.stack([h, s * one], -1), "ab_j": np.stack([-h, -one], -1)}
    return PhotoEval(r, valid, J, dr_drho, np.stack([u, v], -1))


def point_kinds(n_targets: int, stereo: bool) -> list:
    """Key kinds of ``point_factor``: [T_w_bi, rho, ab_i, (ab_right,) then
    (T_w_bj, ab_j) per target]."""
    return ["pose3", 1, 2] + ([2] if stereo else []) + ["pose3", 2] * n_targets


def point_residual_fn(host: HostPatch, targets: Sequence[ImageSampler], K_j: Pinhole,
                      T_b_c: gtsam.Pose3, params: PhotometricParams,
                      stereo: StereoTerm | None = None) -> Callable:
    """Residual function of a point factor over ``point_kinds(len(targets), stereo)``
    keys: rows [stereo (P) if any, then P per target]; one stacked Jacobian (adapter
    convention). Weights as ``sqrt_weights`` with V = 0 (rho is a variable)."""
    if len(host) != 1:
        raise ValueError(f"one factor per point: host patch has {len(host)} points")
    M, P = len(targets), host.bearing.shape[1]
    off = 1 if stereo is not None else 0          # the ab_right key shifts the target keys
    rows0 = P if stereo is not None else 0        # stereo rows come first
    dims = [6, 1, 2] + ([2] if stereo is not None else []) + [6, 2] * M
    cols = np.cumsum([0] + dims)
    m_rows = rows0 + P * M

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        T_i, rho, ab_i = args[0], float(args[1][0]), np.asarray(args[2], float)
        r = np.zeros(m_rows)
        J = np.zeros((m_rows, int(cols[-1])))
        if stereo is not None:
            ev = stereo_eval(np.array([rho]), args[3], host, stereo.target, stereo.K, stereo.T_r_l,
                             stereo.params.exposure_ratio)
            sw = sqrt_weights(ev, host, stereo.params)[0]
            r[:P] = sw * ev.r[0]
            J[:P, cols[1]] = sw * ev.J["rho"][0, :, 0]
            J[:P, cols[3]:cols[4]] = sw[:, None] * ev.J["ab"][0]
        if M:
            tg = [(args[off + 3 + 2 * m], np.asarray(args[off + 4 + 2 * m], float), targets[m])
                  for m in range(M)]
            ev = point_eval(T_i, rho, ab_i, host, tg, K_j, T_b_c)
            sw = sqrt_weights(ev, host, params)                  # (M, P)
            r[rows0:] = (sw * ev.r).reshape(-1)
            w = sw[..., None]
            J[rows0:, 0:6] = (w * ev.J["pose_i"]).reshape(-1, 6)
            J[rows0:, 6] = (sw * ev.dr_drho).reshape(-1)
            J[rows0:, 7:9] = (w * ev.J["ab_i"]).reshape(-1, 2)
            Jpj, Jab = w * ev.J["pose_j"], w * ev.J["ab_j"]
            for m in range(M):
                c, rr = cols[off + 3 + 2 * m], slice(rows0 + m * P, rows0 + (m + 1) * P)
                J[rr, c:c + 6] = Jpj[m]
                J[rr, c + 6:c + 8] = Jab[m]
        return r, J

    return fn


def point_factor(keys: Sequence[int], host: HostPatch, targets: Sequence[ImageSampler],
                 K_j: Pinhole, T_b_c: gtsam.Pose3, params: PhotometricParams = PhotometricParams(),
                 stereo: StereoTerm | None = None, health: FactorHealth | None = None
                 ) -> gtsam.CustomFactor:
    """All observations of one point in one factor; keys in ``point_kinds`` order
    (T_w_bi, rho, ab_i, [ab_right], T_w_bj1, ab_j1, ...). Unit noise model."""
    fn = point_residual_fn(host, targets, K_j, T_b_c, params, stereo)
    P = host.bearing.shape[1]
    m = P * (len(targets) + (stereo is not None))
    if m == 0:
        raise ValueError("point_factor needs a stereo term or at least one target")
    return custom_factor(gtsam.noiseModel.Unit.Create(m), keys,
                         point_kinds(len(targets), stereo is not None), fn, health)
