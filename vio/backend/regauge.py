"""Keyframe history for the scale and gravity refinement (:mod:`vio.backend.scale_refine`)
and the application of its similarity correction to the estimator's state.

:class:`ScaleRefiner` keeps, since the (re)start, every keyframe's latest smoothed pose
and velocity and the preintegrated IMU of each interval (bridged IMU gaps excluded); at
the scheduled times it solves for scale and gravity and, when the solution passes the
determinacy test, :func:`apply_similarity` moves the whole state into the corrected
world: camera centres scaled by ``s`` about the history's first camera and rotated by
``R_corr`` (gravity back along -z), attitudes rotated, velocities ``s R_corr v``, inverse
depths ``rho / s``; biases, extrinsic and td unchanged. The gtsam ``Values`` is the only
state copy, so the smoother is rebuilt from its own factors at its transformed
linearization point: projection factors are invariant under a similarity, IMU factors
are not (that is the point), and each marginal factor (``LinearContainerFactor``, linear
about the old point) is moved to the transformed point with its columns in the new
world's tangents (:func:`_marginal`: world-frame velocities and points rotate by ``R``
and scale by ``s``, body-frame translation steps scale by ``s``). Factor indices change,
so the landmark manager's records are remapped.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from vio.backend import graph
from factors.robust import RobustKernel
from vio.backend import viba
from vio.backend.smoother import install, rebuilt
from vio.backend.scale_refine import RefineConfig, Refinement, interval, solve
from vio.backend.viba import History
from vio.backend.viba_worker import BatchWorker
from vio.errors import one_line

if TYPE_CHECKING:
    from vio.backend.estimator import Estimator

log = logging.getLogger(__name__)
X, V, B = graph.X, graph.V, graph.B


class Similarity:
    """``x -> pivot + s R (x - pivot) + shift`` on camera centres, applied to body states with the
    lever arm ``t_bc`` (m, body frame)."""

    def __init__(self, s: float, R: gtsam.Rot3, pivot: np.ndarray, t_bc: np.ndarray,
                 shift: np.ndarray | None = None) -> None:
        self.s, self.R, self.Rm = float(s), R, R.matrix()
        self.pivot, self.t_bc = np.asarray(pivot, float), np.asarray(t_bc, float)
        self.shift = np.zeros(3) if shift is None else np.asarray(shift, float)

    def pose(self, T: gtsam.Pose3) -> gtsam.Pose3:
        Rb = T.rotation().matrix()
        c = T.translation() + Rb @ self.t_bc
        c2 = self.pivot + self.s * self.Rm @ (c - self.pivot) + self.shift
        R2 = self.Rm @ Rb
        return gtsam.Pose3(gtsam.Rot3(R2), c2 - R2 @ self.t_bc)

    def point(self, p_w: np.ndarray) -> np.ndarray:
        """A world point moves like a camera centre."""
        return self.pivot + self.s * self.Rm @ (np.asarray(p_w, float) - self.pivot) + self.shift

    def velocity(self, v: np.ndarray) -> np.ndarray:
        return self.s * self.Rm @ np.asarray(v, float)

    def tangent(self, key: int, dim: int) -> np.ndarray:
        """(dim, dim): the old tangent step of ``key``'s variable from the new one
        (``d_old = M d_new``, first order). Poses ``[omega, v]`` (body frame): the rotation
        step is unchanged, ``v = (v' + (s - 1) t_bc x omega') / s`` (the camera centre scales,
        the lever arm does not); velocities and world points ``R^T / s``; inverse depths
        ``s``; the others (biases, extrinsic, td, padding, brightness) unchanged."""
        ch, M = chr(gtsam.Symbol(key).chr()), np.eye(dim)
        if ch == "x":
            M[3:, :3] = (self.s - 1.0) / self.s * gtsam.Rot3.Hat(self.t_bc)
            M[3:, 3:] /= self.s
        elif ch in ("v", "p"):
            M = self.Rm.T / self.s
        elif ch == "l":
            M *= self.s
        return M

    def identity(self) -> bool:
        return self.s == 1.0 and np.array_equal(self.Rm, np.eye(3))

    def values(self, vals: gtsam.Values, keys=None) -> gtsam.Values:
        """The transformed copy of ``vals`` (only ``keys`` if given)."""
        out = gtsam.Values()
        for key in (vals.keys() if keys is None else keys):
            ch = chr(gtsam.Symbol(key).chr())
            if ch == "x":
                out.insert(key, self.pose(vals.atPose3(key)))
            elif ch == "v":
                out.insert(key, self.velocity(vals.atVector(key)))
            elif ch == "l":
                out.insert(key, vals.atVector(key) / self.s)
            elif ch == "p":      # world points (vio.backend.point_tracks)
                out.insert(key, self.point(vals.atVector(key)))
            elif ch == "b":
                out.insert(key, vals.atConstantBias(key))
            elif ch == "e":
                out.insert(key, vals.atPose3(key))
            elif ch in ("d", "z", "a"):   # td; padding keys (vio.backend.padding); affine brightness (vio.direct)
                out.insert(key, vals.atVector(key))
            else:
                raise ValueError(f"cannot transform key {gtsam.DefaultKeyFormatter(key)}")
        return out


def _marginal(f: gtsam.LinearContainerFactor, sim: Similarity, lin: gtsam.Values
              ) -> gtsam.LinearContainerFactor:
    """The marginal ``f`` (linear about ``lin``) about ``sim(lin)``, its columns in the new
    world's tangents (:meth:`Similarity.tangent`): the augmented information ``[A b]^T [A b]``
    congruent under ``diag(M_1 .. M_n, 1)``, back to rows by its eigen decomposition, and
    those rows made a factor on all of ``f``'s keys by linearizing a ``CustomFactor`` whose
    Jacobians they are (the Python API builds multi-key linear factors no other way)."""
    keys = list(f.keys())
    new = sim.values(lin, keys)
    if sim.identity():
        return gtsam.LinearContainerFactor(f.factor(), new)
    dims = [lin.extract([k]).dim() for k in keys]
    D = np.zeros((sum(dims) + 1, sum(dims) + 1))
    o = 0
    for k, d in zip(keys, dims):
        D[o:o + d, o:o + d] = sim.tangent(k, d)
        o += d
    D[-1, -1] = 1.0
    w, U = np.linalg.eigh(D.T @ f.factor().augmentedInformation() @ D)
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    rows = (np.sqrt(w[keep])[:, None] * U[:, keep].T)
    if rows.shape[0] == 0:
        return gtsam.LinearContainerFactor(f.factor(), new)
    edges = np.cumsum([0] + dims)
    blocks = [np.ascontiguousarray(rows[:, a:b]) for a, b in zip(edges[:-1], edges[1:])]

    def at_new(_, v, H):   # linearized only at ``new`` (below): the step there is 0
        if H is not None:
            for i, Bk in enumerate(blocks):
                H[i] = Bk
        return -rows[:, -1]

    cf = gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows.shape[0]), keys, at_new)
    return gtsam.LinearContainerFactor(cf.linearize(new), new)


def _factor(f, sim: Similarity, lin: gtsam.Values):
    """``f`` in the transformed world (module docstring); ``lin``: the smoother's
    linearization point, at which ``smoother.rebuilt`` hands over each marginal factor
    (``smoother.anchored``: its linear factor about ``lin``)."""
    if isinstance(f, gtsam.LinearContainerFactor):
        return _marginal(f, sim, lin)
    if isinstance(f, gtsam.PriorFactorPose3) and chr(gtsam.Symbol(f.keys()[0]).chr()) == "x":
        return gtsam.PriorFactorPose3(f.keys()[0], sim.pose(f.prior()), f.noiseModel())
    if isinstance(f, gtsam.PriorFactorVector) and chr(gtsam.Symbol(f.keys()[0]).chr()) == "v":
        return gtsam.PriorFactorVector(f.keys()[0], sim.velocity(f.prior()), f.noiseModel())
    if isinstance(f, gtsam.PriorFactorVector) and chr(gtsam.Symbol(f.keys()[0]).chr()) == "p":
        return gtsam.PriorFactorVector(f.keys()[0], sim.point(f.prior()), f.noiseModel())
    return f


def apply_similarity(est: "Estimator", sim: Similarity) -> None:
    """Rebuild ``est``'s smoother with its state transformed by ``sim`` (module
    docstring); raises RuntimeError if the solver refuses (the caller keeps the old one).

    What is transformed is the smoother's linearization point, not its estimate: the
    keys iSAM2 holds fixed (``vio.backend.smoother``) stay fixed in the rebuilt smoother
    at their transformed linearization point, where their marginal factors were made,
    and its first solve lands on the transformed estimate. Transforming the estimate
    instead moved those keys' linearization by their whole step: on real MH_05 mono the
    rebuilt estimate then landed up to 0.6 m from the transformed one (scale 1.014)."""
    rescale = getattr(est.lm, "scale_depths", None)   # inverse depths kept outside Values
    if rescale is not None:
        rescale(1.0 / sim.s)
    try:
        lin = est.smoother.getLinearizationPoint()
        new, remap, _ = rebuilt(est, sim.values(lin), lambda f, lin: _factor(f, sim, lin))
    except RuntimeError:
        if rescale is not None:
            rescale(sim.s)
        raise
    install(est, new, remap)


class ScaleRefiner:
    """The history and schedule of the refinement for one ``Estimator`` (module
    docstring). ``gravity`` (3,): the IMU params' n_gravity."""

    def __init__(self, cfg: RefineConfig, gravity: np.ndarray) -> None:
        self.cfg = cfg
        self.gravity = np.asarray(gravity, float)
        self.applied = 0                  # corrections applied
        self.worker: BatchWorker | None = None   # the BA's process (RefineConfig.ba_worker)
        self.generation = -1
        self.log: list[tuple[float, Refinement]] = []   # (s after start, outcome) per attempt
        self.reset()

    def reset(self) -> None:
        """Forget the history (a (re)start: the world frame may have been re-anchored)."""
        self.t: dict[int, int] = {}
        self.T: dict[int, gtsam.Pose3] = {}
        self.v: dict[int, np.ndarray] = {}
        self.b: dict[int, gtsam.imuBias.ConstantBias] = {}
        self.obs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.pims: list[tuple[int, int, object]] = []   # (k0, k1, pim; None where bridged)
        self.t0: int | None = None
        self.next_s = self.cfg.first_s
        self.generation += 1              # jobs still in flight belong to an older one

    def keyframe(self, est: "Estimator", k0: int, k1: int, t_ns: int, pim, bridged: bool,
                 features=None) -> None:
        """Record keyframe ``k1`` (the interval from ``k0`` with ``pim``; a bridged one is
        kept as None) and its ``features`` (``FeatureFrame``), refresh the window's
        estimates, refine when due."""
        if not self.cfg.enabled or est.C_stereo is not None or est.sources:
            return
        if self.t0 is None:
            self.t0 = est.kf_t.get(k0, t_ns)
        if self.cfg.ba_worker and self.cfg.method == "viba" and self.worker is None:
            self.worker = BatchWorker()
            self.worker.start()
        if k0 in est.kf_t and k0 not in self.t:
            self.t[k0] = est.kf_t[k0]
        self.t[k1] = t_ns
        if k0 in self.t:
            self.pims.append((k0, k1, None if bridged else pim))
        if features is not None:
            self.obs[k1] = (np.asarray(features.ids, np.int64).copy(), np.asarray(features.uv, float).copy())
        for k in est.kf_t:
            if est.values.exists(X(k)):
                self.T[k], self.v[k] = est.values.atPose3(X(k)), est.values.atVector(V(k))
                self.b[k] = est.values.atConstantBias(B(k))
        self._trim(t_ns)
        self._collect(est, t_ns)
        age = (t_ns - self.t0) * 1e-9
        if age >= self.next_s and age <= self.cfg.until_s:
            self._attempt(est, age)

    def _trim(self, t_ns: int) -> None:
        keep = t_ns - int(self.cfg.history_s * 1e9)
        for k in [k for k, t in self.t.items() if t < keep]:
            self.t.pop(k)
            for d in (self.T, self.v, self.b, self.obs):
                d.pop(k, None)
        self.pims = [p for p in self.pims if p[0] in self.t]

    def _attempt(self, est: "Estimator", age: float) -> None:
        if self.cfg.method == "viba":
            self._attempt_viba(est, age)
            return
        ks = sorted(k for k in self.t if k in self.T)
        row = {k: n for n, k in enumerate(ks)}
        ivs = [interval(row[a], row[b], pim, self.gravity) for a, b, pim in self.pims
               if pim is not None and a in row and b in row]
        res = solve([self.T[k] for k in ks], np.array([self.v[k] for k in ks]), ivs,
                    est.values.atPose3(graph.EXTRINSIC), self.gravity, self.cfg)
        self.log.append((age, res))
        if not res.ok:
            log.info("scale refinement %.1f s after the start refused: %s", age, res.reason)
            self.next_s = age + self.cfg.retry_s
            return
        self.next_s = self.cfg.first_s + self.cfg.every_s * (int((age - self.cfg.first_s) / self.cfg.every_s) + 1)
        small = (abs(res.scale - 1.0) < self.cfg.min_scale_change
                 and res.gravity_change_deg < self.cfg.min_gravity_change_deg)
        log.info("scale refinement %.1f s after the start over %d intervals: scale %.4f "
                 "(sigma %.2f%%), gravity %.2f deg (sigma %.2f deg), chi2/dof %.2f%s", age,
                 res.n_intervals, res.scale, 100 * res.scale_sigma, res.gravity_change_deg,
                 res.gravity_sigma_deg, res.chi2_dof, " (too small to apply)" if small else "")
        if small:
            return
        T0 = self.T[ks[0]]
        t_bc = est.values.atPose3(graph.EXTRINSIC).translation()
        sim = Similarity(res.scale, res.R_corr, T0.translation() + T0.rotation().matrix() @ t_bc, t_bc)
        self._apply(est, sim, ks)

    def _history(self, est: "Estimator") -> History | None:
        """The recorded keyframes as a :class:`viba.History` (the longest stretch of
        consecutive keyframes with an interval between each, ending at the newest)."""
        ks = sorted(k for k in self.t if k in self.T and k in self.b)
        between = {(a, b): pim for a, b, pim in self.pims}
        run = ks[-1:]
        for k in reversed(ks[:-1]):
            if (k, run[0]) not in between:
                break
            run.insert(0, k)
        if len(run) < 2:
            return None
        empty = (np.zeros(0, np.int64), np.zeros((0, 2)))
        return History([self.t[k] for k in run], [self.T[k] for k in run],
                       np.array([self.v[k] for k in run]), [self.b[k] for k in run],
                       [between[(a, b)] for a, b in zip(run[:-1], run[1:])],
                       [self.obs.get(k, empty) for k in run],
                       np.array([k in est.kf_t for k in run]))

    def _attempt_viba(self, est: "Estimator", age: float) -> None:
        """Batch VI-BA over the history (:mod:`vio.backend.viba`), in the worker process
        (``ba_worker``: finished at the first keyframe ``ba_delay_s`` later) or here."""
        h = self._history(est)
        if h is None:
            self.next_s = age + self.cfg.retry_s
            return
        vc, ic = est.cfg.vision, est.cfg.init
        kernel = None if vc.kernel == "none" else RobustKernel(vc.kernel, vc.kernel_k)
        fx = est.cam.intrinsics[0]
        sig = np.r_[np.full(3, ic.prior_accel_bias_sigma), np.full(3, ic.prior_gyro_bias_sigma)]
        args = (h, est.values.atPose3(graph.EXTRINSIC), vc.pixel_sigma / fx, kernel,
                vc.outlier_px / fx, sig, self.cfg)
        t_ns = est.kf_t[est.k]
        if self.worker is not None:
            if self.worker.submit(t_ns + int(self.cfg.ba_delay_s * 1e9), args, (self.generation, age)):
                self.next_s = float("inf")     # one job at a time; its result sets the next
                return
        t0 = time.perf_counter()
        res = viba.solve(*args)
        self._finish_viba(est, age, res, time.perf_counter() - t0)

    def _collect(self, est: "Estimator", t_ns: int) -> None:
        """Finish the worker's jobs due at keyframe time ``t_ns`` (those submitted before a
        reset are dropped: their world may have been re-anchored)."""
        if self.worker is None or not self.worker.pending():
            return
        for (gen, age), (res, dt) in self.worker.due(t_ns):
            if gen == self.generation:
                self._finish_viba(est, age, res, dt)
        if not self.worker.pending() and self.next_s == float("inf"):   # its result was dropped
            self.next_s = (t_ns - self.t0) * 1e-9

    def _finish_viba(self, est: "Estimator", age: float, res: viba.VibaResult, dt: float) -> None:
        """Log the batch of the attempt at ``age`` (s after the start), schedule the next
        one and, when its scale is well determined and significant, apply it."""
        self.log.append((age, res))
        if not res.ok:
            log.info("visual-inertial BA %.1f s after the start refused: %s", age, res.reason)
            self.next_s = age + self.cfg.retry_s
            return
        self.next_s = self.cfg.first_s + self.cfg.every_s * (int((age - self.cfg.first_s) / self.cfg.every_s) + 1)
        log.info("visual-inertial BA %.1f s after the start over %d keyframes, %d tracks: scale %.4f "
                 "(sigma %.2f%%), gravity %.2f deg (%.1f s)", age, res.n_keyframes, res.n_tracks, res.scale,
                 100 * res.scale_sigma, res.gravity_change_deg, dt)
        if (abs(res.scale - 1.0) < self.cfg.min_scale_change
                and (res.gravity_change_deg < self.cfg.min_gravity_change_deg or not self.cfg.ba_apply_tilt)):
            return
        if abs(np.log(res.scale)) < self.cfg.ba_min_significance * res.scale_sigma:
            log.info("visual-inertial BA scale within %.1f sigma of the smoother's: not applied",
                     self.cfg.ba_min_significance)
            return
        if self.cfg.ba_apply == "prior":
            self._velocity_prior(est, res)
            return
        R = res.R_corr if self.cfg.ba_apply_tilt else gtsam.Rot3()
        sim = Similarity(res.scale, R, res.pivot, est.values.atPose3(graph.EXTRINSIC).translation())
        self._apply(est, sim, list(self.T))

    def _apply(self, est: "Estimator", sim: Similarity, ks: list) -> None:
        try:
            apply_similarity(est, sim)
        except RuntimeError as exc:
            log.error("scale refinement not applied: the rebuilt smoother failed (%s)",
                      one_line(exc))
            return
        self.applied += 1
        est.health.reset(est.kf_t[est.k], est.latest()[2])   # its fallback states are in the old world
        for k in ks:
            self.T[k], self.v[k] = sim.pose(self.T[k]), sim.velocity(self.v[k])

    def _velocity_prior(self, est: "Estimator", res) -> None:
        """The batch's scale as a prior on the newest keyframe's velocity: ``s v`` with an
        isotropic sigma of ``|v|`` times the batch's relative scale sigma (at least
        ``ba_min_sigma``); the smoother moves its scale with its own factors, without a
        rebuild."""
        v = est.values.atVector(V(est.k))
        sd = max(res.scale_sigma, self.cfg.ba_min_sigma) * max(float(np.linalg.norm(v)), 0.05)
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.PriorFactorVector(V(est.k), res.scale * v, gtsam.noiseModel.Isotropic.Sigma(3, sd)))
        try:
            est._update(g, gtsam.Values(), {}, [])
        except RuntimeError as exc:
            log.error("scale prior not applied: the smoother refused it (%s)", one_line(exc))
            return
        self.applied += 1
