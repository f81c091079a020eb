"""One photometric factor per host keyframe, its points' inverse depths eliminated inside.

Keys: ``[T_w_bh (pose3), ab_h (2), then T_w_bm (pose3), ab_m (2) per target m]`` and,
when the frames' exposure times are modelled (``HostTiming``), td (1) last; the
N points of the host (``HostPoints``) carry their inverse depths rho (1/m, host cam0)
inside the factor, not as graph variables. At each linearization the kernel
(``factors.photometric_kernel.host_system``) refines every rho with the poses held
(a few Gauss-Newton steps over the static stereo term at the host, for the points
flagged in ``HostPoints.stereo``, and the temporal terms), drops outlier residuals
(DSO's residual states) and Schur-eliminates the rho:
H = sum (H_xx - H_xr H_rx / H_rr), g likewise. The factor returns a square-root form of
that quadratic: with H + eps I = L L^T (Cholesky; eps = 1e-9 max diag H),

    J = L^T,   r = L^-1 g,   plus one row r_c = sqrt(2 E* - |r|^2), J_c = 0,

so J^T J = H (+ eps I), J^T r = g and 0.5 |r|^2 = E*, the reduced (rho-minimized,
Huber) energy at the linearization point. Residual dimension 8 (M + 1) + 1; Unit noise model. The
factor has no gauge of its own (the reduced H is singular along the global pose,
affine and, without the stereo term, scale directions): eps regularizes them.

With a rolling shutter (``HostShutter``) each image row is exposed at its own time and
the host points and targets move along their cameras' twists over the readout
(``factors.photometric_shutter.Shutter``); the keys and the square-root form stay the same.

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
from factors.photometric_shutter import rolled_bearings
from factors.jit import njit as _njit
from factors.photometric_kernel import host_system
from factors.photometric_warp import DARK, SATURATED, pixel_row_s, rows_or_pinhole

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
    ``stereo`` (N,) the points that carry the static stereo term (default all; a point whose
    depth came from a temporal search has none: its right-image match failed); ``rms``
    (N, M_max) each pair's raw residual RMS at its last linearization (the kernel's
    ``rms``; inf before the first).
    Clipped host pixels (>= ``SATURATED`` or <= ``DARK``) are marked invalid at creation."""

    patch: HostPatch
    wg: np.ndarray
    rho: np.ndarray
    alive: np.ndarray
    tmask: np.ndarray
    stereo: np.ndarray
    rms: np.ndarray

    @staticmethod
    def create(patch: HostPatch, rho: np.ndarray, grad_c: float, max_targets: int,
               stereo: np.ndarray | None = None) -> "HostPoints":
        c2 = grad_c ** 2
        n = len(patch)
        patch = HostPatch(patch.uv, patch.bearing, patch.intensity, patch.grad_sq,
                          patch.valid & (patch.intensity < SATURATED) & (patch.intensity > DARK))
        sm = np.ones(n, bool) if stereo is None else np.array(stereo, bool).reshape(-1)
        if sm.shape != (n,):
            raise ValueError(f"HostPoints.create: stereo mask of {sm.size} for {n} points")
        return HostPoints(patch, c2 / (c2 + patch.grad_sq), np.asarray(rho, float).copy(),
                          np.ones(n, bool), np.ones((n, max_targets), bool), sm,
                          np.full((n, max_targets), np.inf))


@dataclass(frozen=True, eq=False)
class HostShutter:
    """The rolling shutter of a host factor's images (``factors.photometric_shutter.Shutter`` per
    pair): ``line_time_s`` s per row and the cam0 twists [omega (rad/s), v (m/s)] in the
    camera frame, ``twists`` (M + 1, 6), host first, then the targets in key order; the
    right camera's is the host's moved by T_c1_c0. Constants of the factor, as
    ``HostTiming``'s. ``rows``, ``right_rows``: the left and right cameras'
    ``factors.photometric_warp.row_model`` where a lens bends the sensor rows (None: the
    undistorted pinhole rows)."""

    line_time_s: float
    twists: np.ndarray
    rows: np.ndarray | None = None
    right_rows: np.ndarray | None = None


def shutter_args(shutter: HostShutter | None, bearing: np.ndarray, uv: np.ndarray, M: int,
                 T_r_l: gtsam.Pose3, K: Pinhole, K_r: Pinhole) -> tuple:
    """The kernel's rolling-shutter arguments (bearing', sv, TW, TV, rw, rv, sh): the host
    bearings moved to row 0 without their rho part, and that part ``sv`` (N, 3)
    (``factors.photometric.host_points``); the targets' and the right camera's twists; the
    shutter vector (19,) [line time, the left camera's row model, the right's] (pinhole
    rows of ``K``, ``K_r`` without lens models); zeros without a shutter."""
    z3 = np.zeros(3)
    if shutter is None or shutter.line_time_s == 0.0:
        return (bearing, np.zeros((len(uv), 3)), np.zeros((max(M, 1), 3)), np.zeros((max(M, 1), 3)), z3, z3,
                np.zeros(19))
    tw = np.asarray(shutter.twists, float)
    bw, sv = rolled_bearings(bearing, pixel_row_s(shutter.line_time_s, uv, shutter.rows), tw[0])
    xi_r = T_r_l.AdjointMap() @ tw[0]
    T = tw[1:] if M else np.zeros((1, 6))
    sh = np.concatenate([[float(shutter.line_time_s)], rows_or_pinhole(shutter.rows, K),
                         rows_or_pinhole(shutter.right_rows, K_r)])
    return (np.ascontiguousarray(bw), sv, np.ascontiguousarray(T[:, :3]),
            np.ascontiguousarray(T[:, 3:]), xi_r[:3].copy(), xi_r[3:].copy(), sh)


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


def host_kinds(n_targets: int, timed: bool = False) -> list:
    """Key kinds of ``host_factor`` (``timed``: td's 1-vector last)."""
    return ["pose3", 2] + ["pose3", 2] * n_targets + ([1] if timed else [])


def target_list(targets: Sequence[np.ndarray], stereo: StereoHost | None):
    """The kernel's typed list of target stacks (the right stack stands in for an empty
    one). Building it costs ~0.5 ms (Numba's typed ``List``): a factor builds it once."""
    imgs = List()
    for img in (targets if len(targets) else [stereo.stack if stereo is not None else np.zeros((4, 4, 3))]):
        imgs.append(img)
    return imgs


def host_linearize(args: list, pts: HostPoints, targets: Sequence[np.ndarray], K: Pinhole,
                   T_b_c: gtsam.Pose3, params: HostParams, stereo: StereoHost | None,
                   update: bool = True, imgs=None, shutter: HostShutter | tuple | None = None):
    """Kernel call at ``args`` = [T_w_bh, ab_h, T_w_b1, ab_1, ...]: (H, g, E, E*, used);
    ``imgs``: ``target_list(targets, stereo)`` if already built; ``shutter``: the images'
    rolling shutter, or its ``shutter_args`` if already built."""
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
    rs = shutter if isinstance(shutter, tuple) else shutter_args(shutter, pts.patch.bearing, pts.patch.uv, M, T_rl,
                                                                 K, stereo.K if stereo is not None else K)
    return host_system(rs[0], pts.patch.intensity, pts.wg, pts.patch.valid, rho, alive,
                       tm, imgs, _kvec(K), R_ji, t_ji, R_jb, T_b_c.rotation().matrix(),
                       T_b_c.translation(), ab_h, ab_t, w0, st, K1,
                       # C-order, writable: the layout of R_ji[m], t_ji[m], so that the stereo and
                       # temporal terms share one compiled _rho_terms (first-run compile)
                       np.ascontiguousarray(T_rl.rotation().matrix()), np.array(T_rl.translation()),
                       ab_r, w0 * params.stereo_weight,
                       pts.stereo if stereo is not None else np.zeros(len(rho), np.bool_), hk,
                       params.outlier_rms, params.refine_iters, params.rho_min, params.rho_max, update,
                       pts.rms,   # written only with update
                       *rs[1:])


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


@dataclass(frozen=True, eq=False)
class HostTiming:
    """When the frames of a host factor were exposed (seed 004's time offset, applied to
    the photometric term): keyframe f's image was taken ``td - td_obs[f]`` after its
    state's time, where its body was at ``T_w_bf Exp((td - td_obs[f]) xi_f)`` (exact for a
    constant body twist). ``twists`` (M + 1, 6): xi_f = [omega_b (rad/s), v_b (m/s)] in
    GTSAM's tangent order, host first, then the targets in key order; ``td_obs`` (M + 1,)
    s: the part of td each keyframe's time already holds (the sync layer's feedback).
    Both are constants of the factor, as the KLT factors' predicted image velocities."""

    twists: np.ndarray
    td_obs: np.ndarray


def timed_args(args: list, timing: HostTiming) -> tuple[list, np.ndarray]:
    """``args`` = [T_w_bh, ab_h, T_w_b1, ab_1, ..., td (1,)] -> the same list with the poses
    at their exposure times (td dropped), and the map ``A`` (8 (M + 1), 8 (M + 1) + 1) from
    the keys' tangents [..., delta td] to those of the exposure poses:
    T Exp(d) Exp(s xi) = T Exp(s xi) Exp(Ad(Exp(-s xi)) d), and d/ds T Exp(s xi) = xi in
    the right tangent (J_r(s xi) xi = xi), so H' = A^T H A and g' = A^T g."""
    td = float(np.asarray(args[-1], float)[0])
    nf = len(timing.td_obs)
    n = 8 * nf
    out, A = list(args[:-1]), np.zeros((n, n + 1))
    for f in range(nf):
        xi = timing.twists[f]
        E = gtsam.Pose3.Expmap((td - timing.td_obs[f]) * xi)
        out[2 * f] = args[2 * f].compose(E)
        o = 8 * f
        A[o:o + 6, o:o + 6] = E.inverse().AdjointMap()
        A[o + 6, o + 6] = A[o + 7, o + 7] = 1.0
        A[o:o + 6, n] = xi
    return out, A


def host_residual_fn(pts: HostPoints, targets: Sequence[np.ndarray], K: Pinhole, T_b_c: gtsam.Pose3,
                     params: HostParams, stereo: StereoHost | None = None,
                     timing: HostTiming | None = None, shutter: HostShutter | None = None):
    """The residual function over ``host_kinds(len(targets), timing is not None)`` keys
    (module docstring; with ``timing``, td's key last and the poses moved to the exposure
    times, ``timed_args``; with ``shutter``, each image row at its own time)."""
    targets = list(targets)
    imgs = target_list(targets, stereo)
    rs = shutter_args(shutter, pts.patch.bearing, pts.patch.uv, len(targets),
                      stereo.T_r_l if stereo is not None else gtsam.Pose3(), K,
                      stereo.K if stereo is not None else K)

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        if timing is None:
            H, g, _, red, _ = host_linearize(args, pts, targets, K, T_b_c, params, stereo, imgs=imgs,
                                             shutter=rs)
            return square_root(H, g, red, damp=params.damping)
        exposed, A = timed_args(args, timing)
        H, g, _, red, _ = host_linearize(exposed, pts, targets, K, T_b_c, params, stereo, imgs=imgs,
                                         shutter=rs)
        # Marquardt damping in the exposure poses' coordinates, as the untimed factor's. Damped
        # in the keys' coordinates instead, td moved together with the states along their
        # twists (which leaves the exposure poses, and so the photometric cost, unchanged)
        # was charged at every factor, a prior at its linearization point: on a render with
        # td 8 ms the estimate stayed at -0.5 ms from either start (marginal sigma 0.2 ms)
        H = H + params.damping * np.diag(np.diag(H))
        return square_root(A.T @ H @ A, A.T @ g, red)

    return fn


def host_factor(keys: Sequence[int], pts: HostPoints, targets: Sequence[np.ndarray], K: Pinhole,
                T_b_c: gtsam.Pose3, params: HostParams, stereo: StereoHost | None = None,
                health: FactorHealth | None = None, timing: HostTiming | None = None,
                shutter: HostShutter | None = None) -> gtsam.CustomFactor:
    """The per-host factor; ``targets`` the (H, W, 3) image stacks of the target keyframes
    in key order, at most ``pts.tmask.shape[1]`` of them; with ``timing`` the last key is
    td's (``HostTiming``); ``shutter`` the images' rolling shutter (``HostShutter``)."""
    M = len(targets)
    timed = timing is not None
    if M < 1 or M > pts.tmask.shape[1]:
        raise ValueError(f"host_factor: {M} targets, need 1..{pts.tmask.shape[1]}")
    if len(keys) != 2 * (M + 1) + timed:
        raise ValueError(f"host_factor: {len(keys)} keys for {M} targets")
    if timed and (np.shape(timing.twists) != (M + 1, 6) or np.shape(timing.td_obs) != (M + 1,)):
        raise ValueError(f"host_factor: timing for {np.shape(timing.twists)} frames, need {M + 1}")
    if shutter is not None and np.shape(shutter.twists) != (M + 1, 6):
        raise ValueError(f"host_factor: shutter twists for {np.shape(shutter.twists)} frames, need {M + 1}")
    n = 8 * (M + 1) + timed
    return custom_factor(gtsam.noiseModel.Unit.Create(n + 1), keys, host_kinds(M, timed),
                         host_residual_fn(pts, targets, K, T_b_c, params, stereo, timing, shutter), health,
                         cache=True, state=lambda: (pts.rho.tobytes(), pts.alive.tobytes(),
                                                    pts.tmask.tobytes()))
