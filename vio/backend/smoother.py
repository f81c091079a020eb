"""The fixed-lag smoother: its construction from ``SolverConfig``, its rebuild from its own
factors, and the QR re-solve after a Cholesky refusal.

The gtsam ``Values`` is the only state copy, so a rebuild takes the old smoother's
factors (marginal ``LinearContainerFactor``s included, each given its linearization point:
:func:`anchored`), linearization point and timestamps into a fresh
``IncrementalFixedLagSmoother``; factor slots change, so every manager holding smoother
indices (``remap_factor_indices``) is remapped.

Cholesky (``SolverConfig.factorization: CHOLESKY``, the default) eliminates ~1.4x
faster than dense Householder QR on the real sets (real MH_05 mono, main process CPU
6.63 -> 4.68 s, same trajectory), but GTSAM's Cholesky refuses a clique whose last two
R diagonal entries differ by more than 2^18 (``IndeterminateLinearSystem``), which a
weakly observed world point occasionally triggers on generated mid-flight tracks (3 of
13 ``bench_midflight`` excerpts, once each). iSAM2 has then already taken the update's
factors and values in (GTSAM ``ISAM2::update`` adds them before eliminating), so
:func:`qr_resolve` rebuilds the smoother from that graph instead of restarting the window
(a restart loses the window's information), with QR, and :func:`maybe_back_to_cholesky`
rebuilds with Cholesky once the variable GTSAM named has left the window, else once the
keyframes present at the refusal have (the QR window costs ~1.9x per keyframe). Real
MH_01 mono refuses twice, at world points that are gone by the next keyframe: 18 of 89
keyframes were on QR at 91 instead of 54 ms, now none (``keyframe_cost.py``: mean / p90
59.5 / 99.5 -> 49.3 / 57.9 ms; 7 stretches per-frame p95 at the refusing starts 78-96 ->
61-65 ms, ATE the same bits, and the 31 generator variants and 16 mid-flight starts of
seed 7 the same bits: rebuilds are neutral, below).
Opt-in for latency (``SolverConfig.refusal_point_sigma`` > 0): where the refusal names a
world point (one with almost no information in some direction: low parallax, or behind
the cameras at some iterate, where only its 20-m prior holds it), the rebuild keeps
Cholesky and adds a prior holding that one point where it is; QR only if Cholesky
refuses again or the variable is not a point. Off by default: against the default it
moves 3 of the 31 generator variants, one of them past 0.2 % of the path (``SolverConfig``
has the figures).

A rebuild is neutral: the chain of ``tests/test_smoother.py`` rebuilt twice ends within
1e-9 of the smoother never rebuilt. Two things make it so. Marginal factors carry their
linearization point (:func:`anchored`). And the keys iSAM2 held fixed stay fixed
(:func:`_fixing_factors`): ``marginalizeLeaves`` fixes every key of a marginal it makes,
in a window of world points every point a leaving keyframe saw, so their later
observations are linearized at that point too; a fresh smoother would relinearize them.
Until the fixed keys were carried over (measured by rebuilding at a fixed period, a patch,
not a mode of the pipeline): real MH_05 mono from frame 0, one rebuild at ~8.5 s, 0.0665
-> 0.537 m (scale -12.5 %), every 2.5 s from 7 starts mean 81 -> 342 mm, real V1_01
features every 2.5 s 0.0241 -> 0.0258 m; with them 0.0665 m, 80.9 mm and 0.0241 m, as
without a rebuild. (Not relinearizing points at all after a rebuild gave 0.062 m there,
but is no general fix: 17 starts 87.9 -> 93.9 mm, V1_01 0.0241 -> 0.0256 m.)

The estimator (``vio.backend.estimator.Estimator``, or the benchmark's GTSAM-native
baseline) provides ``smoother``, ``values``, ``_new_smoother(factorization)``,
``home_factorization`` (the configured one), ``smoother_factorization`` (the current
one), ``qr_since``, ``qr_resolves``, ``kf_t`` (keyframe -> time), ``k`` and
``remap_factor_indices(remap)``.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Callable

import gtsam
import numpy as np

from vio.backend.config import SolverConfig

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

log = logging.getLogger(__name__)

FIX_CHR = "w"   # key character of the 1-d stand-ins that carry fixed keys over a rebuild


def _void(f: gtsam.NonlinearFactor) -> bool:
    """Whether ``f`` is a marginal without information: what a stand-in of
    :func:`_fixing_factors` leaves, dropped at the next rebuild (which fixes the key anew)."""
    return isinstance(f, gtsam.LinearContainerFactor) and not np.any(f.factor().augmentedInformation())


def _fixing_factors(old: gtsam.IncrementalFixedLagSmoother, lin: gtsam.Values, stamps: dict
                    ) -> tuple[list, gtsam.Values, dict[int, float]]:
    """What makes a new smoother keep ``old``'s fixed keys fixed (module docstring).

    iSAM2 fixes every key of a marginal factor it creates (``marginalizeLeaves``), and that
    is the only way to fix a key from Python. So for each fixed key k: a stand-in variable
    w_i (1-d, value 0) and a linear factor [1 | 0] on (w_i, k) with no information on k,
    stamped older than the window so that the rebuild's own update marginalizes w_i at
    once: the marginal it leaves on k (no rows) marks k fixed. Returns (factors, stand-in
    values, stand-in timestamps)."""
    fixed = [int(k) for k in old.getISAM2().getFixedVariables() if lin.exists(int(k))]
    t_old = min(stamps.values(), default=0.0) - 10.0 * max(old.smootherLag(), 1.0)
    facs, vals, st = [], gtsam.Values(), {}
    unit = gtsam.noiseModel.Unit.Create(1)
    for i, k in enumerate(fixed):
        w = gtsam.Symbol(FIX_CHR, i).key()
        dim = lin.extract([k]).dim()
        jf = gtsam.JacobianFactor(w, np.eye(1), k, np.zeros((1, dim)), np.zeros(1), unit)
        facs.append(gtsam.LinearContainerFactor(jf))
        vals.insert(w, np.zeros(1))
        st[w] = t_old
    return facs, vals, st


def _threshold_map(general: float, td: float, extra: dict[str, int] | None = None,
                   point: float | None = None,
                   own: dict[str, tuple[float, ...]] | None = None) -> gtsam.ISAM2ThresholdMap:
    """Per-variable-type relinearization thresholds: td (seconds) moves by ~1e-4 per
    step and would never cross the general threshold; world points (m) at ``point``
    (None: the general one); ``own``: key character -> one threshold per tangent
    dimension, in the variable's own units (a factor source's, ``FactorSource.key_thresholds``)."""
    m = gtsam.ISAM2ThresholdMap()
    dims = {"x": 6, "v": 3, "b": 6, "e": 6, "l": 1, "p": 3, "z": 1, FIX_CHR: 1, **(extra or {})}
    own = own or {}
    for ch, dim in dims.items():
        th = np.full(dim, point if ch == "p" and point is not None else general)
        if ch in own:
            th = np.asarray(own[ch], dtype=float)
            if th.shape != (dim,):
                raise ValueError(f"relinearization thresholds of key '{ch}': {th.shape[0] if th.ndim else 1} "
                                 f"values for a {dim}-dimensional variable")
        m.insert((ch, th))
    m.insert(("d", np.array([td])))
    return m


def make(s: SolverConfig, extra_dims: dict[str, int] | None = None,
         factorization: str | None = None,
         thresholds: dict[str, tuple[float, ...]] | None = None) -> gtsam.IncrementalFixedLagSmoother:
    """A fresh smoother as ``s`` says (``factorization`` overrides it); ``extra_dims``:
    key character -> dimension of the factor sources' variables, ``thresholds``: their own
    relinearization thresholds where they have them (else the general one)."""
    p = gtsam.ISAM2Params()
    p.setFactorization(factorization or s.factorization)
    p.setRelinearizeThreshold(_threshold_map(s.relinearize_threshold, s.td_relinearize_threshold, extra_dims,
                                            s.point_relinearize_threshold, thresholds))
    p.relinearizeSkip = s.relinearize_skip
    p.findUnusedFactorSlots = True   # reuse removed factor slots: flat memory on long runs
    # iSAM2 skips updating variables whose change is below the wildfire threshold
    # (default 1e-3): td (seconds) then never moves; see SolverConfig.wildfire_threshold
    gn = gtsam.ISAM2GaussNewtonParams()
    gn.setWildfireThreshold(s.wildfire_threshold)
    p.setOptimizationParams(gn)
    return gtsam.IncrementalFixedLagSmoother(s.lag_s, p)


def update(sm: gtsam.IncrementalFixedLagSmoother, *args) -> None:
    """``sm.update(*args)`` with a Python reference to ``sm``'s linearization point held.

    pybind11 hands a Python factor callback its ``const Values&`` as a copy unless that
    very C++ object already has a Python wrapper (its instance registry). iSAM2 linearizes
    at its own ``theta_``, and ``getLinearizationPoint`` wraps that member by reference
    (~0.3 us, keeping the smoother alive), so with the wrapper held every callback of the
    update receives it uncopied: ~0.1 us per key per callback less (generated MH_03
    features: ~460 keys with the padding, ~130 callbacks a keyframe; the copies were 14 %
    of the smoother update in ``py-spy --native``)."""
    theta = sm.getLinearizationPoint()  # noqa: F841 - held for the update's callbacks
    sm.update(*args)


def anchored(f: gtsam.NonlinearFactor, lin: gtsam.Values) -> gtsam.NonlinearFactor:
    """``f``, a marginal factor (``LinearContainerFactor``) made explicit about ``lin``.

    iSAM2's ``marginalizeLeaves`` stores its marginals without a linearization point and
    marks their keys fixed: that smoother never relinearizes them, so its ``theta_`` is
    their point. A new smoother knows nothing of those fixed keys; there a container
    without a point would be handed back unshifted at every relinearization of its keys
    (``LinearContainerFactor::linearize``), dragging its mean along with the estimate.
    Linearized at ``lin`` and given ``lin`` as its point, it shifts as it should (its
    error, 0 without a point, is counted too). Other factors are returned unchanged."""
    if not isinstance(f, gtsam.LinearContainerFactor):
        return f
    return gtsam.LinearContainerFactor(f.linearize(lin), lin.extract(list(f.keys())))


def rebuilt(est: "Estimator", values: gtsam.Values | None = None,
            convert: Callable | None = None, factorization: str | None = None,
            extra: list[gtsam.NonlinearFactor] = ()
            ) -> tuple[gtsam.IncrementalFixedLagSmoother, dict[int, int], list]:
    """A new smoother holding ``est.smoother``'s non-null factors (each through
    ``convert(f, lin)`` if given; ``lin`` the old linearization point) at ``values``
    (default ``lin``) with the old timestamps, factorized as ``factorization`` (default:
    the current smoother's). Returns (smoother, {old slot: new slot}, [(old slot, factor)]
    as taken from the old smoother). Raises RuntimeError if the solver refuses; ``est`` is
    left untouched."""
    old = est.smoother
    lin = old.getLinearizationPoint()
    fg = old.getFactors()
    stamps = {int(k): float(t) for k, t in old.timestamps().items()}
    g, kept = gtsam.NonlinearFactorGraph(), []
    for j in range(fg.size()):
        f = fg.at(j)
        if f is None or _void(f):
            continue
        kept.append((j, f))
        f = anchored(f, lin)
        g.add(f if convert is None else convert(f, lin))
    for f in extra:             # after the kept factors: their slots are not remapped
        g.add(f)
    theta = gtsam.Values(lin if values is None else values)
    fix, wv, wst = _fixing_factors(old, lin, stamps)
    for f in fix:
        g.add(f)
    theta.insert(wv)
    new = est._new_smoother(factorization or est.smoother_factorization)
    update(new, g, theta, {**stamps, **wst})
    idx = list(new.getISAM2Result().getNewFactorsIndices())
    return new, {j: int(i) for (j, _), i in zip(kept, idx)}, kept


def install(est: "Estimator", new: gtsam.IncrementalFixedLagSmoother, remap: dict[int, int],
            factorization: str | None = None) -> None:
    """Make ``new`` (factorized as ``factorization``, default unchanged) the estimator's
    smoother; remap every recorded factor slot."""
    est.remap_factor_indices(remap)
    est.smoother = new
    est.smoother_factorization = factorization or est.smoother_factorization
    est.values = new.calculateEstimate()


def _refused_variable(exc: RuntimeError) -> str:
    """The variable GTSAM names in an ``IndeterminateLinearSystem`` message (e.g. "p187")."""
    return str(exc).split("(Symbol: ")[-1].split(")")[0] if "(Symbol: " in str(exc) else "?"


def _refused_key(var: str) -> int | None:
    """The key of ``var`` as :func:`_refused_variable` names it ("p187"), None if unnamed."""
    if len(var) < 2 or not var[0].isalpha() or not var[1:].isdigit():
        return None
    return gtsam.Symbol(var[0], int(var[1:])).key()


def _point_prior(est: "Estimator", var: str) -> gtsam.NonlinearFactor | None:
    """A prior holding the refused world point ``var`` ("p<index>") where it is, with
    sigma ``SolverConfig.refusal_point_sigma`` times its distance from the newest
    keyframe (module docstring); None for other variables or when that is off."""
    solver = getattr(est.cfg, "solver", None)   # None in the benchmark's baseline: always QR
    rel = getattr(solver, "refusal_point_sigma", 0.0)
    key = _refused_key(var)
    if not rel or key is None or var[0] != "p":
        return None
    lin = est.smoother.getLinearizationPoint()
    x = gtsam.symbol_shorthand.X(est.k)
    if not (lin.exists(key) and lin.exists(x)):
        return None
    p = np.asarray(lin.atVector(key), float)
    sigma = rel * max(float(np.linalg.norm(p - lin.atPose3(x).translation())), 0.1)
    return gtsam.PriorFactorVector(key, p, gtsam.noiseModel.Isotropic.Sigma(3, sigma))


def _slots(g: gtsam.NonlinearFactorGraph, kept: list, remap: dict[int, int]) -> list[int] | None:
    """The rebuilt smoother's slots of ``g``'s factors, in ``g``'s order (taken out of
    ``remap``); None if one is missing."""
    mine = [g.at(i) for i in range(g.size())]   # alive, so pybind11 returns these very objects
    pos = {id(f): i for i, f in enumerate(mine)}
    slots = [-1] * len(mine)
    for j, f in kept:
        i = pos.get(id(f))   # ids of live objects are unique: an equal id is the same factor
        if i is not None:
            slots[i] = remap.pop(j)
    return None if min(slots, default=0) < 0 else slots


def qr_resolve(est: "Estimator", g: gtsam.NonlinearFactorGraph, exc: RuntimeError) -> list[int]:
    """After ``est.smoother.update(g, ...)`` raised under Cholesky: rebuild from the graph
    iSAM2 had taken in (module docstring) and return the new slots of ``g``'s factors, in
    ``g``'s order: with QR, or, refused at a world point with ``SolverConfig.
    refusal_point_sigma`` > 0, with Cholesky and a prior on that point (:func:`_point_prior`)
    if Cholesky then accepts. Re-raises ``exc``
    when this does not apply (QR already, not an indeterminate system, ``g``'s factors
    not all found) or QR refuses too."""
    if est.smoother_factorization != "CHOLESKY" or "Indeterminate" not in str(exc):
        raise exc
    var = _refused_variable(exc)
    prior = _point_prior(est, var)
    if prior is not None:
        try:
            new, remap, kept = rebuilt(est, extra=[prior])
            slots = _slots(g, kept, remap)
        except RuntimeError:
            slots = None
        if slots is not None:
            install(est, new, remap)
            est.point_holds = getattr(est, "point_holds", 0) + 1   # the baseline keeps none
            log.info("keyframe %d: Cholesky refused the update at world point %s; re-solved with "
                     "Cholesky, that point held where it is (sigma %.2f m)", est.k, var,
                     float(prior.noiseModel().sigmas()[0]))
            return slots
    try:
        new, remap, kept = rebuilt(est, factorization="QR")
    except RuntimeError:
        raise exc from None
    slots = _slots(g, kept, remap)
    if slots is None:
        raise exc
    install(est, new, remap, "QR")
    est.qr_since, est.qr_key = est.kf_t.get(est.k), _refused_key(var)
    est.qr_resolves += 1
    log.warning("keyframe %d: Cholesky refused the update (near variable %s); re-solved with QR "
                "(re-solve #%d), QR until %s has left the window", est.k, var, est.qr_resolves,
                var if est.qr_key is not None else "that keyframe")
    return slots


def maybe_back_to_cholesky(est: "Estimator") -> None:
    """After a QR re-solve: once the variable GTSAM named has left the window, or else
    every keyframe of that moment, rebuild with Cholesky (rebuilds are neutral: only the
    solver changes); if Cholesky refuses, QR until the keyframes present then have left."""
    t0 = est.qr_since
    if est.smoother_factorization == est.home_factorization or t0 is None:
        return
    key = est.qr_key   # set with qr_since by qr_resolve
    gone = key is not None and not est.smoother.getLinearizationPoint().exists(key)
    if not gone and min(est.kf_t.values(), default=t0) <= t0:
        return
    try:
        new, remap, _ = rebuilt(est, factorization=est.home_factorization)
    except RuntimeError:
        est.qr_since, est.qr_key = est.kf_t.get(est.k), None
        return
    install(est, new, remap, est.home_factorization)
    est.qr_since = None
    log.info("keyframe %d: back to %s after the QR re-solve", est.k, est.smoother_factorization)
