"""Scale and gravity re-estimation after the start (monocular VIO), the role of
ORB-SLAM3's inertial-only refinements (``LocalMapping::ScaleRefinement`` /
``Optimizer::InertialOptimization`` at 5 s, 15 s, ... after initialization).

A dynamic initialization fixes the metric scale from 1.5 s of IMU; the fixed-lag
smoother then drifts from it: on the real MH_05 mono excerpt the initialization's window
is 7% long (its batch's scale sigma 6.2%), the estimate 3% short over the whole run
(Sim3 ATE 0.039 m, SE3 0.130 m); on generated MH_04 tracks from 40 s the initialization
has the truth's scale (1.004) and the smoother is 1.5-2% short for 30 s, where a batch
over the same factors has the right scale (:mod:`vio.backend.viba`, the default method). Once more excitation has
accumulated, this module re-solves scale and gravity direction over the keyframe history
with the visual-inertial trajectory fixed up to scale (:func:`solve`), and
:mod:`vio.backend.regauge` applies the correction to the estimator's state.

The inertial-only problem over the history's keyframes ``k = 0..N-1`` (world ``w``,
the estimator's current world; camera centres ``c_k`` and attitudes ``R_k`` fixed):

- unknowns ``s`` (scale of the camera trajectory), ``a = (a_x, a_y)`` (rad; gravity in
  ``w`` is ``Exp([a_x, a_y, 0]) g``, yaw is unobservable), a common correction ``dba``
  (m/s^2) of the accelerometer biases the intervals were integrated with, and the
  velocities ``v_k`` (m/s, world);
- body positions ``p_k(s) = s c_k - R_k t_bc``;
- per keyframe interval ``i -> j`` with preintegration ``(dt, dp(b), dv(b))``:
  ``r_p = R_i^T (p_j - p_i - v_i dt - g dt^2 / 2) - dp``,
  ``r_v = R_i^T (v_j - v_i - g dt) - dv``, weighted by the preintegration covariance
  plus ``pos_sigma_m`` of relative keyframe position noise on ``r_p`` (the positions
  are estimates, not truth);
- a prior ``dba ~ N(0, accel_bias_sigma^2)``.

Measured (why it is off by default): the solver recovers a known error from real IMU
and ground truth (MH_05 20-35 s, trajectory scaled by 0.95 and tilted 1.5 degrees:
scale within 1%, tilt within 0.3 degrees; ``tests/test_scale_refine.py``), but on the
estimator's own trajectory it finds what the smoother already has: the smoother's
trajectory is consistent with its IMU factors at its own scale. On generated MH_04 tracks
from 40 s the estimate is 1.6-2.1% short of the truth (Umeyama, chord and speed ratios
agree) while the refinement reports 0.99-1.005 (sigma 0.5%); on the ground truth itself
it reports 0.993 (the real IMU and the ground truth disagree by 0.7% there), and the
estimate's attitude errors (0.3 degrees mean) account for the rest. Applied on the seven
generated mid-flight excerpts of ``benchmarks/bench_midflight.py`` it made every
sequence worse (MH_04@40 0.118 -> 0.231 m, V1_02@30 0.022 -> 0.036 m); on the real MH_05
mono excerpt every attempt is refused (sigma 1.5-7%), and forcing it (sigma bound 3%)
gives 0.20 m instead of 0.13 m. The real MH_05 run is chaotic at that level: rebuilding
the smoother with the identity at frame 60, 150 or 200 gives 0.056, 0.151 and 0.199 m
(Sim3 0.045-0.094 m) for 0.130 m, so single-run differences below ~0.07 m there are
noise. ORB-SLAM3 refines a purely visual map, whose scale the IMU has not yet shaped;
here a full visual-inertial bundle adjustment over the history (attitudes free) would be
the next step.

The body positions get free corrections ``e_k ~ N(0, pos_sigma_m^2)`` (errors in the
variables: the positions are estimates, and a regression on noisy positions would
shrink ``s``). It is linear except in ``a``: a few Gauss-Newton steps from ``s = 1,
a = 0`` and the estimator's velocities. Determinacy test: the marginal standard deviations of ``s``
and of the gravity direction (from the normal equations, inflated by the posterior
variance factor ``chi2 / dof`` when above 1) must be below ``max_scale_sigma`` and
``max_gravity_sigma_deg``, and the change within ``max_scale_change`` and
``max_gravity_change_deg``; otherwise the refinement is refused (and logged).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from vio.config import check_ranges

NAN = float("nan")


@dataclass(frozen=True)
class RefineConfig:
    """When and how to refine the scale (and gravity) after the start (monocular only:
    stereo has a metric baseline). ``method``: ``"viba"`` (:mod:`vio.backend.viba`, a
    visual-inertial BA over the keyframe history) or ``"inertial"`` (this module's
    inertial-only problem, module docstring). Attempts at ``first_s`` after the history's
    start (initialization or restart), then every ``every_s`` until ``until_s``; a refused
    attempt is retried at the next keyframe after ``retry_s``. ``history_s``: the keyframe
    history used (s); ``min_intervals``: fewest IMU intervals (keyframes for viba).
    Inertial: ``max_scale_sigma``, ``max_gravity_sigma_deg`` (determinacy),
    ``min_scale_change`` / ``min_gravity_change_deg`` (below both the state is left alone).
    VIBA: ``ba_iterations`` of Levenberg-Marquardt, tracks seen in ``min_obs`` keyframes
    (the ``max_tracks`` longest, depths within ``[min_depth_m, max_depth_m]``), refused
    above ``ba_max_scale_sigma``; ``ba_apply``: ``"prior"`` puts the batch's scale on the
    newest keyframe's velocity (``s v``, relative sigma the batch's, at least
    ``ba_min_sigma``) and lets the smoother follow, ``"similarity"`` rebuilds the smoother
    at the scaled state (:func:`vio.backend.regauge.apply_similarity`; with
    ``ba_apply_tilt`` also the batch's gravity direction); ``ba_min_significance``: a batch
    whose scale is within that many of its own sigmas of the smoother's (``|ln s| < k
    sigma``) is not applied (0: every accepted batch is). ``scale_prior_sigma`` > 0 holds
    the inertial problem's scale at 1 with that relative sigma (gravity alone: the
    re-alignment after an IMU gap, :mod:`vio.backend.realign`).

    Off by default. Measured with ``enabled: true`` (viba, prior, every 2 s from 3 s over
    15 s of history), SE3 ATE before -> after: real MH_05 mono 15 s 0.130 -> 0.078 m;
    generated mid-flight excerpts (``benchmarks/bench_midflight.py``) MH_04@40 0.378 ->
    0.182% of the path, MH_05@40 0.312 -> 0.197%, MH_05@70 0.152 -> 0.200%, MH_03@50 0.128
    -> 0.152%, V1_02@30 0.086 -> 0.112%, V2_01@20 0.104 -> 0.105%; real V1_01 KLT tracks
    0.0267 -> 0.0225 m. Each BA costs 1-10 s (2 loaded cores; real-time factor 2.0x ->
    0.3x on V1_01), and the real MH_05 run is chaotic at this level (a 10-s history gives
    0.118 m). The similarity rebuild was worse (MH_05@70 0.053 -> 0.138 m, V1_02@30 0.024
    -> 0.042 m: every rebuild perturbs the smoother) and applying the batch's tilt worse
    again (MH_03@50 0.044 -> 0.088 m: 0.3-0.8 degrees back and forth every 2 s).

    What the prior gains is mostly not the batch's scale (issue 16, measured at b32d31c).
    Observed without being applied (``ba_min_significance: 1000000.0``), the batches on
    generated MH_04@40 report 1.000-1.011 up to 11 s and 1.009-1.018 from 13 s on (sigma
    0.8-2.0%) while the smoother is 1.8% short; on real MH_05 mono 0.976-1.023 (sigma
    1.8-2.7%) while it is 3.1% short: within 2.1 sigma every time, within 1.3 sigma on real
    MH_05. A prior at the smoother's own velocity (``s = 1``, sigma 1% of ``|v|``, every
    2 s, no batch) gives most of the gain: MH_04@40 0.378 -> 0.200% of the path, real MH_05
    mono 0.130 -> 0.060 m (Sim3 scale 1.031 -> 0.987), but MH_05@40 0.312 -> 0.300%, V2_02@25
    0.063 -> 0.079%, MH_03@50 0.128 -> 0.139%: it damps the smoother's drift by counting
    its own estimate again, so it is not offered. With ``ba_min_significance`` 1.5:
    MH_05@40 0.312 -> 0.186% (only the batch at 3.1 s applied: 1.036, sigma 2.0%), MH_03@50
    0.128% (none applied; ungated 0.152%), MH_04@40 0.378 -> 0.390% (three applied, from
    19 s), real MH_05 none applied (0.130 m).
    ``ba_worker``: the BA runs in a worker process (:mod:`vio.backend.viba_worker`) and its
    result is applied at the first keyframe ``ba_delay_s`` of data time after the attempt
    (waiting there if the worker is late, so the output stays deterministic); off, it runs
    on the frame path (0.3-0.5 s per BA on real MH_05 mono with GTSAM's C++ projection
    factors, 1-2.5 s with the earlier Python inverse-depth factors). The figures above
    were measured with those earlier factors, in process. With the C++ factors in the
    worker (delay 1.5 s), SE3 ATE, off -> on: real MH_05 mono from frames 0 / 25 / 50 /
    75 / 100 / 125 / 150: 0.057 / 0.151 / 0.231 / 0.108 / 0.172 / 0.076 / 0.097 -> 0.084 /
    0.085 / 0.127 / 0.133 / 0.141 / 0.064 / 0.097 m; mid-flight excerpts MH_03@50 0.128 ->
    0.176%, MH_04@40 0.334 -> 0.133%, MH_05@40 0.300 -> 0.131%, MH_05@70 0.181 -> 0.200%,
    V1_02@30 0.078 -> 0.116%, V2_01@20 0.103 -> 0.184%, V2_02@25 0.060 -> 0.092% (every
    one within 0.2%, the good ones worse); real V1_01 KLT tracks 0.0267 -> 0.031 m (the
    same in process: the world-point batch, not the delay); the benchmark's takeoff
    excerpts (60 s, td 5 ms) MH_04 0.172 -> 0.222%, V2_01 0.098 -> 0.167%, V2_02 0.067 ->
    0.088%, MH_03 0.066 -> 0.073%, the other four within 0.006%. It evens the runs out
    rather than improving them, so it stays off. (Every smoother rebuild dragged the
    marginal factors' means along until 510a2d4, ``vio.backend.smoother.anchored``; since
    then the similarity rebuild on real MH_05 mono from 14 start frames gives a mean 0.115
    m against 0.120 m off, standard error 0.02 m, and on the 20 mid-flight excerpts of
    ``bench_midflight`` (seed 1, td 5 ms) a geometric mean 0.121 % against 0.091 %, 18
    against 20 under 0.2 %: still off.) Since rebuilds keep iSAM2's fixed keys fixed and
    the similarity moves the linearization point with the marginals' columns
    (``vio.backend.smoother``, :func:`vio.backend.regauge.apply_similarity`), the rebuilt
    estimate lands on the transformed one (before: up to 0.6 m away on real MH_05 mono),
    and ``ba_apply: similarity`` gives real MH_05 mono from 17 starts (0, 10, ..., 160) a
    mean 84.5 mm (with ``ba_apply_tilt`` 87.2) against 83.1 mm off (232 / 217 mm before):
    even, so still off (the worst starts, 150 and 160 at +4-5 % scale, are the same bits
    with it: no batch of theirs was accepted)."""

    enabled: bool = False
    method: Literal["viba", "inertial"] = "viba"
    first_s: float = 3.0
    every_s: float = 2.0
    until_s: float = 100.0
    retry_s: float = 1.0
    history_s: float = 15.0
    min_intervals: int = 15
    pos_sigma_m: float = 0.003
    accel_bias_sigma: float = 0.2
    iterations: int = 6
    max_scale_sigma: float = 0.01
    max_gravity_sigma_deg: float = 0.5
    max_scale_change: float = 0.3
    max_gravity_change_deg: float = 5.0
    min_scale_change: float = 0.002
    min_gravity_change_deg: float = 0.05
    ba_iterations: int = 30
    ba_max_scale_sigma: float = 0.03
    ba_apply_tilt: bool = False
    ba_apply: Literal["prior", "similarity"] = "prior"
    ba_min_sigma: float = 0.005
    ba_min_significance: float = 0.0
    min_obs: int = 3
    ba_worker: bool = True
    ba_delay_s: float = 1.5
    max_tracks: int = 400
    min_depth_m: float = 0.2
    max_depth_m: float = 60.0
    scale_prior_sigma: float = 0.0

    def __post_init__(self) -> None:
        check_ranges(self, positive=("every_s", "pos_sigma_m", "accel_bias_sigma", "iterations", "max_scale_sigma",
                                     "max_gravity_sigma_deg", "ba_iterations", "min_obs", "max_tracks",
                                     "min_depth_m", "max_depth_m"))


@dataclass(frozen=True)
class Interval:
    """One keyframe interval's preintegration: keyframe indices ``i``, ``j`` (history
    rows), ``dt`` (s), ``dp``, ``dv`` (3,) at the integration bias (gravity removed,
    frame of keyframe i), their Jacobians ``Jp``, ``Jv`` (3, 3) w.r.t. the accelerometer
    bias, that bias ``ba`` (3,), and the (6, 6) covariance of ``[dp, dv]``."""

    i: int
    j: int
    dt: float
    dp: np.ndarray
    dv: np.ndarray
    Jp: np.ndarray
    Jv: np.ndarray
    ba: np.ndarray
    cov: np.ndarray


def interval(i: int, j: int, pim: gtsam.PreintegratedCombinedMeasurements,
             gravity: np.ndarray, step: float = 0.01) -> Interval:
    """The :class:`Interval` of ``pim`` (gravity ``gravity`` (3,) as in its params); the
    bias Jacobians by differences of GTSAM's (linear) first-order bias correction."""
    b = pim.biasHat()
    dt = pim.deltaTij()

    def delta(ba: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ns = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(ba, b.gyroscope()))
        return ns.position() - 0.5 * dt * dt * gravity, ns.velocity() - dt * gravity

    dp, dv = delta(b.accelerometer())
    Jp, Jv = np.zeros((3, 3)), np.zeros((3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = step
        p1, v1 = delta(b.accelerometer() + e)
        Jp[:, a], Jv[:, a] = (p1 - dp) / step, (v1 - dv) / step
    C = np.asarray(pim.preintMeasCov())[3:9, 3:9]
    return Interval(i, j, dt, dp, dv, Jp, Jv, b.accelerometer().copy(), 0.5 * (C + C.T))


@dataclass(frozen=True)
class Refinement:
    """Outcome of :func:`solve`: ``scale`` (multiply the trajectory's lengths), the
    world correction ``R_corr`` (rotate the world so gravity is along -z again),
    ``dba`` (m/s^2), velocities ``v`` (N, 3) in the corrected world, the sigmas of the
    scale (relative) and gravity direction (deg), ``gravity_change_deg``, ``chi2_dof``,
    the number of intervals; ``ok`` and a ``reason`` when refused."""

    ok: bool
    reason: str
    scale: float = NAN
    R_corr: gtsam.Rot3 | None = None
    dba: np.ndarray | None = None
    v: np.ndarray | None = None
    scale_sigma: float = NAN
    gravity_sigma_deg: float = NAN
    gravity_change_deg: float = NAN
    chi2_dof: float = NAN
    n_intervals: int = 0


def _residuals(x: np.ndarray, R: np.ndarray, c: np.ndarray, t_bc: np.ndarray, ivs: list[Interval],
               g0: np.ndarray, W: np.ndarray, ba_sigma: float, ba0: np.ndarray,
               pos_sigma: float, s_sigma: float = 0.0) -> np.ndarray:
    """Whitened residuals (6 per interval, then the bias prior) at ``x = [s, a_x, a_y,
    dba(3), v (3N), e (3N)]``, then ``(s - 1) / s_sigma`` when ``s_sigma`` > 0 (the
    scale held); one accelerometer bias ``ba0 + dba`` for all intervals (the
    smoother's bias may have drifted to absorb a wrong scale); ``W`` (M, 6, 6) the
    intervals' whitening matrices."""
    s, a, dba = x[0], np.r_[x[1:3], 0.0], x[3:6]
    n = len(R)
    v = x[6:6 + 3 * n].reshape(-1, 3)
    e = x[6 + 3 * n:].reshape(-1, 3)
    g = gtsam.Rot3.Expmap(a).matrix() @ g0
    i = np.array([iv.i for iv in ivs])
    j = np.array([iv.j for iv in ivs])
    dt = np.array([iv.dt for iv in ivs])[:, None]
    p = s * c - np.einsum("kab,b->ka", R, t_bc) + e
    dp = np.array([iv.dp + iv.Jp @ (ba0 + dba - iv.ba) for iv in ivs])
    dv = np.array([iv.dv + iv.Jv @ (ba0 + dba - iv.ba) for iv in ivs])
    RiT = np.transpose(R[i], (0, 2, 1))
    rp = np.einsum("kab,kb->ka", RiT, p[j] - p[i] - v[i] * dt - 0.5 * g * dt ** 2) - dp
    rv = np.einsum("kab,kb->ka", RiT, v[j] - v[i] - g * dt) - dv
    r = np.einsum("kab,kb->ka", W, np.hstack([rp, rv]))
    out = np.r_[r.ravel(), dba / ba_sigma, e.ravel() / pos_sigma]
    return np.r_[out, (s - 1.0) / s_sigma] if s_sigma > 0 else out


def solve(T_w_b: list[gtsam.Pose3], v0: np.ndarray, ivs: list[Interval], T_b_c: gtsam.Pose3,
          gravity: np.ndarray, cfg: RefineConfig) -> Refinement:
    """Scale and gravity direction over keyframes with poses ``T_w_b`` (N) and velocity
    guesses ``v0`` (N, 3), from the preintegrated intervals ``ivs`` (module docstring)."""
    if len(ivs) < cfg.min_intervals:
        return Refinement(False, f"only {len(ivs)} IMU intervals in the history")
    R = np.array([T.rotation().matrix() for T in T_w_b])
    t_bc = T_b_c.translation()
    c = np.array([T.translation() for T in T_w_b]) + np.einsum("kab,b->ka", R, t_bc)
    W = np.array([np.linalg.inv(np.linalg.cholesky(iv.cov)) for iv in ivs])
    x = np.r_[1.0, 0.0, 0.0, np.zeros(3), np.asarray(v0, float).ravel(), np.zeros(3 * len(R))]
    ba0 = np.mean([iv.ba for iv in ivs], axis=0)
    args = (R, c, t_bc, ivs, np.asarray(gravity, float), W, cfg.accel_bias_sigma, ba0, cfg.pos_sigma_m,
            cfg.scale_prior_sigma)
    H = np.eye(len(x))
    for _ in range(cfg.iterations):
        r = _residuals(x, *args)
        J = _jacobian(x, r, args)
        H = J.T @ J
        dx = np.linalg.solve(H + 1e-9 * np.eye(len(x)), -J.T @ r)
        x = x + dx
        if np.max(np.abs(dx[:6])) < 1e-9:
            break
    r = _residuals(x, *args)
    dof = max(len(r) - len(x), 1)
    chi2 = float(r @ r) / dof
    cov = np.linalg.inv(H) * max(chi2, 1.0)
    s_sig = float(np.sqrt(cov[0, 0])) / x[0]
    g_sig = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[1:3, 1:3]).max(), 0.0))))
    a = np.r_[x[1:3], 0.0]
    R_corr = gtsam.Rot3.Expmap(-a)
    v = (R_corr.matrix() @ x[6:6 + 3 * len(R)].reshape(-1, 3).T).T
    out = dict(scale=float(x[0]), R_corr=R_corr, dba=x[3:6].copy(), v=v, scale_sigma=s_sig,
               gravity_sigma_deg=g_sig, gravity_change_deg=float(np.degrees(np.linalg.norm(a))),
               chi2_dof=chi2, n_intervals=len(ivs))
    reason = _refusal(out, cfg)
    return Refinement(reason is None, reason or "ok", **out)


def _jacobian(x: np.ndarray, r: np.ndarray, args: tuple) -> np.ndarray:
    """Jacobian of :func:`_residuals`: forward differences for the six global
    parameters, analytic (the residuals are linear in them) columns for the velocities."""
    R, _, _, ivs, _, W, _, _, pos_sigma, _ = args
    n = len(R)
    J = np.zeros((len(r), len(x)))
    for k, h in enumerate([1e-6, 1e-7, 1e-7, 1e-6, 1e-6, 1e-6]):
        e = np.zeros(len(x))
        e[k] = h
        J[:, k] = (_residuals(x + e, *args) - r) / h
    for m, iv in enumerate(ivs):
        RiT, dt = R[iv.i].T, iv.dt
        blk = np.zeros((6, 6))            # d[rp; rv] / d[v_i, v_j]
        blk[:3, :3], blk[3:, :3], blk[3:, 3:] = -RiT * dt, -RiT, RiT
        Wb = W[m] @ blk
        rows = slice(6 * m, 6 * m + 6)
        J[rows, 6 + 3 * iv.i:9 + 3 * iv.i] += Wb[:, :3]
        J[rows, 6 + 3 * iv.j:9 + 3 * iv.j] += Wb[:, 3:]
        We = W[m][:, :3] @ RiT            # d r_p / d e_j; d / d e_i is its negative
        o = 6 + 3 * n
        J[rows, o + 3 * iv.j:o + 3 * iv.j + 3] += We
        J[rows, o + 3 * iv.i:o + 3 * iv.i + 3] -= We
    m0 = 6 * len(ivs) + 3
    J[m0:m0 + 3 * n, 6 + 3 * n:] = np.eye(3 * n) / pos_sigma
    return J


def _refusal(out: dict, cfg: RefineConfig) -> str | None:
    """Why the solution is not to be applied (None: apply it)."""
    s = out["scale"]
    if not np.isfinite(s) or s <= 0:
        return f"non-finite or non-positive scale {s}"
    if not out["scale_sigma"] <= cfg.max_scale_sigma:
        return (f"scale poorly determined (sigma {100 * out['scale_sigma']:.2f}% > "
                f"{100 * cfg.max_scale_sigma:.2f}%)")
    if not out["gravity_sigma_deg"] <= cfg.max_gravity_sigma_deg:
        return f"gravity poorly determined (sigma {out['gravity_sigma_deg']:.2f} deg)"
    if abs(np.log(s)) > np.log1p(cfg.max_scale_change):
        return f"implausible scale change {s:.3f}"
    if out["gravity_change_deg"] > cfg.max_gravity_change_deg:
        return f"implausible gravity change {out['gravity_change_deg']:.2f} deg"
    return None
