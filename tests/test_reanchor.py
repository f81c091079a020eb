"""Re-anchoring keeps a landmark's information: the depth-transfer factor is zero between
consistent keys, and the fixed-lag estimate on long tracks matches a batch solution
(``tests/test_backend.py::test_fixed_lag_matches_full_batch``)."""

from __future__ import annotations

import numpy as np
import pytest

from cases_projection import random_pose
from conftest import batch_solution
from vio.backend.config import BackendConfig, CalibConfig, SolverConfig, VisionConfig
from vio.io.euroc import load_euroc
from vio.pipeline import PipelineConfig
from vio.run import run_dataset
from factors.reanchor import depth_transfer_residual
from factors.td_projection import shift_uv


def test_transfer_residual_vanishes_between_consistent_keys():
    rng = np.random.default_rng(3)
    Tc, Ta = random_pose(rng, 0.3, 0.1), random_pose(rng, 1.0, 2.0)
    Tb = Ta.compose(random_pose(rng, 0.1, 0.4))
    uv, vel, off, td = np.array([0.1, -0.2]), np.array([0.4, 0.3]), 0.002, 0.006
    lam_o = 0.25
    ray = np.append(shift_uv(uv, vel, off, td), 1.0)     # the old anchor's ray at the keyframe time
    z = Tb.compose(Tc).transformTo(Ta.compose(Tc).transformFrom(ray / lam_o))[2]
    args = [np.array([lam_o]), np.array([1.0 / z]), Tc, Ta, Tb, np.array([td])]
    r, _ = depth_transfer_residual(args, uv, lam_o, vel, off)
    assert abs(r[0]) < 1e-12
    args[1] = np.array([1.02 / z])                        # 2% too near: r = +2% (lam_ref = lam_o)
    assert np.isclose(depth_transfer_residual(args, uv, lam_o, vel, off)[0][0], 0.02)


@pytest.fixture(scope="module")
def slow_long_tracks(tmp_path_factory):
    """10 s of slow motion (0.2 m/s) with every track kept while visible: tracks outlive a
    1-s window, so every keyframe re-anchors most landmarks. Noise-free IMU and tracks."""
    from vio.sim import simulate
    from vio.sim.config import SimConfig
    from vio.sim.tracks import TrackGenConfig, generate_tracks
    root = tmp_path_factory.mktemp("slow")
    simulate(root / "raw", SimConfig(seconds=10.0, seed=5, stereo=False, render_images=False,
                                     imu_noise=False, speed_mps=0.2, yaw_sweep_dps=15.0))
    generate_tracks(root / "raw", root / "trk", TrackGenConfig(td_s=0.005, seed=2, noise_px=0.0,
                                                               outlier_rate=0.0, persistent_fraction=1.0))
    return load_euroc(root / "trk")


@pytest.mark.slow
def test_fixed_lag_keeps_what_reanchored_tracks_measured(slow_long_tracks):
    """With the leaving observations handed to the new key (farewell + depth transfer) the
    1-s fixed-lag estimate stays within 1.5 mm of the batch solution (measured 0.9 mm);
    dropping them, as before, doubles the gap (2.2 mm)."""
    n = 195
    gaps, batches = {}, {}
    for keep in (True, False):
        calib = CalibConfig(td_feedback_at_init=False)   # the same keyframe times in both runs
        cfg = PipelineConfig(backend=BackendConfig(solver=SolverConfig(lag_s=1.0), calib=calib,
                                                   vision=VisionConfig(marginalize_reanchored=keep)))
        lag = run_dataset(slow_long_tracks, cfg, max_frames=n)
        last = next(o for o in reversed(lag.outputs) if o.keyframe)
        full = PipelineConfig(backend=BackendConfig(solver=SolverConfig(lag_s=1000.0), calib=calib))
        if last.t_ns not in batches:    # the same keyframe times: one batch serves both runs
            batches[last.t_ns] = batch_solution(full, slow_long_tracks, n, last.t_ns)[0]
        T_batch = batches[last.t_ns]
        gaps[keep] = float(np.linalg.norm(last.T_w_b.translation() - T_batch.translation()))
    assert gaps[True] < 1.5e-3 and gaps[True] < 0.6 * gaps[False], gaps
