"""The camera-IMU time offset at initialization, from visual rotations against the gyro.

A dynamic initialization cuts the IMU at the frame times. With an unknown offset ``td``
(``t_imu = t_stamp + td``, the sync layer applying a wrong one) every cut is off by the
remainder ``delta``, and at hand-held rotation rates (2 rad/s) a 25-ms remainder puts 3
degrees of rotation error on each keyframe: generated MH_03 tracks at true td 25 ms, synced at 0,
start with 1.5 s of hand-held shaking, and every alignment of the first 7 s was refused
(47-73 % inliers, ``|g|`` off by 3-10 %) until a static start at 7.05 s.

The visual body rotation ``R_ij`` between keyframes i and j (``gyro_init.window_rotations``)
is the gyro's rotation between ``t_i + delta`` and ``t_j + delta``:

    r_ij(delta, bg) = Log(R_gyro(t_i + delta, t_j + delta; bg)^T R_ij)

``R_gyro`` integrates the bias-corrected, linearly interpolated gyro (midpoint rule, as
``vio.imu.integrate``). ``delta`` is searched on a grid over ``+-search_s`` with the gyro
bias solved at each grid point by Gauss-Newton on the pairs within ``tol_deg`` (from the
starting bias, and from a first solve at ``wide_tol_factor`` times that tolerance, the
lower cost kept: ``TdSearchConfig``); the cost
is the truncated quadratic ``sum min(|r|^2, tol^2)``, a parabola through the grid minimum
and its neighbours gives the sub-step value. The remainder is applied when it is
significant: the cost drop against ``delta = 0`` is at least ``min_gain`` times the
residuals' per-axis variance, and the cost's curvature puts its standard deviation below
``max_sigma_s``. A weaker candidate is only tried when the window is refused without it,
and kept if the alignment's own checks (inliers, reprojection error, ``|g|``, batch
agreement) pass at it. A smooth flight (rotation rate nearly constant over the pairs)
leaves ``delta`` unobservable and the search returns 0: the online td estimate then
starts, as before, from the sync layer's offset.

Measured (``bench_midflight``: 30-s mid-flight excerpts of generated tracks on real IMU,
sync layer at 0; ``benchmarks/README.md`` has the tables): at true td +25 / -20 ms, 27
runs, 26 decide within 1.5 s (15 without the search) and 23 stay under 0.2 % of the path
(20), e.g. V2_02@25 at -20 ms 0.649 -> 0.074 %, V1_03@25 at +25 ms 0.601 -> 0.056 %;
one gets worse (MH_04@40 +25 ms 0.135 -> 0.181 %). At the default 5 ms nothing changes
(20 excerpts identical), nor on real MH_05 mono from 14 start frames. The visual pair
rotations (essential matrices) put the remainder within ~2.5-10 ms of the truth (V1_02@30
+25 ms: 27.5 ms); the window's visual-inertial batch then pins it to ~1 ms
(``vio.backend.init_batch``, with :func:`refine_minimum`), and the online td estimate
refines it further.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

from factors.jit import njit, njit_inline
from vio.backend.config import TdSearchConfig
from vio.imu import integrate
from vio.io.types import ImuData


@dataclass(frozen=True)
class TdSearch:
    """Outcome of :func:`search_td`. ``td_s``: the remainder to apply (0 when not
    significant); ``best_s``: the cost minimum; ``sigma_s``: its standard deviation;
    ``gain``: cost drop against 0 in units of the residual variance; ``bg`` (3,) rad/s:
    the gyro bias at ``best_s``; ``n_pairs``: pairs used, ``n_inliers`` within tolerance."""

    td_s: float
    best_s: float
    sigma_s: float
    gain: float
    bg: np.ndarray
    n_pairs: int
    n_inliers: int

    def hints(self, min_gain: float) -> bool:
        """Whether the rotations point at a non-zero offset with a cost drop of at least
        ``min_gain`` (``TdSearchConfig.try_gain``, ``refused_try_gain``, ``walk_gain``)."""
        return self.best_s != 0.0 and self.gain >= min_gain


@njit_inline
def _exp_mul(A, phi, out):
    """``out = A @ Exp(phi)`` (SO(3) exponential by Rodrigues), without temporaries."""
    x, y, z = phi[0], phi[1], phi[2]
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        th = np.sqrt(th2)
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
    # E = I + a K + b K^2, K = [phi]x, K^2 = phi phi^T - th2 I
    e00, e11, e22 = 1.0 + b * (x * x - th2), 1.0 + b * (y * y - th2), 1.0 + b * (z * z - th2)
    e01, e10 = b * x * y - a * z, b * x * y + a * z
    e02, e20 = b * x * z + a * y, b * x * z - a * y
    e12, e21 = b * y * z - a * x, b * y * z + a * x
    for i in range(3):
        r0, r1, r2 = A[i, 0], A[i, 1], A[i, 2]
        out[i, 0] = r0 * e00 + r1 * e10 + r2 * e20
        out[i, 1] = r0 * e01 + r1 * e11 + r2 * e21
        out[i, 2] = r0 * e02 + r1 * e12 + r2 * e22


@njit_inline
def _log(R):
    """SO(3) logarithm (3,) of a rotation away from pi."""
    c = min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    th = np.arccos(c)
    f = 0.5 if th < 1e-8 else 0.5 * th / np.sin(th)
    return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) * f


@njit
def _rot_at(tq, t, w, R, bg, out):
    """``out``: the rotation from the first sample to time ``tq`` (s), inside ``t``."""
    k = min(max(np.searchsorted(t, tq) - 1, 0), t.shape[0] - 2)
    s = tq - t[k]
    f = s / (t[k + 1] - t[k])
    phi = np.empty(3)
    for i in range(3):
        phi[i] = (0.5 * (w[k, i] + w[k, i] + (w[k + 1, i] - w[k, i]) * f) - bg[i]) * s
    _exp_mul(R[k], phi, out)


@njit
def pair_residuals(t, w, bg, delta, ti, tj, R_vis):
    """(P, 3) ``Log(R_gyro(ti + delta, tj + delta; bg)^T R_vis)`` (module docstring);
    ``t`` (N,) s, ``w`` (N, 3) rad/s raw gyro, ``R_vis`` (P, 3, 3) body rotations."""
    n = t.shape[0]
    R = np.empty((n, 3, 3))
    R[0] = np.eye(3)
    phi = np.empty(3)
    for k in range(n - 1):
        for i in range(3):
            phi[i] = (0.5 * (w[k, i] + w[k + 1, i]) - bg[i]) * (t[k + 1] - t[k])
        _exp_mul(R[k], phi, R[k + 1])
    out = np.empty((ti.shape[0], 3))
    Ra, Rb = np.empty((3, 3)), np.empty((3, 3))
    for p in range(ti.shape[0]):
        _rot_at(ti[p] + delta, t, w, R, bg, Ra)
        _rot_at(tj[p] + delta, t, w, R, bg, Rb)
        out[p] = _log(Rb.T @ Ra @ R_vis[p])
    return out


class _Problem:
    """The pairs and the gyro of one search, times in seconds from the first sample."""

    def __init__(self, imu: ImuData, t_kf_ns, pairs: list, search_s: float) -> None:
        self.t = (imu.t_ns - imu.t_ns[0]) * 1e-9
        self.w = np.ascontiguousarray(imu.gyro, float)
        tk = (np.asarray(t_kf_ns, np.int64) - imu.t_ns[0]) * 1e-9
        keep = [p for p in pairs if tk[p[0]] - search_s >= self.t[0] and tk[p[1]] + search_s <= self.t[-1]]
        self.ti = np.array([tk[p[0]] for p in keep], float)
        self.tj = np.array([tk[p[1]] for p in keep], float)
        self.R = np.array([p[2] for p in keep], float).reshape(-1, 3, 3)

    def res(self, bg: np.ndarray, delta: float) -> np.ndarray:
        return pair_residuals(self.t, self.w, bg, delta, self.ti, self.tj, self.R)

    def solve_bg(self, bg: np.ndarray, delta: float, tol: float, iters: int = 3
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton for the bias on the pairs within ``tol``; the bias and the
        residual norms (P,) at it."""
        for _ in range(iters):
            r = self.res(bg, delta)
            inl = np.linalg.norm(r, axis=1) <= tol
            if inl.sum() < 2:
                break
            J = np.stack([(self.res(bg + h, delta)[inl] - r[inl]).ravel() / 1e-6
                          for h in np.eye(3) * 1e-6], axis=1)
            bg = bg - np.linalg.lstsq(J, r[inl].ravel(), rcond=None)[0]
        return bg, np.linalg.norm(self.res(bg, delta), axis=1)


def search_td(imu: ImuData, t_kf_ns, pairs: list, bg0: np.ndarray, cfg: TdSearchConfig) -> TdSearch:
    """The td remainder of a window (module docstring): ``imu`` covering the keyframes
    ``t_kf_ns`` (K,) ns, ``pairs`` ``(i, j, R_bi_bj)`` visual body rotations between
    keyframes, ``bg0`` (3,) rad/s the starting gyro bias."""
    bg0 = np.asarray(bg0, float)
    zero = TdSearch(0.0, 0.0, float("inf"), 0.0, bg0, 0, 0)
    if cfg.search_s <= 0 or len(imu) < 2:
        return zero
    prob = _Problem(imu, t_kf_ns, pairs, cfg.search_s)
    n = len(prob.ti)
    if n < cfg.min_pairs:
        return TdSearch(0.0, 0.0, float("inf"), 0.0, bg0, n, 0)
    tol = np.radians(cfg.tol_deg)
    m = int(round(cfg.search_s / cfg.step_s))
    grid = np.arange(-m, m + 1) * cfg.step_s

    def cost(delta: float) -> tuple[float, np.ndarray, np.ndarray]:
        # the bias from bg0 directly, and from a solve at a wider tolerance first (bg0 is
        # fitted at delta 0 and can leave no pair within tol far from it: generated
        # V2_03@80 at -30 ms, -45..-15 ms all 20 pairs out); the lower cost is kept
        best = None
        for start in (bg0, prob.solve_bg(bg0, delta, cfg.wide_tol_factor * tol)[0]):
            bg, r = prob.solve_bg(start, delta, tol)
            c = float(np.minimum(r, tol) @ np.minimum(r, tol))
            if best is None or c < best[0]:
                best = (c, bg, r)
        return best

    costs = np.array([cost(d)[0] for d in grid])
    i = int(np.argmin(costs))
    best = float(grid[i])
    a = 0.0
    if 0 < i < len(grid) - 1:
        c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
        a = (c0 + c2 - 2.0 * c1) / (2.0 * cfg.step_s ** 2)    # cost ~ c1 + a (delta - best)^2
        if a > 0:
            best += float(np.clip(0.25 * (c0 - c2) / (a * cfg.step_s ** 2), -0.5, 0.5)) * cfg.step_s
    c_best, bg, r = cost(best)
    inl = r <= tol
    dof = 3 * int(inl.sum()) - 4
    if dof <= 0:
        return TdSearch(0.0, best, float("inf"), 0.0, bg, n, int(inl.sum()))
    var = float(r[inl] @ r[inl]) / dof                      # per-axis residual variance
    gain = (costs[m] - c_best) / var                        # grid[m] is delta = 0
    if a <= 0:
        # a minimum on the grid's edge (or a flat cost): no sigma, nothing applied, but its
        # gain still says whether the rotations see an offset; the batch walk from it
        # decides (generated MH_05@40 at -30 ms: edge at -50 ms, window accepted at 0 with
        # the gyro bias taking up the offset, 0.363 % of the path)
        return TdSearch(0.0, best, float("inf"), float(gain), bg, n, int(inl.sum()))
    sigma = float(np.sqrt(var / a))
    ok = gain >= cfg.min_gain and sigma <= cfg.max_sigma_s
    return TdSearch(best if ok else 0.0, best, sigma, float(gain), bg, n, int(inl.sum()))


def refine_minimum(cost: Callable[[float], float], x0: float, step: float, max_shift: float,
                   bracket: bool = False) -> tuple[float, float, float]:
    """The minimum of a 1-D ``cost`` near ``x0``: the grid ``x0 + k step`` is walked from
    ``k = -1, 0, 1`` towards lower cost while the lowest point is at an edge and within
    ``max_shift`` of ``x0``, then a parabola through the lowest point and its neighbours
    gives the sub-step value. Returns ``(x, a, drop)``: the minimum, the parabola's
    curvature (``cost ~ c + a (x - x_min)^2``; 0 when the minimum is at an end of the
    walk, x then the lowest grid point) and the cost drop against ``x0`` (>= 0).
    ``cost`` may return inf (not evaluable): such points are never the minimum. With
    ``bracket``, a lowest point on the range's edge gets one more evaluation a step beyond
    it: ``max_shift`` then bounds the minimum, not its bracket (a minimum within half a step
    beyond the edge is found; one further out still returns the edge with no curvature)."""
    pts = {k: cost(x0 + k * step) for k in (-1, 0, 1)}
    kmax = int(round(max_shift / step))
    while True:
        k = min(pts, key=pts.get)
        lo, hi = min(pts), max(pts)
        if k == lo and k > -kmax and np.isfinite(pts[k]):
            pts[k - 1] = cost(x0 + (k - 1) * step)
        elif k == hi and k < kmax and np.isfinite(pts[k]):
            pts[k + 1] = cost(x0 + (k + 1) * step)
        else:
            break
    if bracket and abs(k) == kmax and kmax > 0 and np.isfinite(pts[k]):
        out = k + (1 if k > 0 else -1)
        pts[out] = cost(x0 + out * step)
        if pts[out] < pts[k]:           # still falling: not bracketed
            del pts[out]
    c1 = pts[k]
    drop = float(pts[0] - c1) if np.isfinite(pts[0]) and np.isfinite(c1) else 0.0
    if not np.isfinite(c1) or k - 1 not in pts or k + 1 not in pts:
        return x0 + k * step, 0.0, drop
    c0, c2 = pts[k - 1], pts[k + 1]
    a = (c0 + c2 - 2.0 * c1) / (2.0 * step ** 2)
    x = x0 + k * step
    if np.isfinite(a) and a > 0:
        x += float(np.clip(0.25 * (c0 - c2) / (a * step ** 2), -0.5, 0.5)) * step
    else:
        a = 0.0
    return x, float(a), drop


def shift_state(T_w_b, v_w: np.ndarray, bias, imu: ImuData, t_from_ns: int, t_to_ns: int, params):
    """The body state ``(T_w_b, v_w)`` at ``t_from_ns`` carried to ``t_to_ns`` (either
    direction) through the IMU between them, at ``bias`` (``gtsam.imuBias.ConstantBias``);
    ``params``: the preintegration parameters (gravity). Returns ``(Pose3, v (3,))``."""
    a, b = sorted((int(t_from_ns), int(t_to_ns)))
    pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
    integrate(pim, imu.segment(a, b))
    if t_to_ns >= t_from_ns:
        nav = pim.predict(gtsam.NavState(T_w_b, np.asarray(v_w, float)), bias)
        return nav.pose(), nav.velocity()
    # backward: from R1 = R0 dR, v1 = v0 + g dt + R0 dv, p1 = p0 + v0 dt + g dt^2 / 2 + R0 dp
    dt, g = (b - a) * 1e-9, np.asarray(params.n_gravity, float)
    unit = pim.predict(gtsam.NavState(), bias)       # R0 = I, p0 = v0 = 0
    dR, dv = unit.attitude(), unit.velocity() - g * dt
    dp = unit.position() - 0.5 * g * dt * dt
    R0 = T_w_b.rotation().compose(dR.inverse())
    v0 = np.asarray(v_w, float) - g * dt - R0.rotate(dv)
    p0 = T_w_b.translation() - v0 * dt - 0.5 * g * dt * dt - R0.rotate(dp)
    return gtsam.Pose3(R0, p0), v0
