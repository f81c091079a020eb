"""One photometric factor per host keyframe, its points' inverse depths eliminated inside.

Keys: ``[T_w_bh (pose3), ab_h (2), then T_w_bm (pose3), ab_m (2) per target m]``; the
N points of the host (``HostPoints``) carry their inverse depths rho (1/m, host cam0)
inside the factor, not as graph variables. At each linearization the kernel
(``factors.photometric_kernel.host_system``) refines every rho with the poses held
(a few Gauss-Newton steps over the static stereo term at the host and the temporal
terms), drops outlier residuals (DSO's residual states) and Schur-eliminates the rho:
H = sum (H_xx - H_xr H_rx / H_rr), g likewise. The factor returns a square-root form of
that quadratic: with H + eps I = L L^T (Cholesky; eps = 1e-9 max diag H),

    J = L^T,   r = L^-1 g,   plus one row r_c = sqrt(2 E* - |r|^2), J_c = 0,

so J^T J = H (+ eps I), J^T r = g and 0.5 |r|^2 = E*, the reduced (rho-minimized,
Huber) energy at the linearization point. Residual dimension 8 (M + 1) + 1; Unit noise model. The
factor has no gauge of its own (the reduced H is singular along the global pose,
affine and, without the stereo term, scale directions): eps regularizes them.

Weights as ``factors.photometric`` with V = 0 (rho is estimated): temporal
w = c^2 / (c^2 + |grad I_host|^2) / (2 sigma_I^2), stereo the same times lambda,
Huber on sqrt(w) r. The right image's affine ``ab_right`` is a constant of the host.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.photometric import HostPatch, PhotometricParams, Pinhole
from factors.jit import njit as _njit
from factors.photometric_kernel import DARK, SATURATED, host_system

try:
    from numba.typed import List
except ImportError:  # pragma: no cover - the kernel then runs as plain Python on a list
    List = list


@dataclass(frozen=True)
class HostParams:
    """Weighting and outlier handling of a host factor: ``photo`` the temporal
    weights (sigma_I, grad_c, huber_k on the whitened residual, exposure ignored);
    ``stereo_weight`` lambda of the static stereo term; ``outlier_rms`` raw residual RMS
    (intensity units) beyond which a (point, target) pair is switched off;
    ``refine_iters`` Gauss-Newton steps on each rho per linearization; ``rho_min``,
    ``rho_max`` bounds (1/m) outside which a point is dropped; ``damping`` mu: the factor
    returns the square root of H + mu diag(H) (a Marquardt-damped step, unbiased at
    convergence because the gradient is kept)."""

    photo: PhotometricParams = field(default_factory=PhotometricParams)
    stereo_weight: float = 1.0
    outlier_rms: float = 15.0
    refine_iters: int = 3
    rho_min: float = 1.0 / 30.0
    rho_max: float = 5.0
    damping: float = 0.0


@dataclass(eq=False)
class HostPoints:
    """Mutable state of one host's points: constants of the host patches, ``rho`` (N,)
    inverse depths (updated at each linearization), ``alive`` (N,) points in use and
    ``tmask`` (N, M_max) (point, target) pairs in use, target slot m = m-th target.
    Clipped host pixels (>= ``SATURATED`` or <= ``DARK``) are marked invalid at creation."""

    patch: HostPatch
    wg: np.ndarray
    rho: np.ndarray
    alive: np.ndarray
    tmask: np.ndarray

    @staticmethod
    def create(patch: HostPatch, rho: np.ndarray, grad_c: float, max_targets: int) -> "HostPoints":
        c2 = grad_c ** 2
        n = len(patch)
        patch = HostPatch(patch.uv, patch.bearing, patch.intensity, patch.grad_sq,
                          patch.valid & (patch.intensity < SATURATED) & (patch.intensity > DARK))
        return HostPoints(patch, c2 / (c2 + patch.grad_sq), np.asarray(rho, float).copy(),
                          np.ones(n, bool), np.ones((n, max_targets), bool))


@dataclass(frozen=True, eq=False)
class StereoHost:
    """The host's right image (``(H, W, 3)`` stack), intrinsics, T_c1_c0 and the
    right image's affine [a, b] relative to the left."""

    stack: np.ndarray
    K: Pinhole
    T_r_l: gtsam.Pose3
    ab: np.ndarray


def _kvec(K: Pinhole) -> np.ndarray:
    return np.array([K.fx, K.fy, K.cx, K.cy])


def host_kinds(n_targets: int) -> list:
    """Key kinds of ``host_factor``."""
    return ["pose3", 2] + ["pose3", 2] * n_targets


def target_list(targets: Sequence[np.ndarray], stereo: StereoHost | None):
    """The kernel's typed list of target stacks (the right stack stands in for an empty
    one). Building it costs ~0.5 ms (Numba's typed ``List``): a factor builds it once."""
    imgs = List()
    for img in (targets if len(targets) else [stereo.stack if stereo is not None else np.zeros((4, 4, 3))]):
        imgs.append(img)
    return imgs


def host_linearize(args: list, pts: HostPoints, targets: Sequence[np.ndarray], K: Pinhole,
                   T_b_c: gtsam.Pose3, params: HostParams, stereo: StereoHost | None,
                   update: bool = True, imgs=None):
    """Kernel call at ``args`` = [T_w_bh, ab_h, T_w_b1, ab_1, ...]: (H, g, E, E*, used);
    ``imgs``: ``target_list(targets, stereo)`` if already built."""
    M = len(targets)
    T_h, ab_h = args[0], np.asarray(args[1], float)
    T_c_b = T_b_c.inverse()
    R_ji, t_ji, R_jb = np.empty((M, 3, 3)), np.empty((M, 3)), np.empty((M, 3, 3))
    ab_t = np.empty((M, 2))
    for m in range(M):
        T_bj_bi = args[2 + 2 * m].between(T_h)
        T_ji = T_c_b.compose(T_bj_bi).compose(T_b_c)
        R_ji[m], t_ji[m] = T_ji.rotation().matrix(), T_ji.translation()
        R_jb[m] = T_bj_bi.rotation().matrix()
        ab_t[m] = np.asarray(args[3 + 2 * m], float)
    ph = params.photo
    w0 = 1.0 / (2.0 * ph.sigma_I ** 2)
    hk = -1.0 if ph.huber_k is None else float(ph.huber_k)
    if stereo is not None:
        st, K1, T_rl, ab_r = stereo.stack, _kvec(stereo.K), stereo.T_r_l, np.asarray(stereo.ab, float)
    else:
        st, K1, T_rl, ab_r = targets[0] if M else np.zeros((4, 4, 3)), _kvec(K), gtsam.Pose3(), np.zeros(2)
    if imgs is None:
        imgs = target_list(targets, stereo)
    rho, alive = (pts.rho, pts.alive) if update else (pts.rho.copy(), pts.alive.copy())
    # the whole (N, M_max) mask, C-contiguous, whatever M (the kernel reads slots < M):
    # a [:, :M] view would be a second Numba signature, ~8 s more to compile on a fresh
    # install (strided for M < M_max, contiguous for M = M_max)
    tm = pts.tmask if update else pts.tmask.copy()
    return host_system(pts.patch.bearing, pts.patch.intensity, pts.wg, pts.patch.valid, rho, alive,
                       tm, imgs, _kvec(K), R_ji, t_ji, R_jb, T_b_c.rotation().matrix(),
                       T_b_c.translation(), ab_h, ab_t, w0, st, K1,
                       # C-order, writable: the layout of R_ji[m], t_ji[m], so that the stereo and
                       # temporal terms share one compiled _rho_terms (first-run compile)
                       np.ascontiguousarray(T_rl.rotation().matrix()), np.array(T_rl.translation()),
                       ab_r, w0 * params.stereo_weight, stereo is not None, hk,
                       params.outlier_rms, params.refine_iters, params.rho_min, params.rho_max, update)


@_njit
def square_root_kernel(H, g, E, rel_eps, damp):
    """(r (n + 1,), J (n + 1, n)) with J^T J = H + damp diag(H) + eps I, J^T r = g,
    0.5 |r|^2 = max(E, .): Cholesky of that = L L^T (eps = rel_eps * max diag H, for the
    gauge directions; damp a Marquardt damping of the factor's own step),
    J = L^T, r = L^-1 g, and a last row sqrt(2 E - |L^-1 g|^2) with a zero Jacobian."""
    n = H.shape[0]
    dmax = 0.0
    for i in range(n):
        dmax = max(dmax, H[i, i])
    eps = rel_eps * max(dmax, 1e-300)
    L = np.zeros((n, n))
    for j in range(n):
        s = H[j, j] * (1.0 + damp) + eps
        for k in range(j):
            s -= L[j, k] * L[j, k]
        d = math.sqrt(s) if s > eps else math.sqrt(eps)
        L[j, j] = d
        for i in range(j + 1, n):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    r = np.zeros(n + 1)
    for i in range(n):
        s = g[i]
        for k in range(i):
            s -= L[i, k] * r[k]
        r[i] = s / L[i, i]
    rr = 0.0
    for i in range(n):
        rr += r[i] * r[i]
    r[n] = math.sqrt(max(2.0 * E - rr, 0.0))
    J = np.zeros((n + 1, n))
    for i in range(n):
        for j in range(i, n):
            J[i, j] = L[j, i]
    return r, J


def square_root(H: np.ndarray, g: np.ndarray, E: float, rel_eps: float = 1e-9, damp: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """(r (n + 1,), J (n + 1, n)) with J^T J = H + eps I, J^T r = g and 0.5 |r|^2 = E (when
    E >= 0.5 g^T H^-1 g): a Cholesky square root (``square_root_kernel``; eps = rel_eps x
    max diag(H) regularizes the gauge directions; LAPACK's eigh costs ~50x more here)."""
    return square_root_kernel(np.ascontiguousarray(H, float), np.ascontiguousarray(g, float),
                              float(E), float(rel_eps), float(damp))


def host_residual_fn(pts: HostPoints, targets: Sequence[np.ndarray], K: Pinhole, T_b_c: gtsam.Pose3,
                     params: HostParams, stereo: StereoHost | None = None):
    """The residual function over ``host_kinds(len(targets))`` keys (module docstring)."""
    targets = list(targets)
    imgs = target_list(targets, stereo)

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        H, g, _, red, _ = host_linearize(args, pts, targets, K, T_b_c, params, stereo, imgs=imgs)
        return square_root(H, g, red, damp=params.damping)

    return fn


def host_factor(keys: Sequence[int], pts: HostPoints, targets: Sequence[np.ndarray], K: Pinhole,
                T_b_c: gtsam.Pose3, params: HostParams, stereo: StereoHost | None = None,
                health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """The per-host factor; ``targets`` the (H, W, 3) image stacks of the target keyframes
    in key order, at most ``pts.tmask.shape[1]`` of them."""
    M = len(targets)
    if M < 1 or M > pts.tmask.shape[1]:
        raise ValueError(f"host_factor: {M} targets, need 1..{pts.tmask.shape[1]}")
    if len(keys) != 2 * (M + 1):
        raise ValueError(f"host_factor: {len(keys)} keys for {M} targets")
    n = 8 * (M + 1)
    return custom_factor(gtsam.noiseModel.Unit.Create(n + 1), keys, host_kinds(M),
                         host_residual_fn(pts, targets, K, T_b_c, params, stereo), health,
                         cache=True, state=lambda: (pts.rho.tobytes(), pts.alive.tobytes(),
                                                    pts.tmask.tobytes()))
