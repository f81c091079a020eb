"""A bundle of landmark tracks in one factor, their inverse depths eliminated inside.

The point-wise problem is that of ``factors.track_kernel`` (one landmark: inverse depth
``lambda`` in its anchor camera, observations through cam0 or cam1 of the "bodies" that
made them, robust reweighting, anchor-noise whitening ``W = I + U diag(d) U^T``). Here N
landmarks share one list of B bodies (``T_w_b``, 4x4) and the calibration: keys
``[T_b_c, body 0 .. body B-1, td]`` (td only with ``use_td``), reduced columns
``T_b_c`` 0:6, body b at ``6 + 6 b``, td last (D = 6 + 6 B + use_td).

At each evaluation every landmark's lambda is refined with the poses held (``iters``
Gauss-Newton steps on its whitened, reweighted residuals, kept inside
``[lam_min, lam_max]`` and within a factor 2 per step; the result stays in
``Bundle.lam`` for the next evaluation) and then eliminated (Schur complement)::

    H = sum_i (J_x^T J_x - J_x^T j j^T J_x / j^T j),  g = sum_i (J_x^T r - J_x^T j j^T r / j^T j),
    E = sum_i 0.5 (r^T r - (j^T r)^2 / j^T j)

with ``j`` the landmark's lambda column, ``J_x`` the rest, all divided by the observation
sigma (the factor uses a unit noise model). The factor returns the square-root form of
``factors.photometric_host.square_root_kernel`` (J^T J = H + eps, J^T r = g, 0.5 |r|^2 = E).
``H``, ``g`` are those of the full problem (lambda as a variable) with lambda eliminated
at its refined value (tests/test_landmark_schur.py and the shared suite's
``REDUCED_CASES``, tests/cases_landmark_schur.py). :func:`square_root` equilibrates the
columns (``diag(H)^-1/2``) before the Cholesky; :func:`refine` runs the depth steps alone
(the backend refines at the estimate after each update and linearizes with ``iters`` 0).
A landmark may carry a depth prior (``p_lam``, ``p_info``), added to its lambda row.

The kernels are in :mod:`factors.landmark_schur_kernel`. The per-landmark Schur
accumulation uses the row structure: row pair o of a landmark is
non-zero only in lambda, ``T_b_c``, the anchor body, the body of its observation and td,
so ``J^T J`` is summed over those columns; the whitening's rank-2 term and the
elimination's rank-1 term are added densely over the landmark's columns.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors.adapter import FactorHealth, custom_factor
from factors.landmark_schur_kernel import _set_whitening, bundle_system
from factors.photometric_host import square_root_kernel
from factors.robust import KERNELS, RobustKernel


@dataclass(eq=False)
class Bundle:
    """N landmarks over B bodies (module docstring), flattened. Per landmark i:
    observations ``start[i]:start[i+1]``, local bodies ``lbodies[lb_start[i]:lb_start[i+1]]``
    (group body indices, local 0 = its anchor), anchor observation ``a_uv``, ``a_vel``
    (2,) and ``a_off`` (s), whitening ``U[2 start[i]:2 start[i+1]]`` (2 n_i, 2) and
    ``d[i]`` (2,) (zero columns: none), inverse depth ``lam[i]`` (1/m, updated in place)
    and ``active[i]`` (False: left out). Per observation o: local body ``target[o]``,
    cam1 flag ``right[o]``, ``uv``, ``vel`` (2,), time offset ``off`` (s), tangent
    ``basis`` (2, 3). ``C``, ``ad_inv``: the stereo rig (``factors.stereo``)."""

    n_bodies: int
    start: np.ndarray
    lb_start: np.ndarray
    lbodies: np.ndarray
    a_uv: np.ndarray
    a_vel: np.ndarray
    a_off: np.ndarray
    target: np.ndarray
    right: np.ndarray
    uv: np.ndarray
    vel: np.ndarray
    off: np.ndarray
    basis: np.ndarray
    C: np.ndarray
    ad_inv: np.ndarray
    lam: np.ndarray
    active: np.ndarray
    U: np.ndarray
    d: np.ndarray
    sphere: bool
    sigma: float
    kind: int
    kk: float
    use_td: bool
    lam_min: float
    lam_max: float
    iters: int = 2
    p_lam: np.ndarray | None = None
    p_info: np.ndarray | None = None
    hll: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.lam)
        self.p_lam = np.zeros(n) if self.p_lam is None else self.p_lam
        self.p_info = np.zeros(n) if self.p_info is None else self.p_info
        self.hll = np.zeros(n) if self.hll is None else self.hll

    @property
    def dim(self) -> int:
        return 6 + 6 * self.n_bodies + int(self.use_td)


def pack(n_bodies: int, landmarks: list[dict], C: np.ndarray, ad_inv: np.ndarray, model: str,
         sigma: float, robust: RobustKernel | None, use_td: bool, lam_bounds: tuple[float, float],
         iters: int = 2) -> Bundle:
    """A :class:`Bundle` from per-landmark dicts with ``bodies`` (group body indices, anchor
    first), ``target`` (n,) local body indices (0 = anchor), ``right`` (n,), ``uv``,
    ``vel`` (n, 2), ``off`` (n,), ``basis`` (n, 2, 3), ``a_uv``, ``a_vel`` (2,), ``a_off``,
    ``lam``, optionally a depth prior ``p_lam``, ``p_info`` (whitened information).
    Whitening none (see :func:`set_whitening`)."""
    if not landmarks:
        raise ValueError("a landmark bundle needs at least one landmark")
    n_obs = np.array([len(lm["uv"]) for lm in landmarks])
    if np.any(n_obs < 1):
        raise ValueError("every landmark of a bundle needs an observation outside its anchor")
    nb = np.array([len(lm["bodies"]) for lm in landmarks])
    start, lb_start = np.r_[0, np.cumsum(n_obs)], np.r_[0, np.cumsum(nb)]
    cat = np.concatenate
    lbodies = cat([np.asarray(lm["bodies"], np.int64) for lm in landmarks])
    if lbodies.min() < 0 or lbodies.max() >= n_bodies:
        raise ValueError("landmark body index outside the bundle's bodies")
    n = int(start[-1])
    c = np.ascontiguousarray
    return Bundle(int(n_bodies), start.astype(np.int64), lb_start.astype(np.int64), lbodies,
                  c([lm["a_uv"] for lm in landmarks], float), c([lm["a_vel"] for lm in landmarks], float),
                  np.array([lm["a_off"] for lm in landmarks], float),
                  cat([np.asarray(lm["target"], np.int64) for lm in landmarks]),
                  cat([np.asarray(lm["right"], np.bool_) for lm in landmarks]),
                  c(cat([lm["uv"] for lm in landmarks]), float), c(cat([lm["vel"] for lm in landmarks]), float),
                  c(cat([lm["off"] for lm in landmarks]), float), c(cat([lm["basis"] for lm in landmarks]), float),
                  c(C, float), c(ad_inv, float), np.array([lm["lam"] for lm in landmarks], float),
                  np.ones(len(landmarks), np.bool_), np.zeros((2 * n, 2)), np.zeros((len(landmarks), 2)),
                  model == "sphere", float(sigma), 0 if robust is None else KERNELS.index(robust.kind),
                  float(robust.k) if robust is not None else 1.0, bool(use_td),
                  float(lam_bounds[0]), float(lam_bounds[1]), int(iters),
                  np.array([lm.get("p_lam", 0.0) for lm in landmarks], float),
                  np.array([lm.get("p_info", 0.0) for lm in landmarks], float))


def set_whitening(bundle: Bundle, bodies: np.ndarray, Tc: np.ndarray, td: float) -> None:
    """The anchor-noise whitening of every landmark (``factors.track_kernel.whitening``)
    at ``bodies`` (B, 4, 4), ``Tc`` and the bundle's lam (constant afterwards)."""
    _set_whitening(np.ascontiguousarray(bodies, float), np.ascontiguousarray(Tc, float), float(td),
                   bundle.use_td, bundle.start, bundle.lb_start, bundle.lbodies, bundle.a_uv, bundle.a_vel,
                   bundle.a_off, bundle.target, bundle.right, bundle.uv, bundle.vel, bundle.off,
                   bundle.basis, bundle.C, bundle.sphere, 1.0, 0, 1.0, bundle.lam, bundle.U, bundle.d)


def linearize(bundle: Bundle, bodies: np.ndarray, Tc: np.ndarray, td: float,
              update: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """(H (D, D), g (D,), E) at ``bodies`` (B, 4, 4), ``Tc`` (4, 4), ``td`` (s); the
    refined inverse depths are written to ``bundle.lam`` unless ``update`` is False."""
    D = bundle.dim
    H, g = np.zeros((D, D)), np.zeros(D)
    lam = bundle.lam if update else bundle.lam.copy()
    b = bundle
    E = bundle_system(np.ascontiguousarray(bodies, float), np.ascontiguousarray(Tc, float), float(td),
                      b.use_td, b.start, b.lb_start, b.lbodies, b.a_uv, b.a_vel, b.a_off, b.target,
                      b.right, b.uv, b.vel, b.off, b.basis, b.C, b.ad_inv, b.sphere, b.sigma, b.kind,
                      b.kk, b.U, b.d, lam, b.active, b.p_lam, b.p_info, b.hll, b.iters, b.lam_min,
                      b.lam_max, H, g, True)   # schur passed, not defaulted: one Numba signature
    return H, g, float(E)


def refine(bundle: Bundle, bodies: np.ndarray, Tc: np.ndarray, td: float, iters: int) -> float:
    """Refine ``bundle.lam`` in place at ``bodies``, ``Tc``, ``td`` (``iters`` Gauss-Newton
    steps, no elimination); returns the energy at the refined depths."""
    b = bundle
    H, g = np.zeros((1, 1)), np.zeros(1)
    return float(bundle_system(np.ascontiguousarray(bodies, float), np.ascontiguousarray(Tc, float),
                               float(td), b.use_td, b.start, b.lb_start, b.lbodies, b.a_uv, b.a_vel,
                               b.a_off, b.target, b.right, b.uv, b.vel, b.off, b.basis, b.C, b.ad_inv,
                               b.sphere, b.sigma, b.kind, b.kk, b.U, b.d, b.lam, b.active, b.p_lam,
                               b.p_info, b.hll, int(iters),
                               b.lam_min, b.lam_max, H, g, False))


def square_root(H: np.ndarray, g: np.ndarray, E: float, rel_eps: float = 1e-9
                ) -> tuple[np.ndarray, np.ndarray]:
    """(r (D + 1,), J (D + 1, D)) with J^T J = H (+ eps), J^T r = g, 0.5 |r|^2 = E:
    ``factors.photometric_host.square_root_kernel`` of the Jacobi-equilibrated
    ``S H S`` (``S = diag(H)^-1/2``), unscaled: the columns' units differ (radians,
    metres, seconds) and the regularization ``rel_eps`` is then relative per column."""
    dg = np.diag(H).copy()
    dg[~(dg > 0)] = 1.0
    s = 1.0 / np.sqrt(dg)
    r, J = square_root_kernel(np.ascontiguousarray(H * s[:, None] * s[None, :]), g * s, float(E),
                              float(rel_eps), 0.0)
    return r, J / s[None, :]


def bundle_kinds(bundle: Bundle) -> list:
    """Key kinds: ``T_b_c``, the bodies, then td if used."""
    return ["pose3"] * (1 + bundle.n_bodies) + ([1] if bundle.use_td else [])


def bundle_residual_fn(bundle: Bundle):
    """The residual function (square-root form) over :func:`bundle_kinds` keys."""
    B, use_td = bundle.n_bodies, bundle.use_td

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        bodies = np.array([T.matrix() for T in args[1:1 + B]])
        td = float(args[1 + B][0]) if use_td else 0.0
        H, g, E = linearize(bundle, bodies, args[0].matrix(), td)
        return square_root(H, g, E)

    return fn


def bundle_factor(keys: list[int], bundle: Bundle, health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """The bundle's factor over ``keys`` = [T_b_c, bodies..., td if used]."""
    kinds = bundle_kinds(bundle)
    if len(keys) != len(kinds):
        raise ValueError(f"bundle_factor: {len(keys)} keys for {len(kinds)} kinds")
    b = bundle   # refined inside at each linearization, rescaled and masked from outside
    return custom_factor(gtsam.noiseModel.Unit.Create(bundle.dim + 1), keys, kinds,
                         bundle_residual_fn(bundle), health, cache=True,
                         state=lambda: (b.lam.tobytes(), b.active.tobytes(), b.p_lam.tobytes(),
                                        b.p_info.tobytes()))
