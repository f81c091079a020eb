"""Visual-inertial alignment of a dynamic-initialization window (step 2 of
:mod:`vio.backend.dynamic_init`): variable projection over ``x = [v0, g0, bg]`` with
closed-form inverse depths, a small robust Levenberg-Marquardt, and the window's
track and IMU bookkeeping. Frames: ``b0`` is the first keyframe's body frame; ``v0``,
``g0`` in b0 (m/s, m/s^2); ``bg`` gyro bias (rad/s); inverse depths in the anchor
camera (1/m); observations in normalized coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from vio.backend.config import InitConfig
from vio.io.types import CameraCalib
from vio.imu import integrate

NAN = float("nan")

if TYPE_CHECKING:
    from vio.backend.dynamic_init import InitWindow


@dataclass(frozen=True)
class WindowObs:
    """Non-anchor observations, N rows: landmark index ``lm`` (of ``ids``), anchor and
    observing keyframes ``a``, ``j``; anchor ray ``m_a`` (N,3); observation ``uv`` (N,2)
    and ``skew`` = ``[m_j]x`` (N,3,3); keyframe times ``t`` (K,) s from the first."""

    ids: tuple[int, ...]
    lm: np.ndarray
    a: np.ndarray
    j: np.ndarray
    m_a: np.ndarray
    uv: np.ndarray
    skew: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class ViSolution:
    """An alignment solution: ``v0``, ``g0`` (b0 frame), gyro bias ``bg``, inverse
    depths ``rho`` (per landmark), residuals ``r`` (N,2) normalized, and the (N,) mask
    of observations used; ``cov`` (6,6) the covariance of ``[v0, g0]``; ``cost`` the
    robust cost."""

    v0: np.ndarray
    g0: np.ndarray
    bg: np.ndarray
    rho: np.ndarray
    r: np.ndarray
    mask: np.ndarray
    cov: np.ndarray
    cost: float


def window_tracks(win: InitWindow, min_obs: int = 3, max_tracks: int = 80
            ) -> dict[int, list[tuple[int, np.ndarray]]]:
    """The ``max_tracks`` longest tracks seen in at least ``min_obs`` keyframes."""
    obs: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k, fr in enumerate(win.features):
        for lid, uv in zip(fr.ids, fr.uv):
            obs.setdefault(int(lid), []).append((k, np.asarray(uv, float)))
    best = sorted((l for l, o in obs.items() if len(o) >= min_obs), key=lambda l: -len(obs[l]))
    return {l: obs[l] for l in best[:max_tracks]}


def window_observations(win: InitWindow, tracks: dict) -> WindowObs:
    rows = [(li, o[0][0], j, o[0][1], uv) for li, o in enumerate(tracks.values()) for j, uv in o[1:]]
    lm, a, j = (np.array([r[k] for r in rows], np.int64) for k in range(3))
    m_a = np.array([[r[3][0], r[3][1], 1.0] for r in rows])
    uv = np.array([r[4] for r in rows], float)
    sk = np.zeros((len(rows), 3, 3))
    sk[:, 0, 1], sk[:, 1, 0], sk[:, 0, 2], sk[:, 2, 0] = -1.0, 1.0, uv[:, 1], -uv[:, 1]
    sk[:, 1, 2], sk[:, 2, 1] = -uv[:, 0], uv[:, 0]
    t = np.array([(s - win.t_ns[0]) * 1e-9 for s in win.t_ns])
    return WindowObs(tuple(tracks), lm, a, j, m_a, uv, sk, t)


def preintegrate_window(win: InitWindow, params) -> list:
    """Per-interval preintegrations at zero bias."""
    pims = []
    for seg in win.imu:
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
        integrate(pim, seg)
        pims.append(pim)
    return pims


def chain_increments(pims: list, bg: np.ndarray, gravity: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``R_k`` (K,3,3), ``dp_k``, ``dv_k`` (K,3) in b0 for gyro bias ``bg`` (zero accel
    bias and initial velocity, no gravity). ``gravity``: the params' n_gravity (3,)."""
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), np.asarray(bg, float))
    R, dp, dv = [np.eye(3)], [np.zeros(3)], [np.zeros(3)]
    for pim in pims:
        dt = pim.deltaTij()
        ns = pim.predict(gtsam.NavState(), bias)   # first-order bias correction
        dp.append(dp[-1] + dv[-1] * dt + R[-1] @ (ns.position() - 0.5 * dt * dt * gravity))
        dv.append(dv[-1] + R[-1] @ (ns.velocity() - dt * gravity))
        R.append(R[-1] @ ns.attitude().matrix())
    return np.array(R), np.array(dp), np.array(dv)


class AlignProblem:
    """The reduced alignment problem over ``x = [v0, g0, bg]`` (b0 frame, gyro bias).

    The gyro bias has a prior (mean ``bg0``, sigma ``bg_sigma``: ``DynamicInitConfig.
    gyro_bias_sigma`` about zero, or ``visual_gyro_bias_sigma`` about the bias measured
    from visual rotations by ``gyro_init``): in a short window a yaw-rate
    error and a sideways velocity error look alike (only depth differences separate
    them), and the observations it is estimated from must be outlier-free (a few swapped
    tracks pulled it by 0.06 rad/s and ``v0`` by 0.5 m/s in the simulated windows)."""

    def __init__(self, obs: WindowObs, pims: list, cam: CameraCalib, gravity: np.ndarray,
                 ic: InitConfig) -> None:
        self.obs, self.pims, self.gravity, self.cam = obs, pims, gravity, cam
        self.fx = cam.intrinsics[0]
        self.rho_lim = (1.0 / ic.dynamic.max_depth_m, 10.0)
        self.bg_sigma = ic.dynamic.gyro_bias_sigma
        self.mask = np.ones(len(obs.lm), bool)
        self.bg0 = np.zeros(3)   # gyro bias of the bias-fixed stage and prior mean (``gyro_init``)
        self._cache: tuple[bytes, tuple] | None = None
        _, _, dv = chain_increments(pims, np.zeros(3), gravity)
        self.g_imu = -dv[-1] / obs.t[-1]   # gravity if v_K = v_0: a starting point only

    def geometry(self, bg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For gyro bias ``bg``: the anchor ray ``R_cj^T R_ca m_a`` (N,3) and the anchor-to-
        camera-j translation in camera j as ``c + M [v0; g0]``: ``c`` (N,3), ``M`` (N,3,6)."""
        key = np.asarray(bg, float).tobytes()
        if self._cache is None or self._cache[0] != key:
            o, T_b_c = self.obs, self.cam.T_b_c
            R, dp, _ = chain_increments(self.pims, bg, self.gravity)
            Rc = R @ T_b_c.rotation().matrix()
            RcjT = np.transpose(Rc[o.j], (0, 2, 1))
            ray = np.einsum("nij,nj->ni", RcjT, np.einsum("nij,nj->ni", Rc[o.a], o.m_a))
            ta, tj = o.t[o.a][:, None, None], o.t[o.j][:, None, None]
            c = np.einsum("nij,nj->ni", RcjT,
                          dp[o.a] - dp[o.j] + (R[o.a] - R[o.j]) @ T_b_c.translation())
            M = np.concatenate([RcjT * (ta - tj), RcjT * (0.5 * (ta ** 2 - tj ** 2))], axis=2)
            self._cache = (key, (ray, c, M))
        return self._cache[1]

    def rho(self, ray: np.ndarray, tr: np.ndarray) -> np.ndarray:
        """Closed-form inverse depths minimising ``sum |[m_j]x (ray + rho tr)|^2`` over the
        masked observations, clipped to ``rho_lim``."""
        o, w = self.obs, self.mask.astype(float)
        kr, kt = (np.einsum("nij,nj->ni", o.skew, v) for v in (ray, tr))
        n = len(o.ids)
        num = np.bincount(o.lm, w * np.sum(kr * kt, 1), n)
        den = np.bincount(o.lm, w * np.sum(kt * kt, 1), n)
        return np.clip(-num / np.maximum(den, 1e-18), *self.rho_lim)

    def residuals(self, x: np.ndarray, full: bool = False):
        """Masked reprojection errors (2N,) and the gyro-bias prior (3,) for
        ``x = [v0, g0, bg]`` (9,) or ``[v0, g0]`` (6,, at gyro bias ``bg0``), in normalized image
        units (the prior: one pixel per sigma); ``full`` also returns ``(rho, r (N,2))``."""
        bg = x[6:9] if len(x) == 9 else self.bg0
        ray, c, M = self.geometry(bg)
        tr = c + M @ x[:6]
        rho = self.rho(ray, tr)
        P = ray + rho[self.obs.lm][:, None] * tr
        r = P[:, :2] / np.maximum(P[:, 2:3], 1e-2) - self.obs.uv
        out = np.r_[(r * self.mask[:, None]).ravel(), (bg - self.bg0) / (self.bg_sigma * self.fx)]
        return (out, rho, r) if full else out

    def alternate(self, depth: float, iters: int = 15) -> np.ndarray:
        """A starting ``[v0, g0]`` (gyro bias ``bg0``) by alternating least squares from equal
        depths ``depth`` m: for fixed inverse depths ``[m_j]x (ray + rho (c + M x)) = 0``
        is linear in ``x``, and for a fixed ``x`` each ``rho`` has its closed form."""
        ray, c, M = self.geometry(self.bg0)
        K, lm = self.obs.skew, self.obs.lm
        Kr, Kc, KM = (np.einsum("nij,nj...->ni...", K, v) for v in (ray, c, M))
        rho, x = np.full(len(self.obs.ids), 1.0 / depth), np.zeros(6)
        for _ in range(iters):
            r = rho[lm][:, None]
            x = np.linalg.lstsq((r[:, :, None] * KM).reshape(-1, 6), -(Kr + r * Kc).ravel(),
                                rcond=None)[0]
            rho = self.rho(ray, c + M @ x)
        return x


def excitation(pims: list, bg: np.ndarray, gravity: np.ndarray, t: np.ndarray) -> float:
    """RMS (m/s^2) over keyframe intervals of the mean specific force, rotated into b0
    with gyro bias ``bg``, about its window mean. Gravity is constant in b0, so this is
    the variation of the kinematic acceleration: without it (constant velocity or
    acceleration) the IMU fixes no scale and the alignment's ``v0`` is arbitrary."""
    _, _, dv = chain_increments(pims, bg, gravity)
    a = np.diff(dv, axis=0) / np.diff(t)[:, None]
    return float(np.sqrt(np.mean(np.sum((a - a.mean(0)) ** 2, axis=1))))


def rotation_only_px(prob: AlignProblem, vi: ViSolution) -> float:
    """Median error (px) of the inlier observations predicted by rotation alone (points
    at infinity): small when the window shows no translation parallax."""
    ray = prob.geometry(vi.bg)[0]
    err = np.linalg.norm(ray[:, :2] / ray[:, 2:3] - prob.obs.uv, axis=1)[vi.mask]
    return float(np.median(err) * prob.fx) if err.size else NAN


def _huber(r: np.ndarray, k: float) -> tuple[float, np.ndarray]:
    """Huber cost ``sum rho(r)`` and IRLS weights (per residual) for width ``k``."""
    a = np.abs(r)
    inside = a <= k
    cost = np.where(inside, 0.5 * r * r, k * (a - 0.5 * k)).sum()
    return float(cost), np.where(inside, 1.0, k / np.maximum(a, 1e-300))


def _robust_lm(fun, x0: np.ndarray, k: float, steps: np.ndarray, max_iter: int = 50
               ) -> tuple[np.ndarray, float, np.ndarray]:
    """Levenberg-Marquardt with Huber (width ``k``) IRLS weights and a forward-difference
    Jacobian (``steps`` per parameter). Small dense normal equations: scipy's
    ``least_squares`` spends most of its time in threaded SVDs of the tall Jacobian here.
    Returns ``x``, the robust cost and the information matrix ``J^T W J``."""
    x, r = np.asarray(x0, float).copy(), fun(x0)
    cost, w = _huber(r, k)
    lam, eye = 1e-3, np.eye(len(x))
    H = eye
    for _ in range(max_iter):
        J = np.stack([(fun(x + h * eye[i]) - r) / h for i, h in enumerate(steps)], axis=1)
        H, grad = J.T @ (J * w[:, None]), J.T @ (w * r)
        while lam < 1e8:
            dx = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -grad)
            r_new = fun(x + dx)
            c_new, w_new = _huber(r_new, k)
            if c_new < cost:
                break
            lam *= 10.0
        else:
            break
        done = cost - c_new < 1e-9 * cost
        x, r, cost, w, lam = x + dx, r_new, c_new, w_new, max(lam / 10.0, 1e-9)
        if done:
            break
    return x, cost, H


def vi_align(prob: AlignProblem, ic: InitConfig, outlier: float, sigma: float) -> ViSolution:
    """Robust alignment at the gyro bias ``prob.bg0`` (the visual-rotation estimate of
    ``gyro_init``, else zero) from several starts (zero velocity with the
    IMU's gravity guess, and :meth:`AlignProblem.alternate` from 1 m and 3 m; the lowest
    cost wins), then with the gyro bias free, each time keeping only the observations
    whose error is below ``outlier`` (normalized), until that inlier set is the
    solution's own (two to four rounds: after only two, the set of the previous solution
    was reported, and a good alignment of generated MH_04 tracks counted 74% inliers
    where its own residuals had 92%). ``sigma``: observation noise (normalized) for the
    covariance.

    ``|g0|`` stays free: forcing it to ``g`` here would push the accelerometer bias's
    component along gravity (0.05 m/s^2 moves a keyframe 6 cm in 1.5 s) into ``v0``;
    the batch LM, which estimates that bias, fixes the magnitude instead."""
    k = ic.dynamic.huber_px / prob.fx
    steps = np.r_[np.full(6, 1e-6), np.full(3, 1e-7)]
    best = None
    for x0 in [np.r_[np.zeros(3), prob.g_imu]] + [prob.alternate(d) for d in (1.0, 3.0)]:
        x, cost, _ = _robust_lm(prob.residuals, x0, k, steps[:6])
        if best is None or cost < best[1]:
            best = (x, cost)
    x = np.r_[best[0], prob.bg0]
    prev = None
    for rnd in range(4):   # until the inlier set is that of the solution (at most 4 rounds)
        prob.mask[:] = True
        _, _, r = prob.residuals(x, full=True)
        mask = np.linalg.norm(r, axis=1) < outlier
        prob.mask = mask
        if rnd > 1 and np.array_equal(mask, prev):
            break
        prev = mask.copy()
        x, cost, H = _robust_lm(prob.residuals, x, k, steps)
    _, rho, r = prob.residuals(x, full=True)
    cov = sigma ** 2 * np.linalg.pinv(H)
    return ViSolution(x[:3], x[3:6], x[6:9], rho, r, prob.mask.copy(), cov, cost)
