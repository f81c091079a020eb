"""An overshooting Gauss-Newton step is iterated again before the outlier check
(``SolverConfig.reiterate_chi2``, ``vio.backend.recovery.reiterate``)."""

from __future__ import annotations

import dataclasses

import pytest

from conftest import shared
from vio.backend.tracks import LandmarkManager
from vio.io.euroc import load_euroc
from vio.run import default_config, run_dataset
from vio.sim.tracks import TrackGenConfig, generate_tracks


@pytest.mark.slow
def test_an_overshooting_update_is_iterated_instead_of_emptying_the_window(tmp_path, monkeypatch):
    """Generated tracks of real V2_03 from 65 s (seed 13): one keyframe update after the
    mid-flight initialization moves every world point ~2 m towards the camera (IMU factor
    chi2 ~800). Without re-iteration the outlier check then rejects every landmark at
    once; with it one more iteration brings the IMU factor back (chi2 < 10) and the
    check rejects a few."""
    out = tmp_path / "v203"
    generate_tracks(shared("euroc_imu_gt", "V2_03_difficult"), out,
                    TrackGenConfig(start_s=65.0, duration_s=30.0, seed=13))
    data = load_euroc(out)
    removed: list[int] = []
    real = LandmarkManager.outlier_removals

    def counted(self, values):
        res = real(self, values)
        removed.append(res[3])
        return res

    monkeypatch.setattr(LandmarkManager, "outlier_removals", counted)
    worst = {}
    for chi2 in (0.0, 100.0):
        cfg = default_config("features")
        cfg = dataclasses.replace(cfg, backend=dataclasses.replace(
            cfg.backend, health=dataclasses.replace(cfg.backend.health, enabled=False),
            solver=dataclasses.replace(cfg.backend.solver, reiterate_chi2=chi2)))
        removed.clear()
        res = run_dataset(data, cfg, mode="features", max_frames=45)
        assert len(res.outputs) == 45
        worst[chi2] = max(removed)
    print("worst removed", worst)
    assert worst[0.0] > 40, "without re-iteration the update's overshoot empties the window"
    # measured 54 without, 9 with: the count follows the window's td remainder (3 at
    # 7.1 ms, 6 at the pair rotations' 6.6 ms of 3b76b93, 9 at the window batch's 4.7 ms
    # of stop 64 for a true 5 ms); a few, against the whole window without re-iteration
    assert worst[100.0] <= 12, f"re-iterated, the check rejected {worst[100.0]} landmarks at once"
