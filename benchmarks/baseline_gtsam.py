"""A GTSAM-native VIO baseline fed with our pipeline's keyframe decisions.

Built only from GTSAM's C++ factors: ``CombinedImuFactor`` between keyframes,
``GenericProjectionFactorCal3_S2`` (Huber, pixel units, ``body_P_sensor = T_b_c``)
from each keyframe to a triangulated ``Point3`` landmark, ``PriorFactor``s for the
first state and zero-velocity updates, all inside ``gtsam.IncrementalFixedLagSmoother``
with the same lag, factorization (Cholesky, re-solved with QR when it refuses, as ours)
and relinearization settings as ours.

Fairness: the keyframes (and their still flags), the initial state, the IMU noise
(``vio.imu.combined_params``), the midpoint preintegration (``vio.imu.integrate``)
and the sync layer's constant td are those of our pipeline on the same data
(``record_schedule`` runs it and records them; ``Schedule`` round-trips to JSON so
a separate process can replay them). The extrinsic is fixed and td is not
estimated (GTSAM has no td factor).

Landmarks: a track is triangulated (``gtsam.triangulatePoint3``) once two window
keyframes see it with enough parallax and a positive depth; then it gets one
projection factor per window keyframe and its timestamp follows its newest
observation, so the smoother marginalizes it with its last observer. New
observations are gated against the IMU-predicted pose; after each update,
landmarks with a reprojection error above ``outlier_px`` lose their in-window
factors (a weak prior keeps the key determined until it is marginalized).

    python benchmarks/baseline_gtsam.py DATASET [--max-frames N] [--schedule S.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vio.backend import graph, smoother  # noqa: E402
from vio.backend.init import InitialState  # noqa: E402
from vio.imu import combined_params, integrate  # noqa: E402
from vio.io.euroc import EurocDataset, load_euroc  # noqa: E402
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib  # noqa: E402
from vio.pipeline import FrameOutput, PipelineConfig  # noqa: E402
from vio.run import RunResult  # noqa: E402
from vio.sync import FramePacket, packets  # noqa: E402

from schedule import Schedule, _capture_init, record_schedule  # noqa: E402,F401 (re-exported)

log = logging.getLogger(__name__)
X, V, B, L = graph.X, graph.V, graph.B, gtsam.symbol_shorthand.L
WEAK_POINT = gtsam.noiseModel.Isotropic.Sigma(3, 10.0)


@dataclass(frozen=True)
class BaselineConfig:
    """Baseline-only knobs; parallax, depth range, outlier threshold, waiting time and
    default depth come from our ``VisionConfig``. ``gate_px``: new observations of a
    landmark farther than this from its projection in the IMU-predicted pose are
    skipped; ``depth_prior_sigma_m``: weak prior on low-parallax landmarks;
    ``zupt``: zero-velocity factors on our still keyframes."""

    gate_px: float = 10.0
    depth_prior_sigma_m: float = 20.0
    zupt: bool = True


@dataclass
class _Landmark:
    """A track: pixel observations by keyframe, its Point3 key once triangulated and
    the smoother factor index of each keyframe's projection factor."""

    obs: dict[int, np.ndarray] = field(default_factory=dict)
    key: int | None = None
    factors: dict[int, int] = field(default_factory=dict)
    last_t: float = 0.0
    waited: int = 0


class BaselineVIO:
    """GTSAM-native fixed-lag VIO; ``initialize`` then ``step`` every packet."""

    def __init__(self, imu_calib: ImuCalib, cam: CameraCalib, cfg: PipelineConfig,
                 bcfg: BaselineConfig = BaselineConfig()) -> None:
        self.cfg, self.bcfg, self.cam = cfg, bcfg, cam
        self.vc = v = cfg.backend.vision
        self.K = gtsam.Cal3_S2(*cam.intrinsics[:2], 0.0, *cam.intrinsics[2:])
        base = gtsam.noiseModel.Isotropic.Sigma(2, v.pixel_sigma)
        self.noise = (base if v.kernel == "none" else gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(v.kernel_k), base))
        self.params = combined_params(imu_calib, cfg.backend.imu)
        self.smoother: gtsam.IncrementalFixedLagSmoother | None = None
        self.values = gtsam.Values()
        self.lms: dict[int, _Landmark] = {}
        self.rejected: set[int] = set()
        self.kf_t: dict[int, float] = {}
        self.k = -1
        self._next_key = 0
        self.recoveries = 0
        self.n_gated = 0
        self.pim = None
        self.smoother_factorization = self.home_factorization   # QR after a re-solve, as ours
        self.qr_since: float | None = None    # in kf_t's unit (s)
        self.qr_resolves = 0

    # ----------------------------------------------------------------- setup
    @property
    def home_factorization(self) -> str:
        return self.cfg.backend.solver.factorization

    def remap_factor_indices(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild (``vio.backend.smoother``, as ours)."""
        for lm in self.lms.values():
            lm.factors = {k: remap[i] for k, i in lm.factors.items() if i in remap}

    def _new_smoother(self, factorization: str | None = None) -> gtsam.IncrementalFixedLagSmoother:
        s = self.cfg.backend.solver
        p = gtsam.ISAM2Params()
        p.setFactorization(factorization or s.factorization)
        p.setRelinearizeThreshold(s.relinearize_threshold)
        p.relinearizeSkip = s.relinearize_skip
        return gtsam.IncrementalFixedLagSmoother(s.lag_s, p)

    def initialize(self, state: InitialState, k: int = 0, pose_sigmas: np.ndarray | None = None) -> None:
        """Start (or restart) the window at ``state`` as keyframe ``k``."""
        self.smoother = self._new_smoother()
        self.smoother_factorization, self.qr_since = self.home_factorization, None
        self.k = k
        t = state.t_ns * 1e-9
        self.kf_t = {k: t}
        g = graph.state_priors(k, state, self.cfg.backend.init, pose_sigmas)
        v = gtsam.Values()
        v.insert(X(k), state.T_w_b)
        v.insert(V(k), state.v_w)
        v.insert(B(k), state.bias)
        self.smoother.update(g, v, {X(k): t, V(k): t, B(k): t})
        self.values = self.smoother.calculateEstimate()
        self.pim = gtsam.PreintegratedCombinedMeasurements(self.params, state.bias)

    def latest(self) -> tuple[gtsam.Pose3, np.ndarray, gtsam.imuBias.ConstantBias]:
        return (self.values.atPose3(X(self.k)), self.values.atVector(V(self.k)),
                self.values.atConstantBias(B(self.k)))

    def predict(self) -> gtsam.NavState:
        T, v, b = self.latest()
        return self.pim.predict(gtsam.NavState(T, v), b)

    def observe(self, k: int, fr: FeatureFrame | None) -> None:
        """Record a keyframe's observations (pixels) without adding factors."""
        if fr is None:
            return
        px = self._pixels(fr)
        for lid, p in zip(fr.ids.tolist(), px):
            if lid not in self.rejected:
                self.lms.setdefault(lid, _Landmark()).obs[k] = p

    def _pixels(self, fr: FeatureFrame) -> np.ndarray:
        fx, fy, cx, cy = self.cam.intrinsics
        return np.column_stack([fx * fr.uv[:, 0] + cx, fy * fr.uv[:, 1] + cy])

    # ------------------------------------------------------------ keyframes
    def add_keyframe(self, t_ns: int, fr: FeatureFrame | None, still: bool) -> None:
        """Insert keyframe ``k+1`` with the IMU preintegrated since keyframe ``k``."""
        smoother.maybe_back_to_cholesky(self)
        k0, k1, t = self.k, self.k + 1, t_ns * 1e-9
        pred = self.predict()
        b0 = self.latest()[2]
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        g.add(graph.imu_factor(k0, k1, self.pim))
        if still and self.bcfg.zupt:
            g.add(graph.zero_velocity(k1, self.cfg.backend.init.zupt_sigma))
        v.insert(X(k1), pred.pose())
        v.insert(V(k1), pred.velocity())
        v.insert(B(k1), b0)
        stamps = {X(k1): t, V(k1): t, B(k1): t}
        lag = self.cfg.backend.solver.lag_s
        leaving = {k for k, tk in self.kf_t.items() if t - tk >= lag - 1e-9}
        self.k = k1
        self.kf_t[k1] = t
        pending = self._vision(k1, t, fr, pred.pose(), leaving, g, v, stamps)
        try:
            self._update(g, v, stamps, [], pending)
            for kk in leaving:
                self.kf_t.pop(kk, None)
            self._remove_outliers()
        except RuntimeError as exc:
            self._recover(exc, pred, b0, t_ns, fr)
        self.pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.latest()[2])

    def _vision(self, k1: int, t: float, fr: FeatureFrame | None, pose: gtsam.Pose3,
                leaving: set[int], g, v, stamps) -> list[tuple[_Landmark, int, int]]:
        """Projection factors of this keyframe; returns (landmark, keyframe, position in g)."""
        pending: list[tuple[_Landmark, int, int]] = []
        seen = set()
        if fr is not None:
            for lid, px in zip(fr.ids.tolist(), self._pixels(fr)):
                if lid in self.rejected:
                    continue
                seen.add(lid)
                lm = self.lms.setdefault(lid, _Landmark())
                if lm.key is not None:
                    if self._reproj(pose, self.values.atPoint3(lm.key), px) > self.bcfg.gate_px:
                        self.n_gated += 1
                        continue
                    lm.obs[k1] = px
                    self._add_factor(lm, k1, g, pending)
                    lm.last_t = stamps[lm.key] = t
                    continue
                lm.obs = {kk: o for kk, o in lm.obs.items() if kk not in leaving}
                lm.obs[k1] = px
                self._try_triangulate(lm, k1, pose, g, v, stamps, pending, t)
        lag = self.cfg.backend.solver.lag_s
        for lid in list(self.lms):
            lm = self.lms[lid]
            if lid not in seen:
                lm.obs = {kk: o for kk, o in lm.obs.items() if kk not in leaving}
            if (lm.key is None and not lm.obs) or (lm.key is not None and t - lm.last_t >= lag - 1e-9):
                del self.lms[lid]     # never triangulated, or marginalized with its last observer
        return pending

    def _reproj(self, T_w_b: gtsam.Pose3, p_w: np.ndarray, px: np.ndarray) -> float:
        p_c = T_w_b.compose(self.cam.T_b_c).transformTo(p_w)
        if p_c[2] <= self.vc.min_depth_m:
            return np.inf
        fx, fy, cx, cy = self.cam.intrinsics
        return float(np.hypot(fx * p_c[0] / p_c[2] + cx - px[0], fy * p_c[1] / p_c[2] + cy - px[1]))

    def _add_factor(self, lm: _Landmark, k: int, g, pending) -> None:
        pending.append((lm, k, int(g.size())))
        g.add(gtsam.GenericProjectionFactorCal3_S2(lm.obs[k], self.noise, X(k), lm.key, self.K,
                                                   self.cam.T_b_c))

    def _try_triangulate(self, lm: _Landmark, k1: int, pose: gtsam.Pose3, g, v, stamps,
                         pending, t: float) -> None:
        """Insert the landmark once triangulable; a low-parallax track that waited
        ``max_wait_keyframes`` (ours' setting) enters at ``default_depth_m`` with a weak
        ``PriorFactorPoint3`` (the projections alone leave its depth unobservable)."""
        frames = sorted(lm.obs)
        if len(frames) < 2:
            return
        bodies = [pose if f == k1 else self.values.atPose3(X(f)) for f in frames]
        cams = [T.compose(self.cam.T_b_c) for T in bodies]
        p, prior, vc = self._triangulate(lm, frames, cams), None, self.vc
        if p is None:
            lm.waited += 1
            if lm.waited < vc.max_wait_keyframes or self._parallax(lm, frames, cams) >= vc.min_parallax_deg:
                return
            m = np.array([*self.K.calibrate(lm.obs[frames[0]]), 1.0])
            p = cams[0].transformFrom(m / m[2] * vc.default_depth_m)
            prior = gtsam.PriorFactorPoint3(L(self._next_key + 1), p, gtsam.noiseModel.Isotropic.Sigma(
                3, self.bcfg.depth_prior_sigma_m))
        if max(self._reproj(T, p, lm.obs[f]) for T, f in zip(bodies, frames)) > vc.outlier_px:
            return
        self._next_key += 1
        lm.key = L(self._next_key)
        v.insert(lm.key, p)
        if prior is not None:
            g.add(prior)
        for f in frames:
            self._add_factor(lm, f, g, pending)
        lm.last_t = stamps[lm.key] = t

    def _parallax(self, lm: _Landmark, frames: list[int], cams: list[gtsam.Pose3]) -> float:
        """Largest angle (deg) between the first ray and the others, in the world."""
        rays = [c.rotation().matrix() @ np.array([*self.K.calibrate(lm.obs[f]), 1.0])
                for c, f in zip(cams, frames)]
        r0 = rays[0] / np.linalg.norm(rays[0])
        cosang = min(float(r @ r0 / np.linalg.norm(r)) for r in rays[1:])
        return float(np.degrees(np.arccos(np.clip(cosang, -1, 1))))

    def _triangulate(self, lm: _Landmark, frames: list[int], cams: list[gtsam.Pose3]) -> np.ndarray | None:
        """``gtsam.triangulatePoint3`` (DLT + refinement) with parallax and depth checks."""
        b = self.vc
        if self._parallax(lm, frames, cams) < b.min_parallax_deg:
            return None
        try:
            p = gtsam.triangulatePoint3(cams, self.K, [lm.obs[f] for f in frames], 1e-9, True)
        except RuntimeError:
            return None
        depths = [c.transformTo(p)[2] for c in cams]
        return p if b.min_depth_m <= min(depths) and max(depths) <= b.max_depth_m else None

    def _update(self, g, v, stamps, removals, pending) -> None:
        try:
            self.smoother.update(g, v, stamps, removals)
            idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
        except RuntimeError as exc:   # a Cholesky refusal is re-solved with QR, as ours
            idx = smoother.qr_resolve(self, g, exc)
        for lm, k, pos in pending:
            lm.factors[k] = int(idx[pos])
        self.values = self.smoother.calculateEstimate()

    def _remove_outliers(self) -> None:
        """Drop landmarks whose in-window reprojection error exceeds ``outlier_px``."""
        g, stamps, removals = gtsam.NonlinearFactorGraph(), {}, []
        for lid in list(self.lms):
            lm = self.lms[lid]
            if lm.key is None or not self.values.exists(lm.key):
                continue
            p = self.values.atPoint3(lm.key)
            live = [f for f in lm.factors if f in self.kf_t and self.values.exists(X(f))]
            errs = [self._reproj(self.values.atPose3(X(f)), p, lm.obs[f]) for f in live]
            if errs and max(errs) > self.vc.outlier_px:
                removals += [lm.factors[f] for f in live]
                g.add(gtsam.PriorFactorPoint3(lm.key, p, WEAK_POINT))
                stamps[lm.key] = 0.0
                self.rejected.add(lid)
                del self.lms[lid]
        if removals:
            self._update(g, gtsam.Values(), stamps, removals, [])

    def _recover(self, exc: Exception, pred: gtsam.NavState, b0, t_ns: int,
                 fr: FeatureFrame | None) -> None:
        """Restart the window from the IMU prediction after a solver failure (as ours)."""
        self.recoveries += 1
        log.error("baseline solver failure at keyframe %d (%s): restarting", self.k,
                  str(exc).splitlines()[0][:120])
        state = InitialState(t_ns, pred.pose(), pred.velocity(), b0, "recovery")
        self.lms = {}
        self.initialize(state, self.k, np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05]))
        self.observe(self.k, fr)

    def n_landmarks(self) -> int:
        return sum(1 for lm in self.lms.values() if lm.key is not None)


def run_baseline(data: EurocDataset, sched: Schedule, cfg: PipelineConfig,
                 bcfg: BaselineConfig = BaselineConfig(), max_frames: int | None = None) -> RunResult:
    """Replay ``sched`` over ``data``'s feature tracks with the baseline."""
    vio = BaselineVIO(data.imu_calib, data.cam0.calib, cfg, bcfg)
    return replay(vio, data, sched, data.features, max_frames)


def replay(vio: BaselineVIO, data: EurocDataset, sched: Schedule, frames: list,
           max_frames: int | None = None) -> RunResult:
    """Feed ``vio`` the packets of ``data`` with the observations ``frames`` (aligned
    with ``data.cam0.t_ns``) on our schedule; the online estimate at every camera
    frame from the initial keyframe on (IMU prediction between keyframes)."""
    res = RunResult()
    stamps = data.cam0.t_ns[:max_frames] if max_frames else data.cam0.t_ns
    t_start = time.perf_counter()
    for pkt in packets(data.imu, stamps, sched.td_s, frames[:len(stamps)]):
        res.frames_in += 1
        t0 = time.perf_counter()
        if vio.smoother is None:
            if pkt.t_ns != sched.init.t_ns:
                continue
            vio.initialize(sched.init)
            vio.observe(0, pkt.features)
            res.keyframes = 1
            res.outputs.append(_output(vio, pkt, True, True, t0))
            res.n_init = 1
            continue
        integrate(vio.pim, pkt.imu)
        still = sched.keyframe_at(pkt.t_ns)
        if still is not None:
            vio.add_keyframe(pkt.t_ns, pkt.features, still)
            res.keyframes += 1
        res.outputs.append(_output(vio, pkt, still is not None, bool(still), t0))
    res.wall_s = time.perf_counter() - t_start
    res.data_s = (stamps[-1] - stamps[0]) * 1e-9 if len(stamps) > 1 else 0.0
    res.recoveries = vio.recoveries
    return res


def _output(vio: BaselineVIO, pkt: FramePacket, kf: bool, still: bool, t0: float) -> FrameOutput:
    if kf:
        T, v, b = vio.latest()
    else:
        nav = vio.predict()
        T, v, b = nav.pose(), nav.velocity(), vio.latest()[2]
    n = 0 if pkt.features is None else len(pkt.features.ids)
    return FrameOutput(pkt.index, pkt.t_ns, T, np.asarray(v), b, kf, still,
                       time.perf_counter() - t0, n, vio.n_landmarks(), vio.cfg.td_s, vio.cam.T_b_c)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="EuRoC feature-track folder")
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--schedule", type=Path, help="schedule JSON (default: run our pipeline first)")
    args = ap.parse_args(argv)
    from vio.run_summary import summary
    data, cfg = load_euroc(args.dataset), PipelineConfig()
    if args.schedule:
        sched = Schedule.from_json(json.loads(args.schedule.read_text()))
    else:
        ours, sched = record_schedule(data, cfg, args.max_frames)
        print("ours:\n  " + "\n  ".join(summary(ours, data)))
    res = run_baseline(data, sched, cfg, max_frames=args.max_frames)
    print("GTSAM-native baseline:\n  " + "\n  ".join(summary(res, data)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
