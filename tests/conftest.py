"""Shared test helpers: the real EuRoC data in ../shared/data (skipped when absent) and a
batch solution of the backend graph to compare fixed-lag estimates with."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared(*parts: str) -> Path:
    """Path inside ../shared/data, or skip the test with the reason when absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real EuRoC data not available at {path} (../shared is absent)")
    return path


def batch_solution(cfg, data, n: int, t_ns: int):
    """Run the full smoother, then LM over all its live factors from its estimate; the
    keyframe pose at ``t_ns`` after LM and in the smoother."""
    import gtsam

    from vio.backend import graph
    from vio.pipeline import Pipeline
    from vio.run import td_feedback
    from vio.sync import packets
    pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg)
    # the sync layer's td feedback as run_dataset has it, so that the keyframe times match
    for pkt in packets(data.imu, data.cam0.t_ns[:n], cfg.td_s, data.features[:n],
                       td_source=td_feedback(pipe, cfg)):
        pipe.process(pkt)
    est = pipe.est
    fg = est.smoother.getFactors()
    g = gtsam.NonlinearFactorGraph()
    for i in range(fg.size()):
        f = fg.at(i)
        if f is not None:
            g.add(f)
    values = est.smoother.calculateEstimate()
    opt = gtsam.LevenbergMarquardtOptimizer(g, values, gtsam.LevenbergMarquardtParams())
    sol = opt.optimize()
    k = next(f for f, t in est.kf_t.items() if t == t_ns)
    return sol.atPose3(graph.X(k)), values.atPose3(graph.X(k))


@pytest.fixture(scope="session")
def sim_tracks_exact(tmp_path_factory):
    """Noise-free IMU and tracks (8 s, moving start): any estimator disagreement is
    bookkeeping, not noise."""
    from vio.io.euroc import load_euroc
    from vio.sim import simulate
    from vio.sim.config import SimConfig
    from vio.sim.tracks import TrackGenConfig, generate_tracks
    root = tmp_path_factory.mktemp("sim_exact")
    simulate(root / "raw", SimConfig(seconds=8.0, seed=5, stereo=False, render_images=False,
                                     imu_noise=False))
    generate_tracks(root / "raw", root / "trk", TrackGenConfig(td_s=0.005, seed=2, noise_px=0.0,
                                                               outlier_rate=0.0))
    return load_euroc(root / "trk")
