"""World-point landmarks (``VisionConfig.reanchor = "point"``, ``vio.backend.point_tracks``)
on generated MH_04 tracks 40 s into the flight (real IMU, td 5 ms, 0.7-px noise, 1.5%
outliers): the run is healthy, td is found through the points' factors, every main factor
holds only keyframes still in the window (observations of leaving keyframes went to
farewell factors), and the trajectory is close to the one with anchored inverse depths."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.conftest import shared
from vio.evaluation import evaluate
from vio.io.euroc import load_euroc
from vio.run import default_config, run_dataset
from vio.sim.tracks import TrackGenConfig, generate_tracks


@pytest.fixture(scope="module")
def mh04_12s(tmp_path_factory):
    src = shared("euroc_imu_gt", "MH_04_difficult")
    out = tmp_path_factory.mktemp("mh04_40_12")
    generate_tracks(src, out, TrackGenConfig(start_s=40.0, duration_s=12.0, seed=1))
    return load_euroc(out)


def _cfg(reanchor: str):
    cfg = default_config("features")
    vision = dataclasses.replace(cfg.backend.vision, reanchor=reanchor)
    return dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, vision=vision))


def _keep_pipeline(mp: pytest.MonkeyPatch, seen: dict) -> None:
    """Keep the run's pipeline in ``seen["pipe"]`` to inspect its estimator afterwards."""
    from vio.pipeline import Pipeline
    orig = Pipeline.__init__

    def keep(self, *a, **k):
        orig(self, *a, **k)
        seen["pipe"] = self

    mp.setattr(Pipeline, "__init__", keep)


@pytest.fixture(scope="module")
def point_run(mh04_12s):
    """One world-point run on the excerpt, watched: its estimator (``seen["pipe"]``), the
    farewells taken from the prefetch (``early``), and the outlier check's trimmed and
    dropped observations and the points retired after a trim (``retired``)."""
    from vio.backend.point_tracks import PointTracks
    seen: dict = {"early": 0, "trimmed": 0, "dropped": 0, "retired": []}
    prepare, check_outliers = PointTracks.prepare_update, PointTracks.outlier_removals

    def count(self, *a, **k):
        if self._early_values is self.est.values:
            seen["early"] += len(self._early)
        return prepare(self, *a, **k)

    def check(self, *a, **k):
        dropped, trimmed = check_outliers(self, *a, **k)
        seen["trimmed"] += len(trimmed)
        seen["dropped"] += len(dropped)
        seen["retired"] += [(pt, set(pt.obs)) for pt in self.tracks.values() if pt.retired and pt.lid in trimmed]
        return dropped, trimmed

    with pytest.MonkeyPatch.context() as mp:
        _keep_pipeline(mp, seen)
        mp.setattr(PointTracks, "prepare_update", count)
        mp.setattr(PointTracks, "outlier_removals", check)
        seen["res"] = run_dataset(mh04_12s, _cfg("point"), mode="features")
    return seen


def test_world_points_run_find_td_and_keep_main_factors_in_the_window(mh04_12s, point_run):
    d, res = mh04_12s, point_run["res"]
    est = point_run["pipe"].est
    assert res.restarts == 0 and res.recoveries == 0
    pts = est.lm.points.tracks
    assert len(pts) >= 10 and not [lid for lid in pts if lid in est.lm.tracks]
    window = set(est.kf_t)
    for pt in pts.values():      # the main factor holds only window keyframes
        assert pt.index is not None and set(pt.frames) == set(pt.obs) <= window
        assert est.values.exists(pt.key)
    assert abs(est.td() - 0.005) < 0.001
    # the outlier check's rows (kept from the factors built, else gathered): as gathered
    from vio.backend.track_arrays import gather
    plist = list(pts.values())
    hits = sum(pt.rows is not None and pt.rows[0] == tuple(pt.frames) for pt in plist)
    kept, plist[0].rows = plist[0].rows, None
    got = est.lm.points._rows(plist)
    plist[0].rows = kept
    ref = gather([[pt.obs[f] for f in pt.frames] for pt in plist], est.cam.line_time_s)
    assert hits >= len(plist) // 2 and all(np.array_equal(a, b, equal_nan=True) for a, b in zip(got, ref))
    e = evaluate(*res.arrays(), d.groundtruth)
    a = evaluate(*run_dataset(d, _cfg("anchor"), mode="features").arrays(), d.groundtruth)
    print(f"point {e.ate_rmse:.4f} anchor {a.ate_rmse:.4f} m over {e.path_length:.1f} m")
    # one 12-s excerpt moves by centimetres with any solver setting (point / anchor:
    # relinearization every 10th update 0.062 / 0.064 m, every update 0.060 / 0.049 m,
    # with the gauge prior 0.054 / 0.042 m, points relinearized at 5 cm 0.061 / 0.042 m);
    # which representation is better was decided on 20 excerpts (vio.modes), and the
    # points' threshold on 20 excerpts, 49 table rows and the real V1_01 tracks
    # (SolverConfig), so this bounds the gap instead of ranking them
    assert e.ate_rmse < 0.01 * e.path_length and e.ate_rmse <= 1.5 * a.ate_rmse


def test_prefetched_farewells_change_nothing(mh04_12s, point_run, monkeypatch):
    """Farewell factors built between keyframes (``Estimator.prefetch``) are the ones the
    keyframe's update would build: the run is the same to the last bit with and without,
    and most farewells come from the prefetch."""
    from vio.backend.estimator import Estimator
    assert point_run["early"] > 100
    monkeypatch.setattr(Estimator, "prefetch", lambda self, t_ns: None)
    without = run_dataset(mh04_12s, _cfg("point"), mode="features")
    for a, b in zip(point_run["res"].arrays(), without.arrays()):
        assert np.array_equal(a, b)


def test_isolated_outliers_trim_the_observation_and_retire_the_point(point_run):
    """The generated tracks' gross outliers (1.5 %, single observations): the outlier check
    drops only those observations (``VisionConfig.outlier_obs``); the point keeps a main
    factor over its other observations, with the slot the outlier update gave it, and gets
    no new observation while it is in the window."""
    from vio.backend import graph
    seen, res = point_run, point_run["res"]
    est = seen["pipe"].est
    assert res.restarts == 0 and res.recoveries == 0
    assert seen["trimmed"] >= 5 and seen["retired"]
    for pt, obs in seen["retired"]:       # never observed again after it was retired
        assert set(pt.obs) <= obs
    factors = est.smoother.getFactors()
    live = [(key, pt) for key, pt in est.lm.points.tracks.items()]
    assert any(pt.retired for _, pt in live)
    for key, pt in live:                  # each main factor sits in its recorded slot
        f = factors.at(pt.index)
        assert f is not None and pt.key in f.keys()
        assert {graph.X(k) for k in pt.frames} == {k for k in f.keys() if k != pt.key} - {graph.TD}


def test_world_points_calibrate_a_wrong_extrinsic_online(mh04_12s):
    """Online calibration (``CalibConfig.estimate_extrinsic``) with world points: every main
    factor takes the extrinsic as a key, and from a ``T_b_c`` 1 degree and 10 mm off the
    rotation comes back to within a third of its error (translation: weakly observable in
    12 s, only bounded); the trajectory stays within 1 % of the path."""
    import gtsam

    from vio.backend import graph
    d = mh04_12s
    true = d.cam0.calib.T_b_c
    off = gtsam.Pose3(gtsam.Rot3.Rodrigues(np.radians([0.6, -0.5, 0.6])), np.array([0.006, -0.005, 0.006]))
    wrong = true.compose(off)
    bad = dataclasses.replace(d, cam0=dataclasses.replace(d.cam0, calib=dataclasses.replace(d.cam0.calib, T_b_c=wrong)))
    cfg = _cfg("point")
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(
        cfg.backend, calib=dataclasses.replace(cfg.backend.calib, estimate_extrinsic=True)))
    seen: dict = {}
    with pytest.MonkeyPatch.context() as mp:
        _keep_pipeline(mp, seen)
        res = run_dataset(bad, cfg, mode="features")
    est = seen["pipe"].est
    assert res.restarts == 0 and res.recoveries == 0
    factors = est.smoother.getFactors()
    pts = list(est.lm.points.tracks.values())
    assert len(pts) >= 10 and all(graph.EXTRINSIC in factors.at(pt.index).keys() for pt in pts)

    def rot_deg(T):
        return np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(true.rotation().between(T.rotation()))))

    got = res.outputs[-1].T_b_c
    print(f"rotation error {rot_deg(wrong):.2f} -> {rot_deg(got):.2f} deg, translation "
          f"{1e3 * np.linalg.norm(wrong.translation() - true.translation()):.1f} -> "
          f"{1e3 * np.linalg.norm(got.translation() - true.translation()):.1f} mm")
    assert rot_deg(got) < rot_deg(wrong) / 3
    assert np.linalg.norm(got.translation() - true.translation()) < 0.02
    from vio.run_summary import summary  # the summary says how far it moved from the calibration
    moved = np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(wrong.rotation().between(got.rotation()))))
    assert any(ln.startswith("extrinsic t_b_c") and f"(moved {moved:.3f} deg" in ln for ln in summary(res, bad))
    e = evaluate(*res.arrays(), d.groundtruth)
    assert e.ate_rmse < 0.01 * e.path_length
