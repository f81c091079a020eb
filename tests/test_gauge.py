"""The window's gauge prior (``vio.backend.gauge``): what it holds and where it sits."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from vio.backend import graph
from vio.backend.config import BackendConfig, SolverConfig
from vio.backend.gauge import GaugeConfig, gauge_prior
from vio.backend.init import gravity_aligned_rotation
from vio.evaluation import evaluate
from vio.pipeline import Pipeline, PipelineConfig
from vio.run import RunResult
from vio.sync import packets


def _error(f, T: gtsam.Pose3) -> float:
    v = gtsam.Values()
    v.insert(graph.X(3), T)
    return f.error(v)


def test_gauge_prior_holds_position_and_world_yaw_only():
    """EuRoC's IMU x axis points up: the prior must act on the rotation about world z
    and on the position, and leave the rotations about world x / y (gravity's) free."""
    cfg = GaugeConfig()
    R = gravity_aligned_rotation(np.array([9.8, 0.3, -0.5])).compose(gtsam.Rot3.Yaw(0.7))
    T = gtsam.Pose3(R, np.array([1.0, -2.0, 0.5]))
    f = gauge_prior(graph.X(3), T, cfg)
    assert _error(f, T) == pytest.approx(0.0, abs=1e-12)
    d = 1e-4
    for axis in range(3):
        w = np.zeros(3)
        w[axis] = d                                               # world-frame rotation
        e = _error(f, gtsam.Pose3(gtsam.Rot3.Expmap(w).compose(R), T.translation()))
        expect = 0.5 * (d / (cfg.yaw_rad if axis == 2 else cfg.free_rad)) ** 2
        assert e == pytest.approx(expect, rel=1e-3, abs=1e-12)
        dp = np.zeros(3)
        dp[axis] = d                                              # world-frame position
        e = _error(f, gtsam.Pose3(R, T.translation() + dp))
        assert e == pytest.approx(0.5 * (d / cfg.position_m) ** 2, rel=1e-6)


def _pose_priors(est) -> list[tuple[int, gtsam.PriorFactorPose3]]:
    fg = est.smoother.getFactors()
    out = []
    for j in range(fg.size()):
        f = fg.at(j)
        if isinstance(f, gtsam.PriorFactorPose3) and chr(gtsam.Symbol(f.keys()[0]).chr()) == "x":
            out.append((j, f))
    return out


@pytest.mark.slow
def test_gauge_anchor_follows_the_oldest_window_keyframe(sim_tracks_exact):
    """Past the first lag the smoother holds exactly one pose prior, the gauge's, on the
    oldest window keyframe (the previous one removed before its keyframe is
    marginalized); the estimate stays on the truth (exact data)."""
    d = sim_tracks_exact
    cfg = PipelineConfig(backend=BackendConfig(solver=SolverConfig(lag_s=1.5)))
    pipe = Pipeline(d.imu_calib, d.cam0.calib, cfg)
    checked, outs = 0, []
    for pkt in packets(d.imu, d.cam0.t_ns, cfg.td_s, d.features):
        outs += pipe.process(pkt)
        est = pipe.est
        if not est.initialized or est.gauge.moves == 0:
            continue
        priors = _pose_priors(est)
        assert [j for j, _ in priors] == [est.gauge.slot]
        assert priors[0][1].keys()[0] == graph.X(est.gauge.k) and est.gauge.k == min(est.kf_t)
        checked += 1
    assert est.gauge.moves >= 10 and checked >= 50
    ate = evaluate(*RunResult(outputs=outs).arrays(), d.groundtruth).ate_rmse
    print(f"ATE {ate:.4f} m")      # measured 0.9 mm
    assert ate < 0.02, ate
