"""Where the monocular scale information goes (issue 16). At one moment of a generated
mid-flight excerpt (``bench_midflight.py``'s sets), the relative standard deviation of the
translation between the keyframes at both ends of the last ``--span`` seconds, from

- ``smoother``: the fixed-lag smoother's own graph (its marginal factors included);
- ``all factors``: every factor the smoother was given, minus those it was told to remove,
  as one graph without marginalization (the same factors, none linearized early), at the
  smoother's estimates and at that graph's own optimum;
- ``batch``: the visual-inertial BA of :mod:`vio.backend.viba` over the keyframe history
  (every recorded observation of tracks seen 3 times, no td, no anchor-noise whitening);

and the scale of the ``all factors`` optimum and of the batch relative to the smoother's
keyframe positions (least squares over the history).

    python benchmarks/scale_information.py MH_04_difficult@40 [--at 15] [--span 2.45]
                                           [--config FILE] [--noise-px 0.7]

Measured (b32d31c, MH_04@40 at 15 s, where the smoother's trajectory is ~2% short):
smoother 1.51%, all factors 1.38% (1.33% at their optimum, whose scale is 1.0006 of the
smoother's), batch 0.62%; with ``backend: {solver: {lag_s: 40}}`` (nothing marginalized,
no re-anchoring) smoother 1.08%, all factors 1.07%; with ``backend: {vision:
{anchor_noise: false}}`` smoother 1.17%, all factors 1.20%. So marginalization loses
nothing and the smoother sits at the optimum of its own factors: the scale information is
lost in how the 2.5-s window turns observations into factors (the same observations hold
1.4x less than without re-anchoring, 2.2x less than in the batch), not in marginalization.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import gtsam
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from bench_midflight import _dataset  # noqa: E402
from factors.robust import RobustKernel  # noqa: E402
from vio.backend import graph, viba  # noqa: E402
from vio.backend.estimator import Estimator  # noqa: E402
from vio.io.euroc import load_euroc  # noqa: E402
from vio.pipeline import Pipeline  # noqa: E402
from vio.run import default_config, load_config  # noqa: E402
from vio.sim.tracks import TrackGenConfig  # noqa: E402
from vio.sync import packets  # noqa: E402


class Recorder:
    """Wraps each smoother the estimator creates: keeps every factor it is given (by slot,
    dropped when the estimator removes that slot) and the latest estimate of every key."""

    def __init__(self) -> None:
        self.factors: dict[int, object] = {}
        self.slot: dict[int, int] = {}
        self.values = gtsam.Values()

    def wrap(self, smoother):
        rec = self

        class Wrapped:
            def __getattr__(self, name):
                return getattr(smoother, name)

            def update(self, g=None, v=None, stamps=None, removals=None):
                if g is None:
                    return smoother.update()
                for r in removals or []:
                    rec.factors.pop(rec.slot.pop(int(r), -1), None)
                out = smoother.update(g, v, stamps, removals or [])
                for j, i in enumerate(smoother.getISAM2Result().getNewFactorsIndices()):
                    f = g.at(j)     # one wrapper object per factor: its id is the record's key
                    rec.slot[int(i)] = id(f)
                    rec.factors[id(f)] = f
                rec.merge(smoother.calculateEstimate())
                return out

        return Wrapped()

    def merge(self, new: gtsam.Values) -> None:
        keep = gtsam.Values()
        for key in list(self.values.keys()):
            if not new.exists(key):
                _copy(self.values, keep, key)
        keep.insert(new)
        self.values = keep

    def graph(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """All recorded factors, a weak prior (1 1/m) on each inverse depth (keys whose
        factors were all removed), and the latest estimate of their keys."""
        g, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for f in self.factors.values():
            g.add(f)
        for key in list(g.keys()):
            _copy(self.values, vals, key)
            if chr(gtsam.Symbol(key).chr()) == "l":
                g.add(gtsam.PriorFactorVector(key, vals.atVector(key), gtsam.noiseModel.Isotropic.Sigma(1, 1.0)))
        return g, vals


def _copy(src: gtsam.Values, dst: gtsam.Values, key: int) -> None:
    ch = chr(gtsam.Symbol(key).chr())
    if ch in "xe":
        dst.insert(key, src.atPose3(key))
    elif ch == "b":
        dst.insert(key, src.atConstantBias(key))
    else:
        dst.insert(key, src.atVector(key))


def rel_sigma(g: gtsam.NonlinearFactorGraph, vals: gtsam.Values, ka: int, kb: int) -> float:
    """Relative standard deviation of ``|p_b - p_a|`` (dense information matrix, pseudo-inverse:
    GTSAM's Cholesky marginals refuse some of these graphs)."""
    lin = g.linearize(vals)
    keys = lin.keys()       # held: iterating the temporary KeySet crashes
    order = gtsam.Ordering()
    for k in [k for k in list(keys) if k not in (ka, kb)] + [ka, kb]:
        order.push_back(k)
    H, _ = lin.hessian(order)
    C = np.linalg.pinv(H, rcond=1e-12, hermitian=True)[-12:, -12:]
    Ta, Tb = vals.atPose3(ka), vals.atPose3(kb)
    d = Tb.translation() - Ta.translation()
    u = d / np.linalg.norm(d)
    J = np.zeros(12)
    J[3:6], J[9:12] = -u @ Ta.rotation().matrix(), u @ Tb.rotation().matrix()
    return float(np.sqrt(J @ C @ J)) / float(np.linalg.norm(d))


def scale_of(ref: list[np.ndarray], other: list[np.ndarray]) -> float:
    """Least-squares scale of the centred positions ``other`` against ``ref``."""
    A, B = np.array(ref), np.array(other)
    A, B = A - A.mean(0), B - B.mean(0)
    return float(np.sum(A * B) / np.sum(A * A))


def run_until(data, cfg, at_s: float, rec: Recorder) -> Estimator:
    """The features pipeline until the first keyframe ``at_s`` after the history's start."""
    orig = Estimator._new_smoother
    Estimator._new_smoother = lambda self: rec.wrap(orig(self))
    try:
        pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg)
        for pkt in packets(data.imu, data.cam0.t_ns, cfg.td_s, data.features):
            pipe.process(pkt)
            est = pipe.est
            t0 = est.refiner.t0 if est is not None else None
            if t0 is not None and (est.kf_t[est.k] - t0) * 1e-9 >= at_s:
                return est
    finally:
        Estimator._new_smoother = orig
    raise SystemExit(f"the excerpt ends before {at_s} s after the start")


def batch(est: Estimator) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, viba.History]:
    h = est.refiner._history(est)
    vc, ic = est.cfg.vision, est.cfg.init
    fx = est.cam.intrinsics[0]
    sig = np.r_[np.full(3, ic.prior_accel_bias_sigma), np.full(3, ic.prior_gyro_bias_sigma)]
    g, vals, _ = viba.build(h, est.values.atPose3(graph.EXTRINSIC), vc.pixel_sigma / fx,
                            RobustKernel(vc.kernel, vc.kernel_k), sig, 3, 400, (0.2, 60.0))
    return g, viba._optimize(g, vals, 10), h


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="SEQUENCE@START, e.g. MH_04_difficult@40")
    ap.add_argument("--at", type=float, default=15.0)
    ap.add_argument("--span", type=float, default=2.45)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--noise-px", type=float, default=TrackGenConfig.noise_px)
    a = ap.parse_args()
    cfg = load_config(a.config, mode="features") if a.config else default_config("features")
    ref = dataclasses.replace(cfg.backend.refine, enabled=True, first_s=1e9)   # history only
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, refine=ref))
    seq, start = a.run.split("@")
    data = load_euroc(_dataset(seq, float(start), a.at + 2.0, 1, a.noise_px))
    rec = Recorder()
    est = run_until(data, cfg, a.at, rec)
    t_new = est.kf_t[est.k]
    ks = sorted(k for k in est.kf_t if est.values.exists(graph.X(k)) and t_new - est.kf_t[k] < a.span * 1e9)
    ka, kb = graph.X(ks[0]), graph.X(ks[-1])
    fg = est.smoother.getFactors()
    g = gtsam.NonlinearFactorGraph()
    for j in range(fg.size()):
        if fg.at(j) is not None:
            g.add(fg.at(j))
    print(f"at {a.at:g} s, keyframes {ks[0]}-{ks[-1]} ({(t_new - est.kf_t[ks[0]]) * 1e-9:.2f} s):")
    print(f"  smoother     relative sigma {100 * rel_sigma(g, est.values, ka, kb):.2f}%")
    ga, va = rec.graph()
    opt = viba._optimize(ga, va, 10)
    hist = [k for k in sorted(rec.values.keys()) if chr(gtsam.Symbol(k).chr()) == "x" and opt.exists(k)]
    s_all = scale_of([va.atPose3(k).translation() for k in hist], [opt.atPose3(k).translation() for k in hist])
    print(f"  all factors  relative sigma {100 * rel_sigma(ga, va, ka, kb):.2f}% at the smoother's "
          f"estimates, {100 * rel_sigma(ga, opt, ka, kb):.2f}% at their optimum ({ga.size()} factors; "
          f"optimum's scale {s_all:.4f} of the smoother's)")
    gb, eb, h = batch(est)
    ia, ib = h.t_ns.index(est.kf_t[ks[0]]), h.t_ns.index(est.kf_t[ks[-1]])
    s_b = scale_of([T.translation() for T in h.T_w_b], [eb.atPose3(viba.X(i)).translation() for i in range(len(h.t_ns))])
    print(f"  batch        relative sigma {100 * rel_sigma(gb, eb, viba.X(ia), viba.X(ib)):.2f}% "
          f"({len(h.t_ns)} keyframes; its scale {s_b:.4f} of the smoother's)")


if __name__ == "__main__":
    main()
