"""Tests of the feature-track generator (vio.sim.tracks) on real EuRoC IMU + ground truth.

Re-projection checks use an independent reader and scipy's slerp, not the module's own
interpolation. Tolerances: noise-free observations must match to 1e-9 (normalized
units; the file keeps 12 decimals).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from conftest import shared
from vio.config import from_dict
from vio.errors import ConfigError, DataError
from vio.io.calib import read_camera_yaml
from vio.io.euroc import load_euroc
from vio.sim import tracks_cli
from vio.sim.tracks import TrackGenConfig, generate_tracks

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GT_DIR = DATA / "euroc_imu_gt"
needs_data = pytest.mark.skipif(not GT_DIR.is_dir(), reason=f"EuRoC IMU+GT data not found at {GT_DIR}")
CLEAN = dict(start_s=20.0, duration_s=10.0, noise_px=0.0, outlier_rate=0.0)
NOISY = TrackGenConfig(start_s=20.0, duration_s=10.0, td_s=0.005, seed=1, noise_px=0.8,
                       outlier_rate=0.02)


@pytest.fixture(scope="module")
def v102_clean(tmp_path_factory):
    if not GT_DIR.is_dir():
        pytest.skip(f"EuRoC IMU+GT data not found at {GT_DIR}")
    out = tmp_path_factory.mktemp("v102_clean")
    return generate_tracks(GT_DIR / "V1_02_medium", out, TrackGenConfig(td_s=0.005, seed=1, **CLEAN))


@pytest.fixture(scope="module")
def mh03_clean(tmp_path_factory):
    if not GT_DIR.is_dir():
        pytest.skip(f"EuRoC IMU+GT data not found at {GT_DIR}")
    out = tmp_path_factory.mktemp("mh03_clean")
    return generate_tracks(GT_DIR / "MH_03_medium", out, TrackGenConfig(td_s=-0.008, seed=2, **CLEAN))


@pytest.fixture(scope="module")
def v102_noisy(tmp_path_factory):
    if not GT_DIR.is_dir():
        pytest.skip(f"EuRoC IMU+GT data not found at {GT_DIR}")
    out = tmp_path_factory.mktemp("v102_noisy")
    return generate_tracks(GT_DIR / "V1_02_medium", out, NOISY)


# ---------------------------------------------------------------- independent readers
def data_lines(path: Path) -> list[str]:
    return [s for s in path.read_text().splitlines() if not s.startswith("#")]


def read_features(path: Path):
    lines = path.read_text().splitlines()
    assert lines[0] == "timestamp_ns,frame_idx,landmark_id,u_norm,v_norm"
    rows = [s.split(",") for s in lines[1:]]
    t = np.array([int(r[0]) for r in rows], dtype=np.int64)
    f = np.array([int(r[1]) for r in rows])
    i = np.array([int(r[2]) for r in rows])
    uv = np.array([[float(r[3]), float(r[4])] for r in rows])
    return t, f, i, uv


def read_gt(mav0: Path):
    """(t_ns, p (N,3), q_xyzw (N,4)) from the written EuRoC csv or TUM file."""
    gt = mav0 / "state_groundtruth_estimate0"
    if (gt / "data.csv").exists():
        rows = [s.split(",") for s in data_lines(gt / "data.csv")]
        assert all(len(r) == 17 for r in rows)
        t = np.array([int(r[0]) for r in rows], dtype=np.int64)
        v = np.array([[float(x) for x in r[1:8]] for r in rows])
        return t, v[:, 0:3], v[:, [4, 5, 6, 3]]
    rows = [s.split() for s in data_lines(gt / "groundtruth_tum.txt")]
    assert all(len(r) == 8 for r in rows)
    t = np.array([int(Decimal(r[0]) * 10**9) for r in rows], dtype=np.int64)
    v = np.array([[float(x) for x in r[1:]] for r in rows])
    return t, v[:, 0:3], v[:, 3:7]


def reproject(out: Path, t_exp: np.ndarray, frame: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Normalized uv of each observation's landmark, camera at GT(t_exp[frame]) * T_b_c."""
    mav0 = out / "mav0"
    lm = np.loadtxt(out / "landmarks.csv", delimiter=",", skiprows=1)
    p_by_id = dict(zip(lm[:, 0].astype(int).tolist(), lm[:, 1:]))
    gt_t, gt_p, gt_q = read_gt(mav0)
    i = np.searchsorted(gt_t, t_exp, "right") - 1
    assert i.min() >= 0 and i.max() < len(gt_t) - 1, "exposure outside the written GT"
    a = (t_exp - gt_t[i]) / (gt_t[i + 1] - gt_t[i])
    R0, R1 = Rotation.from_quat(gt_q[i]), Rotation.from_quat(gt_q[i + 1])
    R_w_b = R0 * Rotation.from_rotvec(a[:, None] * (R0.inv() * R1).as_rotvec())
    p_w_b = gt_p[i] + a[:, None] * (gt_p[i + 1] - gt_p[i])
    T_b_c = read_camera_yaml(mav0 / "cam0" / "sensor.yaml").T_b_c
    R_w_c = R_w_b.as_matrix() @ T_b_c.rotation().matrix()
    p_w_c = p_w_b + R_w_b.apply(np.array(T_b_c.translation()))
    P = np.array([p_by_id[k] for k in ids.tolist()])
    p_c = np.einsum("nji,nj->ni", R_w_c[frame], P - p_w_c[frame])
    return p_c[:, :2] / p_c[:, 2:]


# ---------------------------------------------------------------- tests
@pytest.mark.parametrize("name", ["v102_clean", "mh03_clean"])
def test_files_parse_and_cover(name, request):
    res = request.getfixturevalue(name)
    mav0 = res.out / "mav0"
    src = GT_DIR / ("V1_02_medium" if name.startswith("v102") else "MH_03_medium") / "mav0"
    cam = (mav0 / "cam0/data.csv").read_text().splitlines()
    assert cam[0] == "#timestamp [ns],filename"
    stamps = np.array([int(s.split(",")[0]) for s in cam[1:]], dtype=np.int64)
    assert np.array_equal(stamps, res.t_ns) and len(stamps) in (200, 201)
    assert np.all(np.diff(stamps) == 50_000_000)  # regular 20 Hz grid
    t, f, i, uv = read_features(mav0 / "cam0/features.csv")
    assert np.array_equal(t, stamps[f]) and np.all(np.diff(f) >= 0)
    np.testing.assert_allclose(uv, res.uv, atol=1e-11)
    assert (mav0 / "cam0/sensor.yaml").read_bytes() == (src / "cam0/sensor.yaml").read_bytes()
    imu_t = np.array([int(s.split(",")[0]) for s in data_lines(mav0 / "imu0/data.csv")])
    lo, hi = min(stamps[0], stamps[0] + res.td_ns), max(stamps[-1], stamps[-1] + res.td_ns)
    assert imu_t[0] <= lo - 50_000_000 and imu_t[-1] >= hi + 50_000_000  # IMU margin both sides
    gt_t = read_gt(mav0)[0]
    assert gt_t[0] <= min(stamps[0], stamps[0] + res.td_ns) and gt_t[-1] >= max(stamps[-1], stamps[-1] + res.td_ns)
    truth = yaml.safe_load((res.out / "sim_truth.yaml").read_text())
    assert truth["td_ns"] == res.td_ns and truth["n_observations"] == len(t)
    ds = load_euroc(res.out)  # the project's own reader accepts the folder
    assert ds.kind == "features" and len(ds.features) == len(stamps)


@pytest.mark.parametrize("name", ["v102_clean", "mh03_clean"])
def test_features_per_frame_and_tracks(name, request):
    res = request.getfixturevalue(name)
    fpf = res.features_per_frame
    assert fpf.max() <= 40 and 30 <= fpf.mean() <= 40, f"features/frame mean {fpf.mean():.1f}"
    assert res.n_visible.mean() >= 40, "room too sparse for the cap"
    tl = res.track_lengths
    # geometric early losses plus persistent tracks (the calibration test checks the mix)
    assert 5 <= np.median(tl) <= 25 and tl.max() >= 40, (np.median(tl), tl.max())
    for lid in np.unique(res.landmark_id)[::7]:  # a lost track never resumes under its old id
        frames = res.frame_idx[res.landmark_id == lid]
        assert np.all(np.diff(frames) == 1), f"id {lid} has gaps: {frames}"


@pytest.mark.parametrize("name", ["v102_clean", "mh03_clean"])
def test_noise_free_reprojection_at_stamp_plus_td(name, request):
    res = request.getfixturevalue(name)
    t, f, i, uv = read_features(res.out / "mav0/cam0/features.csv")
    err_td = np.abs(reproject(res.out, res.t_ns + res.td_ns, f, i) - uv).max()
    assert err_td < 1e-9, f"max error at stamp+td {err_td:.2e}"
    err_stamp = np.median(np.abs(reproject(res.out, res.t_ns, f, i) - uv))
    err_wrong_sign = np.median(np.abs(reproject(res.out, res.t_ns - res.td_ns, f, i) - uv))
    assert err_stamp > 1e4 * err_td and err_stamp > 1e-5, f"td invisible: {err_stamp:.2e}"
    assert err_wrong_sign > 1.5 * err_stamp  # twice the offset -> about twice the error


def test_noise_and_outliers(v102_noisy, v102_clean):
    res, clean = v102_noisy, v102_clean
    # the same seed gives the same tracks: noise and outliers use their own random streams
    assert np.array_equal(res.frame_idx, clean.frame_idx)
    assert np.array_equal(res.landmark_id, clean.landmark_id)
    np.testing.assert_allclose(res.uv_true, clean.uv, atol=1e-12)
    fx, fy = 458.654, 457.296
    d_px = (res.uv - res.uv_true) * [fx, fy]
    kind = res.outlier_kind
    inl = d_px[kind == 0]
    assert abs(inl.std() - 0.8) < 0.05 and np.abs(inl.mean(0)).max() < 0.05
    rate = np.count_nonzero(kind) / len(kind)
    assert 0.014 <= rate <= 0.026, f"outlier rate {rate:.4f}"
    disp = np.linalg.norm(d_px[kind == 1], axis=1)
    assert disp.min() > 10 - 4 and disp.max() < 50 + 4
    assert np.count_nonzero(kind == 2) >= 2 and np.count_nonzero(kind == 2) % 2 == 0
    for j in np.flatnonzero(kind == 2):  # swapped: matches another swapped point of the same frame
        mates = np.flatnonzero((res.frame_idx == res.frame_idx[j]) & (kind == 2))
        d = np.linalg.norm((res.uv_true[mates] - res.uv[j]) * [fx, fy], axis=1)
        assert d.min() < 5 and np.linalg.norm(d_px[j]) >= 10 - 4
    truth = yaml.safe_load((res.out / "sim_truth.yaml").read_text())
    listed = {(f, i) for f, i, _ in truth["outliers"]}
    assert listed == set(zip(res.frame_idx[kind > 0].tolist(), res.landmark_id[kind > 0].tolist()))


def test_deterministic_for_a_seed(v102_noisy, tmp_path):
    generate_tracks(GT_DIR / "V1_02_medium", tmp_path / "a", NOISY)
    for rel in ("mav0/cam0/features.csv", "landmarks.csv", "sim_truth.yaml", "mav0/imu0/data.csv"):
        a = (tmp_path / "a" / rel).read_text()
        b = (v102_noisy.out / rel).read_text()
        assert a == b.replace(str(v102_noisy.out), str(tmp_path / "a")), rel
    other = generate_tracks(GT_DIR / "V1_02_medium", tmp_path / "b", dataclasses.replace(NOISY, seed=2))
    assert not np.array_equal(other.uv[:100], v102_noisy.uv[:100])


def test_config_strict():
    cfg = from_dict(TrackGenConfig, {"td_s": -0.003, "outlier_px": [5, 20], "duration_s": 60})
    assert cfg.td_s == -0.003 and cfg.outlier_px == (5.0, 20.0) and cfg.duration_s == 60.0
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(TrackGenConfig, {"td": 0.1})
    with pytest.raises(ConfigError, match="noise_px"):
        from_dict(TrackGenConfig, {"noise_px": -1.0})


@needs_data
def test_bad_input_names_file_and_line(tmp_path):
    src = tmp_path / "src" / "mav0"
    (src / "cam0").mkdir(parents=True)
    (src / "imu0").mkdir()
    shutil.copyfile(GT_DIR / "V1_02_medium/mav0/cam0/sensor.yaml", src / "cam0/sensor.yaml")
    (src / "imu0/data.csv").write_text("#t,wx,wy,wz,ax,ay,az\n1000,0,0,0,0,0,9.8\n2000,0,0,x,0,0,9.8\n")
    with pytest.raises(DataError, match=r"imu0/data\.csv:3: "):
        generate_tracks(src.parent, tmp_path / "out", TrackGenConfig())
    (src / "imu0/data.csv").write_text("#t,wx,wy,wz,ax,ay,az\n1000,0,0,0,0,0,9.8\n2000,0,0,0,0,0,9.8\n")
    with pytest.raises(DataError, match="state_groundtruth_estimate0"):
        generate_tracks(src.parent, tmp_path / "out", TrackGenConfig())


@needs_data
def test_cli(tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="vio")
    tracks_cli.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["tracks", str(GT_DIR / "V2_01_easy"), str(tmp_path / "o"), "--start", "30",
                              "--seconds", "2", "--td", "-0.004", "--seed", "3", "--noise-px", "0.5"])
    assert tracks_cli.run(args) == 0
    truth = yaml.safe_load((tmp_path / "o/sim_truth.yaml").read_text())
    assert truth["td_ns"] == -4_000_000 and truth["seed"] == 3 and truth["noise_px"] == 0.5
    assert truth["config"]["duration_s"] == 2.0 and "features/frame" in capsys.readouterr().out
    args = parser.parse_args(["tracks", str(GT_DIR / "V2_01_easy"), str(tmp_path / "o"),
                              "--outliers", "0.9"])
    assert tracks_cli.run(args) == 2 and "outlier_rate" in capsys.readouterr().err


def _track_stats(landmark_id: np.ndarray) -> tuple[float, float]:
    """Median track length and the mean length of the track an observation belongs to."""
    _, n = np.unique(landmark_id, return_counts=True)
    return float(np.median(n)), float(np.repeat(n, n).mean())


def test_track_lifetimes_are_calibrated_on_real_klt_tracks(tmp_path):
    """On the first 30 s of V1_01 the generator's lifetimes resemble the real EqVIO KLT
    tracks shipped with it (median 15 frames, observation-weighted mean 124): half the
    tracks persist while visible. Geometric lifetimes alone made them 5x shorter."""
    src = shared("euroc_V1_01_30s_features")
    real = np.loadtxt(src / "mav0/cam0/features.csv", delimiter=",", skiprows=1)[:, 2].astype(int)
    med_real, w_real = _track_stats(real)
    assert med_real == 15 and 120 < w_real < 130
    med, w = _track_stats(generate_tracks(src, tmp_path / "p", TrackGenConfig(seed=1)).landmark_id)
    assert 10 <= med <= 20 and 0.6 * w_real < w < 1.2 * w_real, (med, w)
    geo = generate_tracks(src, tmp_path / "g", TrackGenConfig(seed=1, persistent_fraction=0.0))
    assert _track_stats(geo.landmark_id)[1] < 0.3 * w_real


@needs_data
def test_boxwall_variant_from_the_cli(tmp_path):
    """``--variant boxwall`` (issue 20's generator): 60 random tracks per frame on the walls
    of a box 2.5 m beyond the flight envelope, geometric lifetimes (3% loss per frame, no
    persistent tracks), 1% displaced outliers (no swaps), the raw ground truth written
    verbatim; an explicit option still overrides the variant."""
    parser = argparse.ArgumentParser(prog="vio")
    tracks_cli.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["tracks", str(GT_DIR / "V2_01_easy"), str(tmp_path / "o"), "--start", "30",
                              "--seconds", "10", "--variant", "boxwall", "--seed", "4", "--td", "0.012"])
    cfg = tracks_cli.config_from_args(args)
    assert cfg.selection == "random" and cfg.max_features == 60 and not cfg.imu_consistent
    assert cfg.td_s == 0.012 and cfg.n_clutter_boxes == 0 and cfg.swap_fraction == 0.0
    res = generate_tracks(GT_DIR / "V2_01_easy", tmp_path / "o", cfg)
    fpf = res.features_per_frame
    assert fpf.min() >= 55 and fpf.mean() > 59
    assert set(np.unique(res.outlier_kind)) <= {0, 1}
    n_out = np.count_nonzero(res.outlier_kind)
    assert 0.005 * len(res.frame_idx) < n_out < 0.02 * len(res.frame_idx)
    err = np.linalg.norm(res.uv - res.uv_true, axis=1)[res.outlier_kind == 1] * 458.654
    assert err.max() < 47 and np.median(err) > 10
    # every landmark lies on the box (no clutter): one coordinate at a face
    p = res.landmark_p_w
    lo, hi = p.min(0), p.max(0)
    on_face = np.any(np.isclose(p, lo, atol=1e-9) | np.isclose(p, hi, atol=1e-9), axis=1)
    assert on_face.all()
    # raw ground truth: the source rows verbatim, not the IMU-fused trajectory
    rel = "mav0/state_groundtruth_estimate0/data.csv"
    src_rows = set((GT_DIR / "V2_01_easy" / rel).read_text().splitlines())
    out_rows = (tmp_path / "o" / rel).read_text().splitlines()
    assert len(out_rows) > 2000 and set(out_rows) <= src_rows


@needs_data
def test_random_selection_differs_from_the_grid(tmp_path):
    """``selection="random"`` picks new tracks uniformly: fewer image cells covered per
    frame than the grid picker on the same room and trajectory."""
    cells = {}
    for sel in ("grid", "random"):
        res = generate_tracks(GT_DIR / "V1_02_medium", tmp_path / sel,
                              TrackGenConfig(seed=1, selection=sel, **CLEAN))
        px = res.uv_true * 458.654 + [367.2, 248.4]
        c = (np.clip(px[:, 0] // (752 / 8), 0, 7) + 8 * np.clip(px[:, 1] // (480 / 5), 0, 4)).astype(int)
        cells[sel] = np.mean([len(np.unique(c[res.frame_idx == f])) for f in range(0, len(res.t_ns), 10)])
    assert cells["random"] < cells["grid"]
    with pytest.raises(ValueError, match="selection"):
        TrackGenConfig(selection="nearest")


def test_nearest_row_pose_interpolation():
    """``pose_interp="nearest"`` samples the raw ground truth at the nearest row (a cruder
    generator's camera poses); ``"slerp"`` interpolates between the bracketing rows."""
    from vio.sim.tracks import _render_times
    from vio.trajectory import interpolate_poses
    gt_t = np.array([0, 5, 10], np.int64) * 1_000_000
    p = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    q = np.tile([1.0, 0, 0, 0], (3, 1))
    t = np.array([1, 2, 3, 7, 9], np.int64) * 1_000_000

    def raw_poses(cfg):   # as generate_tracks takes them from the raw ground truth
        return interpolate_poses(gt_t, p, q, _render_times(cfg, gt_t, t))

    near, _ = raw_poses(TrackGenConfig(pose_interp="nearest"))
    np.testing.assert_allclose(near[:, 0], [0, 0, 1, 1, 2])
    np.testing.assert_array_equal(_render_times(TrackGenConfig(pose_interp="nearest"), gt_t, t) // 1_000_000,
                                  [0, 0, 5, 5, 10])   # the times the frames show (truth's render_offset_s)
    lin, _ = raw_poses(TrackGenConfig())
    np.testing.assert_allclose(lin[:, 0], [0.2, 0.4, 0.6, 1.4, 1.8])
    with pytest.raises(ValueError, match="pose_interp"):
        TrackGenConfig(pose_interp="cubic")


def test_one_respect_variants_differ_from_ours_in_one_group_of_settings():
    """Every ``one:*`` variant sets only settings boxwall sets too, to boxwall's values, and
    no two ``one:*`` variants share a setting: together they make up boxwall."""
    from vio.sim.variants import VARIANTS
    ones = {k: v for k, v in VARIANTS.items() if k.startswith("one:")}
    assert len(ones) >= 6
    keys = [set(v) for v in ones.values()]
    assert set().union(*keys) == set(VARIANTS["boxwall"])
    assert sum(len(k) for k in keys) == len(set().union(*keys))
    for v in ones.values():
        assert all(VARIANTS["boxwall"][k] == x for k, x in v.items())
        TrackGenConfig(**v)
