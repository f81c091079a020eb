"""td re-anchoring (``CalibConfig.td_reanchor_s``): once the sync layer applies the fed-back
td, the window restarts at the current state and td, forgetting the td information gathered
while the offset left to the td variable was large (there the regressor's noise attenuates it).
Generated tracks on the real V2_01 IMU and ground truth, true td +25 ms, sync layer at 0."""

from __future__ import annotations

import logging

import pytest

from conftest import shared


@pytest.fixture(scope="module")
def v2_td25(tmp_path_factory):
    from vio.sim.tracks import TrackGenConfig, generate_tracks
    out = tmp_path_factory.mktemp("td25")
    generate_tracks(shared("euroc_imu_gt", "V2_01_easy"), out,
                    TrackGenConfig(start_s=20.0, duration_s=16.0, td_s=0.025, seed=7, imu_consistent=False))
    return out


def _run(root, **calib):
    from vio.config import from_dict
    from vio.evaluation import evaluate
    from vio.io.euroc import load_euroc
    from vio.modes import MODE_DEFAULTS, merged
    from vio.run import PipelineConfig, run_dataset
    data = load_euroc(root)
    over = {"backend": {"calib": {"td_feedback_after_s": 2.0, **calib}}}
    cfg = from_dict(PipelineConfig, merged(MODE_DEFAULTS.get("features", {}), over))
    res = run_dataset(data, cfg, mode="features")
    return res, evaluate(*res.arrays(), data.groundtruth).ate_rmse


def test_td_reanchors_once_after_the_feedback_and_ends_near_the_truth(v2_td25, caplog):
    """The initialization's window replayed at the sync layer's offset (as before
    ``CalibConfig.td_init_retime``), so the first window holds the whole offset."""
    with caplog.at_level(logging.INFO, logger="vio.backend.td_reanchor"):
        res, ate = _run(v2_td25, td_init_retime=False)
    assert caplog.text.count("td re-anchored") == 1
    assert res.restarts == 0 and res.recoveries == 0
    assert abs(res.outputs[-1].td_s - 0.025) < 0.0008, res.outputs[-1].td_s
    assert ate < 0.1, ate


def test_td_reanchoring_off(v2_td25, caplog):
    with caplog.at_level(logging.INFO, logger="vio.backend.td_reanchor"):
        res, _ = _run(v2_td25, td_reanchor_s=0.0)
    assert "td re-anchored" not in caplog.text
    assert abs(res.outputs[-1].td_s - 0.025) < 0.003


def test_window_replayed_at_its_found_td_needs_no_reanchoring(v2_td25, caplog):
    """The default: the window replayed at the offset the initialization found
    (``vio.init_retime``) starts with the sync layer's offset near the truth."""
    with caplog.at_level(logging.INFO, logger="vio.backend.td_reanchor"):
        res, ate = _run(v2_td25)
    assert "td re-anchored" not in caplog.text
    assert res.restarts == 0 and res.recoveries == 0
    assert abs(res.outputs[-1].td_s - 0.025) < 0.0008, res.outputs[-1].td_s
    assert ate < 0.1, ate
