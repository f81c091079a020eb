"""Smoke tests of the benchmark suite (benchmarks/): the GTSAM-native baselines run
(feature tracks on real data; stereo on a tiny rendered sequence through the worker),
the dataset registry lists the image modes, and the report renders. No timing
assertions (numbers live in benchmarks/).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import report  # noqa: E402
from conftest import shared  # noqa: E402


@pytest.fixture(scope="module")
def v101_150():
    """Our run and the baseline on the first 150 frames of the real V1_01 tracks."""
    from baseline_gtsam import Schedule, record_schedule, run_baseline
    from vio.io.euroc import load_euroc
    from vio.pipeline import PipelineConfig
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    cfg = PipelineConfig()
    ours, sched = record_schedule(data, cfg, max_frames=150)
    sched = Schedule.from_json(json.loads(json.dumps(sched.to_json())))  # JSON round trip
    base = run_baseline(data, sched, cfg, max_frames=150)
    return data, ours, sched, base


def test_baseline_runs_on_our_keyframes_and_scores_finite_ate(v101_150):
    from vio.evaluation import evaluate
    data, ours, sched, base = v101_150
    # same keyframes: every keyframe the baseline inserted is one of ours, and all of ours are used
    kf_base = {o.t_ns for o in base.outputs if o.keyframe}
    assert kf_base == set(sched.keyframes), "baseline keyframes differ from the schedule"
    assert base.keyframes == ours.keyframes
    assert base.recoveries == 0
    # one online estimate per frame from the initial keyframe on
    assert base.outputs[0].t_ns == sched.init.t_ns
    assert len(base.outputs) == base.frames_in - sum(t < sched.init.t_ns for t in data.cam0.t_ns[:150])
    e = evaluate(*base.arrays(), data.groundtruth)
    assert math.isfinite(e.ate_rmse)
    # 150 frames (7.5 s, ~2.7 m path): a working VIO stays within 10 cm
    assert e.ate_rmse < 0.10, f"baseline ATE {e.ate_rmse:.3f} m"


def test_schedule_json_round_trip(v101_150):
    _, _, sched, _ = v101_150
    back = type(sched).from_json(json.loads(json.dumps(sched.to_json())))
    assert back.keyframes == sched.keyframes and back.td_s == sched.td_s
    assert back.init.T_w_b.equals(sched.init.T_w_b, 1e-12)
    np.testing.assert_allclose(back.init.bias.vector(), sched.init.bias.vector(), atol=1e-15)


TINY = {
    "machine": {"cpu": "Test CPU", "cores": 2, "python": "3.11", "gtsam": "4.3.0", "numpy": "2.0",
                "commit": "abc123"},
    "created": "2025-01-01 00:00:00", "quick": True,
    "accuracy": {
        "runs": [{"dataset": "SEQ@0+20s/td5ms", "mode": "features", "group": "SEQ@0+20s", "twin": "SEQ@0+20s/td0ms",
                  "td_true_ms": 5.0, "overrides": {},
                  "ours": {"ate_rmse": 0.05, "ate_pct": 0.5, "path_m": 10.0, "rpe_trans": 0.02, "rpe_rot_deg": 0.3,
                           "recoveries": 0, "keyframes": 100, "frame_ms": {"mean": 5.0, "p50": 1.0, "p95": 20.0,
                                                                           "max": 40.0},
                           "rtf": 10.0, "peak_rss_mb": 250.0, "td_ms": 3.0, "td_err_ms": -2.0},
                  "baseline": {"ate_rmse": 0.1, "ate_pct": 1.0, "path_m": 10.0, "recoveries": 1,
                               "frame_ms": {"mean": 2.5, "p50": 0.5, "p95": 9.0, "max": 12.0}, "rtf": 20.0,
                               "peak_rss_mb": 200.0},
                  "ratio": {"ate": 0.5, "time": 2.0}}],
        "td": [{"group": "SEQ@0+20s", "td_true_ms": 5.0, "td_est_ms": 3.0, "td0_est_ms": -1.0,
                "raw_err_ms": -2.0, "diff_ms": 4.0, "diff_err_ms": -1.0}],
        "skipped": {"stereo": "not wired"}},
}


def test_report_renders_tables_from_tiny_json():
    md = report.render(json.loads(json.dumps(TINY)))
    assert "Test CPU, 2 cores" in md and "gtsam 4.3.0" in md
    row = next(line for line in md.splitlines() if line.startswith("| SEQ@0+20s/td5ms | 10.0"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:5] == ["0.050", "0.100", "0.50"]       # ATE ours, baseline, ratio
    assert "| SEQ@0+20s | 5.0 | 3.00 | -1.00 | -2.00 | 4.00 | -1.00 |" in md
    assert "5.0 / 1.0 / 20.0 / 40.0" in md                 # ours ms/frame mean/p50/p95/max
    assert "`stereo` (not wired)" in md


def test_readme_section_only_between_markers(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{report.START}\nold\n{report.END}\noutro\n")
    assert report.update_readme(readme, report.readme_section(TINY))
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{report.END}\noutro\n")
    assert "old" not in text and "| SEQ@0+20s/td5ms | 0.050 | 0.100 | 5.0 | 2.5 |" in text
    plain = tmp_path / "PLAIN.md"
    plain.write_text("no markers here\n")
    assert not report.update_readme(plain, "new")
    assert plain.read_text() == "no markers here\n"
    assert "markers" in capsys.readouterr().out


# ------------------------------------------------------------------ image modes
def test_registry_lists_image_specs():
    import datasets as ds
    specs, skipped = ds.registry(quick=False, modes=["stereo", "mono", "direct", "hybrid"])
    real = [s for s in specs if s.sim is None and not s.stamp_shift_s]
    moved = [s for s in specs if s.stamp_shift_s]
    # the real stereo and mono folders again with issue 20's offsets (not in the photometric modes)
    assert sorted((s.mode, s.td_true_s) for s in moved) == ([] if not real else sorted(
        (m, td) for m in ("mono", "stereo") for td in ds.SHIFT_TD_S))
    assert all(s.twin == s.name.split("/td")[0] and s.stamp_shift_s == -s.td_true_s for s in moved)
    # the real MH_01 stereo images run in stereo, direct and hybrid, the real MH_05 cam0
    # images (td unknown) in mono (skipped, with the reason, where ../shared is absent)
    assert sorted(s.mode for s in real) == (["direct", "hybrid", "mono", "stereo"] if real else [])
    assert all(s.source == ds.MH_01_STEREO and s.td_true_s == 0.0 for s in real if s.mode != "mono")
    assert all(s.source == ds.MH_05_MONO and s.td_true_s is None for s in real if s.mode == "mono")
    assert set(skipped) == (set() if real else {"MH_01_real_stereo", "MH_05_real_mono"})
    specs = [s for s in specs if s.sim is not None]
    by_mode: dict = {}
    for s in specs:
        by_mode.setdefault(s.mode, []).append(s)
    assert sorted(by_mode) == ["direct", "hybrid", "mono", "stereo"]
    for s in specs:
        c = s.sim_config()
        assert s.generated and s.td_true_s == c.td_s == (0.0 if c.exposure_changes == "smooth" else 0.010)
        assert c.seconds == 20.0 and c.image_scale == 1.0 and c.seed not in (0, 3, 5)   # unseen seeds
        assert c.stereo == (s.mode != "mono")
    assert sorted(s.sim_config().line_time_s for s in by_mode["stereo"]) == [0.0, 0.0, 30e-6]
    # the photometric modes run on every stereo render, as stereo does: exposure changes,
    # global shutter with td 10 ms and rolling shutter (modelled since stop 73)
    for m in ("direct", "hybrid"):
        runs = by_mode[m]
        assert sorted(s.sim_config().exposure_changes for s in runs) == ["none", "none", "smooth"]
        assert sorted(s.sim_config().line_time_s for s in runs) == [0.0, 0.0, 30e-6]
        assert {s.group for s in runs} == {s.group for s in by_mode["stereo"]}
    assert len(specs) == 10 and len({s.key() for s in specs}) == 4    # one rendering per sequence
    quick, _ = ds.registry(quick=True, modes=["stereo", "mono"])
    quick = [s for s in quick if s.sim is not None]
    assert [s.sim_config().seconds for s in quick] == [8.0] * 4
    assert {s.key() for s in quick}.isdisjoint({s.key() for s in specs})


def test_frames_npz_round_trip(tmp_path):
    from baseline_stereo import load_frames, save_frames
    from vio.io.types import FeatureFrame
    rng = np.random.default_rng(3)
    right = rng.normal(size=(4, 2))
    right[1] = np.nan
    frames = [None,
              FeatureFrame(5, np.arange(4), rng.normal(size=(4, 2)), rng.normal(size=(4, 2)),
                           rng.normal(size=4), right, rng.normal(size=(4, 2))),
              FeatureFrame(7, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)),
              FeatureFrame(9, np.array([3, 8]), rng.normal(size=(2, 2)), np.zeros((2, 2)), np.full(2, np.nan))]
    save_frames(tmp_path / "f.npz", frames)
    back = load_frames(tmp_path / "f.npz")
    assert back[0] is None and len(back) == 4
    for a, b in zip(frames[1:], back[1:]):
        assert a.t_ns == b.t_ns
        np.testing.assert_array_equal(a.ids, b.ids)
        for name in ("uv", "velocity", "row", "right_uv", "right_velocity"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None), name
            if x is not None:
                np.testing.assert_array_equal(x, y)       # exact, NaN where NaN


def test_stereo_rig_matches_generic_stereo_factor():
    """Points projected into the unrectified simulator cameras give rectified
    measurements with equal rows, which GenericStereoFactor3D (body_P_sensor = the
    rectified cam0) explains with zero error at the true pose and point."""
    import gtsam
    from baseline_stereo import StereoRig
    from vio.io.types import FeatureFrame
    from vio.sim.render import sim_camera
    cam0, cam1 = sim_camera("cam0"), sim_camera("cam1")
    rig = StereoRig.from_calib(cam0, cam1)
    assert abs(rig.K.baseline() - 0.110) < 0.002              # EuRoC: ~11 cm
    T_w_b = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.1, 0.2), np.array([1.0, 2.0, 0.5]))
    T_w_c0, T_w_c1 = T_w_b.compose(cam0.T_b_c), T_w_b.compose(cam1.T_b_c)
    rng = np.random.default_rng(1)
    pts = [T_w_c0.transformFrom(np.array([*rng.uniform(-1, 1, 2) * z, z])) for z in rng.uniform(1, 8, 20)]
    norm = lambda T, p: (lambda q: q[:2] / q[2])(T.transformTo(p))  # noqa: E731
    fr = FeatureFrame(0, np.arange(20), np.array([norm(T_w_c0, p) for p in pts]), np.zeros((20, 2)),
                      np.zeros(20), np.array([norm(T_w_c1, p) for p in pts]))
    meas = rig.measure(fr, epipolar_px=1e-6, min_disparity_px=0.5)
    assert np.isfinite(meas).all()                            # rows agree after rectification
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    for p, m in zip(pts, meas):
        f = gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(*m), noise, 1, 2, rig.K, rig.T_b_r)
        vals = gtsam.Values()
        vals.insert(1, T_w_b)
        vals.insert(2, p)
        assert np.abs(f.unwhitenedError(vals)).max() < 1e-6   # pixels
    # and a match off the epipolar line is dropped
    bad = FeatureFrame(0, np.arange(1), fr.uv[:1], fr.velocity[:1], fr.row[:1], fr.right_uv[:1] + [0, 0.02])
    assert np.isnan(rig.measure(bad, 2.0, 0.5)).all()


@pytest.mark.slow
def test_tiny_stereo_job_round_trips_through_worker(tmp_path):
    """3 s of rendered stereo at half resolution, ours then the stereo baseline, each
    in a fresh ``run_all.py --worker`` process: both run on the same keyframes."""
    import datasets as ds
    import run_all
    spec = ds.sim_spec("stereo", "tiny", seed=11, seconds=3.0, image_scale=0.5)
    path = ds.prepare(spec, cache=tmp_path)
    assert (path / ".done").exists() and ds.prepare(spec, cache=tmp_path) == path   # cached
    row = run_all.compare(spec, path, log=lambda m: None)
    o, b = row["ours"], row["baseline"]
    assert "error" not in o and "error" not in b, (o.get("error"), b.get("error"))
    assert row["mode"] == "stereo" and o["keyframes"] == b["keyframes"] > 5
    assert 0 < o["frames"] <= b["frames"] and o["frame_wall_ms"]["mean"] > 0
    assert o["ate_rmse"] < 0.05 and b["ate_rmse"] < 0.10, (o["ate_rmse"], b["ate_rmse"])
    assert abs(o["td_err_ms"]) < 5.0                           # td 10 ms, estimated
    assert row["ratio"]["ate"] is not None
    known = row["baseline_td_known"]                           # the baseline told the true td
    assert "error" not in known and known["keyframes"] == o["keyframes"] and known["ate_rmse"] < 0.10


def test_report_puts_image_rows_in_their_own_tables():
    res = json.loads(json.dumps(TINY))
    features_only = report.render(res)
    img = {"dataset": "sim11-stereo-20s/td10ms", "mode": "stereo", "group": "sim11-stereo-20s", "twin": None,
           "td_true_ms": 10.0, "overrides": {},
           "ours": {"ate_rmse": 0.011, "path_m": 14.0, "recoveries": 0, "keyframes": 125, "td_ms": 8.6,
                    "td_err_ms": -1.4, "frame_ms": {"mean": 30.0, "p50": 20.0, "p95": 90.0, "max": 200.0},
                    "frame_wall_ms": {"mean": 33.0, "p50": 30.0, "p95": 95.0, "max": 210.0}, "rtf": 1.6,
                    "rtf_process": 1.3},
           "baseline": {"ate_rmse": 0.041, "recoveries": 0, "keyframes": 125,
                        "frame_ms": {"mean": 20.0, "p50": 2.0, "p95": 80.0, "max": 150.0}, "rtf": 2.5},
           "baseline_td_known": {"ate_rmse": 0.007},
           "ratio": {"ate": 0.268, "time": 1.5, "ate_td_known": 1.571}}
    res["accuracy"]["runs"].append(img)
    md = report.render(res)
    # the feature-mode section is unchanged by an image row
    head = features_only.split("Skipped:")[0]
    assert md.startswith(head.rstrip()) and "## Accuracy and speed, image modes" in md
    row = next(line for line in md.splitlines() if line.startswith("| sim11-stereo-20s/td10ms | stereo"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3:8] == ["0.011", "0.041", "0.27", "0.007", "1.57"] and cells[9:11] == ["10.0", "8.60 (-1.40)"]
    assert "| sim11-stereo-20s/td10ms | 30.0 / 20.0 / 90.0 / 200.0 | 33.0 / 95.0 |" in md
    section = report.readme_section(res)
    assert "| SEQ@0+20s/td5ms | 0.050 | 0.100 | 5.0 | 2.5 |" in section           # feature rows as before
    assert ("| sim11-stereo-20s/td10ms | stereo | 0.011 | 0.041 | 0.007 | 8.60 (-1.40) | 30.0 | 33.0 | 20.0 "
            "| 1.60 / 1.30 |") in section
    # the speed table gives the whole-process real-time factor next to the loop's
    assert "| 1.60 / 2.50 | 1.30 |" in md


# ------------------------------------------------------------------ calibration runs
def test_calibration_spec_perturbs_the_extrinsic_and_keeps_the_truth(tmp_path):
    """The calibration row starts from a T_BS off by CALIB_ERROR (deg, mm) and scores
    the estimate against the true T_b_c recorded next to the data."""
    import shutil

    import gtsam

    import datasets as ds
    from vio.io.calib import read_camera_yaml
    src = shared("euroc_V1_01_30s_features", "mav0", "cam0", "sensor.yaml")
    (tmp_path / "mav0" / "cam0").mkdir(parents=True)
    shutil.copy(src, tmp_path / "mav0" / "cam0" / "sensor.yaml")
    true = read_camera_yaml(src).T_b_c
    ds.perturb_extrinsic(tmp_path, 2.0, 20.0)
    wrong = read_camera_yaml(tmp_path / "mav0" / "cam0" / "sensor.yaml").T_b_c
    d = true.between(wrong)
    assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation()))) == pytest.approx(2.0, rel=1e-6)
    assert np.linalg.norm(d.translation()) == pytest.approx(0.020, rel=1e-3)   # Exp: J(w) v
    np.testing.assert_allclose(ds.true_extrinsic(tmp_path), true.matrix(), atol=1e-12)
    assert ds.true_extrinsic(tmp_path / "mav0") is None
    spec = ds.calibration_spec(quick=False)
    assert spec.calib_error == ds.CALIB_ERROR and spec.twin is None
    assert spec.pipeline_overrides() == {"backend.calib.estimate_extrinsic": True}
    plain = next(s for s in ds.feature_datasets(False) if s.group == spec.group.split("/calib")[0])
    assert spec.key() != plain.key()     # its own cache folder


def test_variant_rows_get_their_own_table_with_the_twin_ratio():
    """``variants`` rows (other generators) are tabulated apart, with the td error and the
    ATE ratio to their td = 0 twin, for ours and for the baseline told the true td (its
    plain run at td 0); the feature tables and the td table are unchanged."""
    res = json.loads(json.dumps(TINY))
    base = report.render(res)

    def row(td, ate, est, base_ate):
        name = f"boxwall:SEQ@0+60s/td{td:g}ms"
        b = {"ate_rmse": base_ate, "ate_pct": base_ate * 2.5} if base_ate else {"error": "failed"}
        r = {"dataset": name, "mode": "variants", "group": "boxwall:SEQ", "td_true_ms": float(td),
             "twin": None if td == 0 else "boxwall:SEQ@0+60s/td0ms", "overrides": {},
             "ours": {"ate_rmse": ate, "ate_pct": 0.1, "td_ms": est, "td_err_ms": est - td, "path_m": 50.0,
                      "frame_ms": {"mean": 30.0, "p50": 20.0, "p95": 90.0, "max": 200.0}},
             "baseline": b if td == 0 else {"skipped": "told the true td"}, "ratio": {"ate": None, "time": None}}
        if td:
            r["baseline_td_known"] = b
        return r
    res["accuracy"]["runs"] += [row(0, 0.04, -0.1, 0.04), row(25, 0.05, 24.7, 0.06), row(12, 0.044, 11.9, None)]
    md = report.render(res)
    assert "### Generator variants" in md
    assert "| boxwall:SEQ@0+60s/td25ms | 25.0 | 24.70 | -0.30 | 0.050 | 0.100 | 1.25 | 0.060 / 0.150 | 1.50 |" in md
    assert "| boxwall:SEQ@0+60s/td0ms | 0.0 | -0.10 | -0.10 | 0.040 | 0.100 | n/a | 0.040 / 0.100 | n/a |" in md
    assert "| boxwall:SEQ@0+60s/td12ms | 12.0 | 11.90 | -0.10 | 0.044 | 0.100 | 1.10 | n/a | n/a |" in md
    line = report._readme_variants(res["accuracy"])[0]
    assert "ATE / td0 twin max 1.25 (2 of 2 within 1.25x; the GTSAM-native baseline told the true td " \
           "max 1.50 (0 of 1 within 1.25x))" in line
    assert md.split("### Generator variants")[0].rstrip() == base.split("Skipped:")[0].rstrip() or \
        "boxwall" not in md.split("### Generator variants")[0]
    import datasets as ds
    specs, _ = ds.registry(quick=False, modes=["variants"])
    if not specs:
        pytest.skip("euroc_imu_gt not found (../shared/data)")
    assert {s.td_true_s for s in specs} == {-0.020, 0.0, 0.012, 0.025}
    assert all(s.mode == "variants" and ds.run_mode(s.mode) == "features" for s in specs)
    names = {s.name for s in specs}
    assert all(s.twin is None or s.twin.endswith("/td0ms") and s.twin in names
               and s.twin.split(":")[0] == s.name.split(":")[0] for s in specs)
    assert dict(specs[0].gen)["selection"] == "random"
    # the exact boxwall rows: td 0 only, the boxwall seeds, no pixel noise or outliers
    exact = [s for s in specs if s.name.startswith("boxwall-exact:")]
    assert len(exact) == 3 and {s.td_true_s for s in exact} == {0.0}
    for s in exact:
        noisy = next(n for n in specs if n.name == s.name.replace("boxwall-exact:", "boxwall:"))
        ge, gn = s.gen_config(), noisy.gen_config()
        assert ge.seed == gn.seed and ge.noise_px == 0 and ge.outlier_rate == 0
    # one respect each: same excerpt and seed as ours, generator settings differ only there
    from vio.sim.variants import VARIANTS
    from dataclasses import asdict
    ours = {s.td_true_s: asdict(s.gen_config()) for s in specs if s.name.startswith("ours:")}
    n = 0
    for s in specs:
        v = s.name.split(":MH_03")[0]
        if v.startswith("one:") and s.td_true_s in ours:
            diff = {k for k, x in asdict(s.gen_config()).items() if ours[s.td_true_s][k] != x}
            assert diff == set(VARIANTS[v]), (v, diff)
            n += 1
    assert n >= 12


def test_moved_stamps_copy_carries_the_offset_and_its_rows_are_summarised(tmp_path):
    """``shifted_spec``: a copy of a real image folder whose camera stamps moved by -td (the
    image files kept), its own cache folder; the report's line compares each moved run with
    the unmoved one."""
    import datasets as ds
    src = ds.DatasetSpec("MH_01_real_stereo", "stereo", ds.MH_01_STEREO, None, 0.0, group="MH_01_real_stereo")
    spec = ds.shifted_spec(src, 0.012)
    assert (spec.name, spec.td_true_s, spec.stamp_shift_s, spec.twin) == ("MH_01_real_stereo/td12ms", 0.012,
                                                                           -0.012, "MH_01_real_stereo")
    assert spec.generated and spec.key() != ds.shifted_spec(src, 0.025).key()
    assert ds.shifted_spec(dataclasses.replace(src, td_true_s=None), -0.02).td_true_s == -0.02
    if not src.source.exists():
        pytest.skip("euroc_MH_01_stereo_synimu not found (../shared/data)")
    out = ds.prepare(spec, cache=tmp_path)
    assert ds.true_td_s(spec, out) == 0.012
    from vio.io.euroc import load_euroc
    a, b = load_euroc(src.source), load_euroc(out)
    np.testing.assert_array_equal(b.cam0.t_ns, a.cam0.t_ns - 12_000_000)
    np.testing.assert_array_equal(b.cam1.t_ns, a.cam1.t_ns - 12_000_000)
    assert [p.name for p in b.cam0.files[:3]] == [p.name for p in a.cam0.files[:3]]
    np.testing.assert_array_equal(b.imu.t_ns, a.imu.t_ns)

    def row(name, td_true, td, ate, twin=None):
        return {"dataset": name, "mode": "mono", "group": "R", "twin": twin, "td_true_ms": td_true,
                "ours": {"ate_rmse": ate, "td_ms": td, "td_err_ms": None if td_true is None else td - td_true},
                "baseline": {}}
    acc = {"runs": [row("R", None, -0.1, 0.05), row("R/td12ms", 12.0, 11.8, 0.06, "R"),
                    row("R/td-20ms", -20.0, -19.7, 0.07, "R"),
                    dict(row("R", 0.0, 3.0, 0.01), mode="hybrid")]}    # the same name in another mode
    line = report.real_td_lines(acc)[-1]
    assert [r["dataset"] for r in report._unmoved(acc["runs"])] == ["R", "R"]   # not in the headline ratios
    assert "offsets -20, +12 ms; 2 runs" in line and "td error max 0.30 ms" in line
    assert "plus the offset max 0.40 ms" in line and "max 1.40 (1 of 2 within 1.25x)" in line


def test_stretch_copy_starts_the_cameras_at_the_frame(tmp_path):
    """bench_stretches: the copy's camera lists begin at the start frame (every ``step``-th
    from there), everything else (images, IMU, ground truth) is the original's; a start too
    close to the end refuses."""
    from bench_stretches import stretch
    from vio.io.euroc import load_euroc
    src = shared("euroc_V1_01_static_stereo")
    full = load_euroc(src)
    part = load_euroc(stretch(src, 30, tmp_path / "s30"))
    assert np.array_equal(part.cam0.t_ns, full.cam0.t_ns[30:])
    assert np.array_equal(part.cam1.t_ns, full.cam1.t_ns[30:])
    assert np.array_equal(part.imu.t_ns, full.imu.t_ns)
    assert Path(part.cam0.files[0]).exists()
    with pytest.raises(SystemExit, match="no stretch from frame"):
        stretch(src, len(full.cam0.t_ns) - 5, tmp_path / "late")
    every3 = load_euroc(stretch(src, 1, tmp_path / "s1x3", step=3))      # 6.7 Hz from frame 1
    assert np.array_equal(every3.cam0.t_ns, full.cam0.t_ns[1::3])
    assert np.array_equal(every3.cam1.t_ns, full.cam1.t_ns[1::3])
    feats = shared("euroc_V1_01_30s_features")     # a feature-track dataset: its tracks cut too
    whole, cut = load_euroc(feats), load_euroc(stretch(feats, 40, tmp_path / "f40", step=2))
    assert np.array_equal(cut.cam0.t_ns, whole.cam0.t_ns[40::2])
    assert [f.t_ns for f in cut.features] == [f.t_ns for f in whole.features[40::2]]
    assert all(np.array_equal(a.ids, b.ids) for a, b in zip(cut.features, whole.features[40::2]))


def test_imu_gt_consistency_is_one_on_consistent_motion_and_sees_a_scaled_imu():
    """imu_gt_consistency: the triangle-kernel second difference of an analytic path
    matches its acceleration (k = 1), an IMU 3 % hot gives k = 1 / 1.03, and on the
    synthesized MH_01 IMU (consistent with its ground truth by construction) k = 1."""
    from imu_gt_consistency import consistency, imu_world_accel
    t = np.arange(0.0, 20.0, 0.005)
    w = np.array([1.3, 0.7, 2.1])
    p = np.sin(np.outer(t, w)) * [1.0, 0.5, 0.2]
    acc = -p * w ** 2
    R = np.broadcast_to(np.eye(3), (len(t), 3, 3))
    for T in (0.25, 1.0):
        assert consistency(t, p, acc, R, T, fit_bias=False)[0] == pytest.approx(1.0, abs=2e-4)
        k, n = consistency(t, p, 1.03 * acc + [0.0, 0.0, 0.05], R, T, fit_bias=True)
        assert k == pytest.approx(1 / 1.03, abs=2e-4) and n > 10
    t, p, acc, R, has_bias = imu_world_accel(shared("euroc_MH_01_stereo_synimu"))
    assert has_bias
    assert consistency(t, p, acc, R, 0.25, fit_bias=False)[0] == pytest.approx(1.0, abs=3e-3)


def test_imu_gt_consistency_per_axis_finds_one_hot_accelerometer_axis():
    """``per_axis``: an accelerometer whose y axis reads 3 % hot (and a constant bias) on
    an analytic path with gravity gives s = (1, 1 / 1.03, 1); a consistent IMU s = 1."""
    from imu_gt_consistency import GRAVITY_W, per_axis
    t = np.arange(0.0, 20.0, 0.005)
    w = np.array([1.3, 0.7, 2.1])
    p = np.sin(np.outer(t, w)) * [1.0, 0.5, 0.2]
    f_b = -p * w ** 2 - GRAVITY_W                   # specific force, body = world axes
    R = np.broadcast_to(np.eye(3), (len(t), 3, 3))
    s, n = per_axis(t, p, f_b + GRAVITY_W, R, 0.5)
    assert s == pytest.approx(np.ones(3), abs=2e-4) and n > 10
    hot = f_b * [1.0, 1.03, 1.0] + [0.02, -0.01, 0.03]
    s, _ = per_axis(t, p, hot + GRAVITY_W, R, 0.5)
    assert s == pytest.approx([1.0, 1 / 1.03, 1.0], abs=2e-4)


def test_keyframe_cost_times_every_keyframe_and_restores_the_estimator():
    import keyframe_cost
    from vio.backend import estimator, smoother
    add, update = estimator.Estimator.add_keyframe, smoother.update
    rows = keyframe_cost.measure(shared("euroc_V1_01_30s_features"), "features", None)
    assert estimator.Estimator.add_keyframe is add and smoother.update is update
    assert len(rows) > 10
    t, t_upd, n_vars, n_points, n_kf, home = zip(*rows)
    assert all(0 < u <= s for s, u in zip(t, t_upd)) and all(home)
    assert max(n_points) > 0 and max(n_kf) > 3 and all(v > p for v, p in zip(n_vars, n_points))


def test_td_range_runs_every_sequence_at_td_0_and_rates_each_run_against_it():
    """``bench_td_range.py``: the run list adds each sequence's td = 0 run, keeps the seed
    and the variant's generator, and the table gives each run's td error and its ATE over
    its sequence's td = 0 run (NaN where a run has no twin or no baseline)."""
    import bench_td_range as tr
    from vio.sim.variants import VARIANTS
    todo = tr.specs("boxwall", ["MH_03_medium", "V2_01_easy"], [-30.0, 30.0], 430, 60.0)
    assert [s.td_true_s for s in todo] == [-0.03, 0.0, 0.03] * 2
    assert all(dict(s.gen)["seed"] == 430 and s.name.startswith("boxwall:") for s in todo)
    assert dict(todo[0].gen)["selection"] == dict(VARIANTS["boxwall"].items())["selection"]
    with pytest.raises(SystemExit, match="not one of"):
        tr.specs("nonesuch", ["MH_03_medium"], [0.0], 1, 60.0)
    rows = [{"name": "a/td0", "group": "A", "td_true_ms": 0.0, "td_ms": 0.2, "ate": 0.04, "pct": 0.1, "base": 0.05},
            {"name": "a/td30", "group": "A", "td_true_ms": 30.0, "td_ms": 29.4, "ate": 0.06, "pct": 0.15,
             "base": 0.04},
            {"name": "b/td30", "group": "B", "td_true_ms": 30.0, "td_ms": 30.1, "ate": 0.02, "pct": 0.05}]
    out = tr.table(rows)
    assert out[2].split()[1:] == ["30.00", "29.40", "-0.60", "0.0600", "0.150", "1.50", "0.0400", "0.80"]
    assert out[3].split()[-3:] == ["nan", "nan", "nan"]
    assert out[-1] == "td error max 0.60 ms, 2 of 3 within 0.5 ms; ATE max 0.150 % of the path"
