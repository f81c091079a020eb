"""Rerun sink: entity paths and contents read back from .rrd files, track lengths,
ground-truth alignment, and the ``vio run --rrd`` / ``vio plan`` wiring."""

from __future__ import annotations

import dataclasses
import math
import re
import tempfile
from collections import defaultdict
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from conftest import shared
from vio.conventions import quat_wxyz_from_rot
from vio.frontend.camera import Camera
from vio.io.types import CameraCalib, FeatureFrame, GroundTruth, ImuData
from vio.pipeline import FrameOutput
from vio.sync import FramePacket
from vio.viz import (ENTITIES, EventLog, GroundTruthAligner, RerunConfig, RerunSink, TrackLengths,
                     fit_yaw_translation)
from vio.viz_state import LandmarkMap, Segments, TrackTrails

T0 = 1_403_715_273_262_142_976
DT = 50_000_000
# camera looking along body +x: cam x = -body y, cam y = -body z, cam z = body x
CAM = CameraCalib(gtsam.Pose3(gtsam.Rot3(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])),
                              np.array([0.05, 0.0, 0.0])),
                  (400.0, 400.0, 320.0, 240.0), "radial-tangential", (-0.2, 0.05, 1e-4, -1e-4),
                  (640, 480))
YAW_GT, T_GT = 0.7, np.array([1.5, -2.0, 0.3])   # estimate world = Rz(YAW_GT) * gt world + T_GT


def _rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def _scene(n: int = 30, images: bool = True) -> tuple[list[FrameOutput], GroundTruth]:
    """Body on a 2 m circle facing along its tangent, landmarks on a 5 m cylinder."""
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 80)
    lms = np.column_stack([5 * np.cos(ang), 5 * np.sin(ang), rng.uniform(-1, 1, 80)])
    cam = Camera(CAM)
    outs, gt_p, gt_q = [], [], []
    for k in range(n):
        a = 0.05 * k
        T_w_b = gtsam.Pose3(gtsam.Rot3.Yaw(a + np.pi / 2), np.array([2 * np.cos(a), 2 * np.sin(a), 0.1]))
        T_w_c = T_w_b.compose(CAM.T_b_c)
        p_c = np.array([T_w_c.transformTo(p) for p in lms])
        px = cam.project(p_c)
        vis = np.flatnonzero((p_c[:, 2] > 0.5) & cam.in_image(px))
        uv = p_c[vis, :2] / p_c[vis, 2:]
        t = T0 + k * DT
        ff = FeatureFrame(t, vis.astype(np.int64), uv, np.zeros_like(uv), np.full(len(vis), np.nan))
        img = (np.arange(480 * 640, dtype=np.uint32).reshape(480, 640) % 251).astype(np.uint8)
        pkt = FramePacket(k, t, t, ImuData(np.array([t]), np.zeros((1, 3)), np.zeros((1, 3))), ff,
                          images=(img,) if images else ())
        kf = k % 3 == 0
        bias = gtsam.imuBias.ConstantBias(np.array([0.001 * k, 0.002, 0.003]),  # (accel, gyro)
                                          np.array([0.1, 0.2, 0.3]))
        outs.append(FrameOutput(
            index=k, t_ns=t, T_w_b=T_w_b, v_w=np.zeros(3), bias=bias, keyframe=kf, still=False,
            seconds=0.002, n_features=len(vis), n_landmarks=40, td_s=0.001, T_b_c=CAM.T_b_c,
            landmark_ids=vis if kf else None, landmarks_w=lms[vis] if kf else None, features=ff,
            packet=pkt))
        R_gt = _rz(-YAW_GT) @ T_w_b.rotation().matrix()
        gt_p.append(_rz(-YAW_GT) @ (T_w_b.translation() - T_GT))
        gt_q.append(quat_wxyz_from_rot(gtsam.Rot3(R_gt)))
    t_gt = T0 + np.arange(n, dtype=np.int64) * DT
    return outs, GroundTruth(t_gt, np.array(gt_p), np.array(gt_q))


def read_rrd(path: Path) -> dict[str, list[dict]]:
    """Entity path (no leading '/') -> list of rows (column name -> value) from the file."""
    rows: dict[str, list[dict]] = defaultdict(list)
    for ch in RrdReader(path).stream():
        d = ch.to_record_batch().to_pydict()
        n = len(next(iter(d.values())))
        for i in range(n):
            rows[ch.entity_path.lstrip("/")].append({k: v[i] for k, v in d.items()})
    return rows


def _views(chunks) -> tuple[dict[str, list[str]], list[str]]:
    views: dict[str, list[str]] = defaultdict(list)
    tracked: list[str] = []
    for ch in chunks:
        d = ch.to_record_batch().to_pydict()
        if "ViewBlueprint:class_identifier" in d:
            views[d["ViewBlueprint:class_identifier"][0][0]].append(d["ViewBlueprint:space_origin"][0][0])
        if "EyeControls3D:tracking_entity" in d:
            tracked.append(d["EyeControls3D:tracking_entity"][0][0])
    return views, tracked


def read_blueprint(path: Path) -> tuple[dict[str, list[str]], list[str]]:
    """Default blueprint in a .rrd: view class -> origins, and the entities the 3D eyes track."""
    r = RrdReader(path)
    return _views(r.stream(store=r.blueprints()[0]))


def read_blueprint_of(sink: RerunSink) -> tuple[dict[str, list[str]], list[str]]:
    """The same for a sink that has not written any file (its blueprint object)."""
    rec = rr.RecordingStream("bp")
    mem = rec.memory_recording()
    rec.send_blueprint(sink.blueprint)
    sink.close()
    path = Path(tempfile.mkdtemp()) / "bp.rrd"
    path.write_bytes(mem.drain_as_bytes())
    return read_blueprint(path)


def polyline(strips) -> np.ndarray:
    """The (N, 3) polyline of a trajectory logged as N - 1 two-point strips."""
    a = np.array([np.array(t) for t in strips])
    return np.concatenate([a[:, 0], a[-1:, 1]])


def scalars(rows: list[dict]) -> list[dict]:
    """The rows of a plot entity that hold a value (not its static style)."""
    return [r for r in rows if r.get("Scalars:scalars") is not None]


def latest(rows: list[dict], column: str):
    """Value of ``column`` in the row with the largest frame index."""
    return max((r for r in rows if r.get(column) is not None), key=lambda r: r["frame"])[column]


# ------------------------------------------------------------------ units
def test_track_lengths_count_consecutive_appearances():
    tl = TrackLengths()
    np.testing.assert_array_equal(tl.update(np.array([5, 1, 9])), [1, 1, 1])
    np.testing.assert_array_equal(tl.update(np.array([9, 5, 7])), [2, 2, 1])
    np.testing.assert_array_equal(tl.update(np.array([7, 1, 9])), [2, 1, 3])   # 1 came back: reset
    np.testing.assert_array_equal(tl.update(np.zeros(0, np.int64)), [])
    np.testing.assert_array_equal(tl.update(np.array([9])), [1])


def test_fit_yaw_translation_recovers_a_rigid_4dof_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R, t = _rz(-2.5), np.array([0.3, 4.0, -1.0])
    Rf, tf = fit_yaw_translation(src, src @ R.T + t)
    np.testing.assert_allclose(Rf, R, atol=1e-12)
    np.testing.assert_allclose(tf, t, atol=1e-12)


def test_aligner_interpolates_and_rejects_outside_or_gaps():
    gt = GroundTruth(np.array([0, 10, 20, 500_000_000]), np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0],
                                                                   [3, 0, 0]]), np.tile([1.0, 0, 0, 0], (4, 1)))
    al = GroundTruthAligner(gt, max_gap_s=0.1)
    np.testing.assert_allclose(al.position(15), [1.5, 0, 0])
    np.testing.assert_allclose(al.position(20), [2, 0, 0])
    assert al.position(-1) is None and al.position(600_000_000) is None
    assert al.position(300_000_000) is None                     # 0.48 s gap


def test_config_rejects_bad_rates():
    with pytest.raises(ValueError, match="strip_every"):
        RerunConfig(strip_every=0)
    with pytest.raises(ValueError, match="jpeg_quality"):
        RerunConfig(jpeg_quality=0)


# ---------------------------------------------------------- synthetic run
def test_sink_writes_every_entity(tmp_path):
    outs, gt = _scene(30)
    rrd = tmp_path / "run.rrd"
    with RerunSink(rrd=rrd, groundtruth=gt, cam=CAM, cfg=RerunConfig(strip_every=7, segment_len=12)) as sink:
        for o in outs:
            sink(o)
    rows = read_rrd(rrd)
    missing = [e for e in ENTITIES if not rows.get(e)]
    assert not missing, f"entities absent from the .rrd: {missing}"
    assert sorted(r["frame"] for r in rows["world/body"]) == list(range(30))
    # the first frame's time (initialization) is an event, not a plot point
    assert len(scalars(rows["metrics/timing/frame_ms"])) == 29
    assert len(scalars(rows["metrics/timing/keyframe_ms"])) == 9                      # frames 3, 6, ..., 27
    np.testing.assert_allclose(latest(rows["metrics/accel_bias/x"], "Scalars:scalars"), [0.029])
    np.testing.assert_allclose(latest(rows["metrics/velocity/norm"], "Scalars:scalars"), [0.0])
    # the trajectory is logged every frame, in segments of 12 sharing their end points
    seg = {e: rows[e] for e in rows if e.startswith("world/trajectory/estimate/")}
    assert sorted(seg) == [f"world/trajectory/estimate/{k}" for k in range(3)]
    assert sum(len(r) for r in seg.values()) == 29                            # frames 1..29
    strip = np.concatenate([polyline(latest(seg[f"world/trajectory/estimate/{k}"],
                                            "LineStrips3D:strips"))[(k > 0):] for k in range(3)])
    np.testing.assert_allclose(strip, [o.T_w_b.translation() for o in outs], atol=1e-6)
    # ground truth (exact rigid copy in another world) lands on the estimate
    gt_strip = polyline(latest(rows["world/trajectory/groundtruth"], "LineStrips3D:strips"))
    np.testing.assert_allclose(gt_strip, strip, atol=1e-5)
    np.testing.assert_allclose(sink.aligner.R, _rz(YAW_GT), atol=1e-9)
    np.testing.assert_allclose(sink.aligner.t, T_GT, atol=1e-9)
    # images (JPEG) every 3rd frame by default, with the features and trails of that frame
    img = rows["world/body/cam0/image"]
    assert sorted(r["frame"] for r in img) == list(range(0, 30, 3))
    assert all(r["EncodedImage:media_type"] == ["image/jpeg"] for r in img)
    feats = rows["world/body/cam0/image/features"]
    assert sorted(r["frame"] for r in feats) == list(range(0, 30, 3))
    px = np.array(latest(feats, "Points2D:positions"))
    np.testing.assert_allclose(px, Camera(CAM).project_normalized(outs[27].features.uv), atol=1e-3)
    trails = latest(rows["world/body/cam0/image/tracks"], "LineStrips2D:strips")
    assert len(trails) > 10 and max(len(t) for t in trails) == RerunConfig().trail_len
    assert min(len(t) for t in trails) >= 2
    assert np.max(latest(feats, "Points2D:radii")) < 0                          # UI points
    # landmarks leaving the window accumulate in the map; the window is shown apart
    window = np.array(latest(rows["world/map/window"], "Points3D:positions"))
    assert len(window) == len(outs[27].landmarks_w)
    gone = set().union(*(set(a.landmark_ids) - set(b.landmark_ids) for a, b in
                         zip(outs[0:28:3], outs[3:30:3])))
    marg = np.array(latest(rows["world/map/marginalized/0"], "Points3D:positions"))
    assert len(marg) == len(gone) > 5


def test_blueprint_views(tmp_path):
    """The default blueprint lays out the 3D view following the body, both cameras,
    one plot per meaning (with ground truth: its error) and the event log."""
    outs, gt = _scene(4)                               # keyframes 0 and 3
    rrd = tmp_path / "bp.rrd"
    with RerunSink(rrd=rrd, groundtruth=gt, cam=CAM, cam1=CAM) as sink:
        for o in outs:
            sink(o)
    views, tracked = read_blueprint(rrd)
    assert views["3D"] == ["world", "world"]                  # following the body; overview
    assert sorted(views["2D"]) == ["cam1/image", "world/body/cam0/image"]
    assert sorted(views["TimeSeries"]) == sorted(f"metrics/{p}" for p in (
        "timing", "counts", "velocity", "gyro_bias", "accel_bias", "td", "gt_error"))
    assert views["TextLog"] == ["events"]
    # the eyes track invisible framing points: static around the body, and at the centre
    # of the trajectory's bounding box on keyframes
    assert sorted(tracked) == ["world/body/follow", "world/overview_frame"]
    rows = read_rrd(rrd)
    assert len(rows["world/body/follow"]) == 1
    c = np.mean(latest(rows["world/overview_frame"], "Points3D:positions"), axis=0)
    p = np.array([o.T_w_b.translation() for o in outs])
    np.testing.assert_allclose(c, (p.min(0) + p.max(0)) / 2, atol=1e-5)
    mono, _ = read_blueprint_of(RerunSink(cam=CAM))
    assert mono["2D"] == ["world/body/cam0/image"] and "metrics/gt_error" not in mono["TimeSeries"]


def test_events_forward_vio_log_records(tmp_path):
    """INFO and above of the ``vio`` loggers reach the ``events`` TextLog, stamped with
    the next logged frame; the handler is removed and the logger level restored at close."""
    import logging
    outs, _ = _scene(4)
    lg = logging.getLogger("vio.sync")
    level0 = logging.getLogger("vio").level
    rrd = tmp_path / "ev.rrd"
    with RerunSink(rrd=rrd, cam=CAM) as sink:
        sink(outs[0])
        lg.warning("IMU gap of %.2f s bridged", 0.25)
        lg.debug("not shown")
        logging.getLogger("vio.pipeline").info("restart")
        logging.getLogger("other").warning("not ours")
        sink(outs[1])
    rows = read_rrd(rrd)["events"]
    logged = {(r["frame"], r["TextLog:level"][0], r["TextLog:text"][0]) for r in rows}
    assert (1, "WARN", "vio.sync: IMU gap of 0.25 s bridged") in logged
    assert (1, "INFO", "vio.pipeline: restart") in logged
    assert not any("not shown" in t or "not ours" in t for _, _, t in logged)
    assert any(f == 0 and "initialization" in t for f, _, t in logged)
    assert logging.getLogger("vio").level == level0
    assert not any(isinstance(h, EventLog) for h in logging.getLogger("vio").handlers)


def test_stereo_matches_and_disparity(tmp_path):
    outs, _ = _scene(3)
    o = outs[0]
    ff = o.features
    right = ff.uv - np.array([0.05, 0.0])
    right[::2] = np.nan                                  # every other feature unmatched
    ff = dataclasses.replace(ff, right_uv=right)
    pkt = dataclasses.replace(o.packet, features=ff, images=(o.packet.images[0],) * 2)
    rrd = tmp_path / "st.rrd"
    with RerunSink(rrd=rrd, cam=CAM, cam1=CAM) as sink:
        sink(dataclasses.replace(o, features=ff, packet=pkt))
    rows = read_rrd(rrd)
    assert len(rows["cam1/image"]) == 1
    m = np.array(rows["cam1/image/matches"][0]["Points2D:positions"])
    cam = Camera(CAM)
    np.testing.assert_allclose(m, cam.project_normalized(right[1::2]), atol=1e-3)
    lines = rows["cam1/image/disparity"][0]["LineStrips2D:strips"]
    np.testing.assert_allclose(np.array(lines[0]), cam.project_normalized(
        np.stack([right[1], ff.uv[1]])), atol=1e-3)


def test_direct_points_come_with_their_keyframe_image(tmp_path):
    """In direct/hybrid modes every keyframe's image is logged (with its photometric
    points), besides the regular rate; the points are cleared with the next image."""
    from vio.direct.source import PointSnapshot
    outs, _ = _scene(10)
    snap = PointSnapshot(0, 0, np.array([[0.0, 0.0]]), np.array([1.0]), np.array([True]), np.array([0.5]))
    rrd = tmp_path / "d.rrd"
    with RerunSink(rrd=rrd, cam=CAM, cfg=RerunConfig(image_every=4)) as sink:
        sink.add_direct_source(lambda: snap)
        for o in outs:
            sink(o)
    rows = read_rrd(rrd)
    assert sorted(r["frame"] for r in rows["world/body/cam0/image"]) == [0, 3, 4, 6, 8, 9]
    pts = rows["world/body/cam0/image/direct_points"]
    shown = sorted(r["frame"] for r in pts if r.get("Points2D:positions") is not None)
    cleared = sorted(r["frame"] for r in pts if r.get("Points2D:positions") is None)
    assert shown == [0, 3, 6, 9] and cleared == [4, 8]


def test_recording_size_of_real_stereo_images(tmp_path):
    """Default rates on real MH_01 pairs: a 30-s 20-Hz stereo run stays under 30 MB
    (the JPEG images are most of it), and compaction leaves a few chunks."""
    from vio.io.euroc import load_euroc
    data = load_euroc(shared("euroc_MH_01_stereo_synimu"))
    n = 24
    outs, _ = _scene(n, images=False)
    rrd = tmp_path / "size.rrd"
    with RerunSink(rrd=rrd, cam=CAM, cam1=CAM) as sink:
        for o, f0, f1 in zip(outs, data.cam0.files, data.cam1.files):
            pkt = dataclasses.replace(o.packet, image_files=(f0, f1))
            sink(dataclasses.replace(o, packet=pkt))
    per_frame = rrd.stat().st_size / n
    assert per_frame * 600 < 30e6, f"{per_frame / 1e3:.0f} kB per frame"
    raw = 752 * 480 * 2 / RerunConfig().image_every
    assert per_frame < raw / 4, (per_frame, raw)                           # JPEG, not raw
    rows = read_rrd(rrd)
    assert len(rows["cam1/image"]) == len(rows["world/body/cam0/image"]) == n // 3
    n_chunks = sum(1 for _ in RrdReader(rrd).stream())
    assert n_chunks < 60, n_chunks


def test_feature_only_frames_log_no_image_and_memory_default():
    outs, _ = _scene(5, images=False)
    sink = RerunSink(cam=CAM)           # neither viewer nor file: in-memory recording
    for o in outs:
        sink(o)
    sink.close()
    sink.close()                         # idempotent
    data = sink.memory.drain_as_bytes()
    assert len(data) > 1000
    with pytest.raises(RuntimeError, match="closed"):
        sink(outs[0])


def test_image_files_are_loaded_and_missing_files_only_warn(tmp_path, caplog):
    outs, _ = _scene(4, images=False)
    png = tmp_path / "f.png"
    cv2.imwrite(str(png), np.full((480, 640), 77, np.uint8))
    files = [(png,), (png,), (tmp_path / "missing.png",), (png,)]
    rrd = tmp_path / "img.rrd"
    with RerunSink(rrd=rrd, cam=CAM, cfg=RerunConfig(image_every=1, jpeg_quality=80)) as sink:
        for o, f in zip(outs, files):
            pkt = FramePacket(o.packet.index, o.t_ns, o.t_ns, o.packet.imu, o.features, image_files=f)
            sink(dataclasses.replace(o, packet=pkt))
    rows = read_rrd(rrd)
    assert sorted(r["frame"] for r in rows["world/body/cam0/image"]) == [0, 1]  # stops after the error
    assert "not logging images" in caplog.text


def test_compaction_failure_only_warns(tmp_path, caplog):
    from vio.viz_io import optimize_rrd
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not a recording")
    assert optimize_rrd(bad) is False
    assert bad.read_bytes() == b"not a recording" and "could not compact" in caplog.text
    assert list(tmp_path.iterdir()) == [bad]


def test_rrd_in_missing_directory_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        RerunSink(rrd=tmp_path / "nope" / "x.rrd")


# --------------------------------------------------------------- real data
def test_real_run_gt_alignment(tmp_path):
    from vio.evaluation import evaluate
    from vio.io.euroc import load_euroc
    from vio.pipeline import PipelineConfig
    from vio.run import run_dataset
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    rrd = tmp_path / "real.rrd"
    sink = RerunSink(rrd=rrd, groundtruth=data.groundtruth, cam=data.cam0.calib)
    res = run_dataset(data, PipelineConfig(), max_frames=200, sinks=[sink])
    sink.close()
    assert len(res.outputs) > 100
    rows = read_rrd(rrd)
    no_image = ("world/body/cam0/image", "world/body/cam0/image/tracks")
    missing = [e for e in ENTITIES if e not in no_image and not rows.get(e)]
    assert not missing, f"entities absent from the .rrd: {missing}"
    assert "world/body/cam0/image" not in rows            # feature-only dataset
    # without images the features are logged every frame
    assert len(rows["world/body/cam0/image/features"]) == len(res.outputs)
    segs = sorted((e for e in rows if e.startswith("world/trajectory/estimate/")), key=lambda e: int(e.split("/")[-1]))
    est = np.concatenate([polyline(latest(rows[e], "LineStrips3D:strips"))[(k > 0):] for k, e in enumerate(segs)])
    gt = polyline(latest(rows["world/trajectory/groundtruth"], "LineStrips3D:strips"))
    np.testing.assert_allclose(est, res.arrays()[1], atol=1e-5)   # float32 in the file
    # the logged ground truth is the aligner's final mapping of the true positions
    al = sink.aligner
    np.testing.assert_allclose(gt[0], al.R @ al.position(res.outputs[0].t_ns) + al.t, atol=1e-5)
    assert len(gt) == len(res.outputs)
    # 4-DoF aligned ground truth lies on the estimate: the estimator's own SE3-aligned
    # ATE over these 200 frames was 0.008 m; 0.05 m leaves room for the yaw-only fit.
    d = np.array([np.linalg.norm(al.R @ al.position(o.t_ns) + al.t - o.T_w_b.translation())
                  for o in res.outputs])
    ate = evaluate(*res.arrays(), data.groundtruth).ate_rmse
    rms = float(np.sqrt(np.mean(d ** 2)))
    assert rms < 0.05, f"aligned GT {rms:.3f} m RMS from the estimate (SE3 ATE {ate:.3f} m)"
    assert rms < 1.5 * ate + 0.01, (rms, ate)
    err = np.array([r["Scalars:scalars"][0] for r in scalars(rows["metrics/gt_error/error_m"])])
    assert len(err) == len(res.outputs) and np.median(err) < 0.05
    # the map of landmarks that left the window builds up over the run
    n_map = sum(len(latest(rows[e], "Points3D:positions")) for e in rows if e.startswith("world/map/marginalized/"))
    kfs = [set(o.landmark_ids.tolist()) for o in res.outputs if o.landmark_ids is not None]
    assert n_map == sum(len(a - b) for a, b in zip(kfs, kfs[1:])) > 20


def test_cli_run_writes_rrd(tmp_path, capsys):
    from vio.cli import main
    ds = shared("euroc_V1_01_30s_features")
    rrd = tmp_path / "cli.rrd"
    assert main(["run", str(ds), "--rrd", str(rrd), "--max-frames", "100", "--no-progress",
                 "--viz-image-every", "5", "--viz-jpeg-quality", "0"]) == 0
    n_est = int(re.search(r"(\d+) estimated", capsys.readouterr().out).group(1))
    assert rrd.stat().st_size > 10_000
    rows = read_rrd(rrd)
    needed = ["world/trajectory/estimate/0", "world/trajectory/groundtruth", "world/map/window",
              "world/body", "world/body/cam0", "metrics/timing/frame_ms", "metrics/counts/features",
              "metrics/gyro_bias/z", "metrics/td/td_ms", "metrics/timing/keyframe_ms", "events"]
    missing = [e for e in needed if not rows.get(e)]
    assert not missing, f"entities absent from the .rrd: {missing}"
    assert len(scalars(rows["metrics/counts/features"])) == len(rows["world/body"]) == n_est > 50
    # the pipeline's initialization message reached the event log
    assert any("initialization" in r["TextLog:text"][0] for r in rows["events"])


def test_cli_viz_flags_reach_the_sink(monkeypatch, tmp_path):
    """``--viz-image-every`` / ``--viz-jpeg-quality`` (0: raw) configure the sink."""
    import vio.viz
    from vio.cli import main
    seen = []

    class Fake:
        def __init__(self, **kw):
            seen.append(kw)

        def __call__(self, out):
            pass

        def close(self):
            pass

    monkeypatch.setattr(vio.viz, "RerunSink", Fake)
    ds = str(shared("euroc_V1_01_30s_features"))
    args = ["run", ds, "--rrd", str(tmp_path / "x.rrd"), "--max-frames", "3", "--no-progress"]
    assert main(args + ["--viz-image-every", "4", "--viz-jpeg-quality", "0"]) == 0
    assert main(args) == 0
    assert (seen[0]["cfg"].image_every, seen[0]["cfg"].jpeg_quality) == (4, None)
    assert seen[1]["cfg"] == RerunConfig() and seen[1]["cam1"] is None


# ------------------------------------------------------------- view state
def test_track_trails_keep_the_last_positions_of_unbroken_tracks():
    tt = TrackTrails(3)
    assert tt.update(np.array([1, 2]), np.array([[0.0, 0], [5, 5]])) == []
    out = tt.update(np.array([1, 3]), np.array([[1.0, 0], [9, 9]]))
    assert len(out) == 1 and np.array_equal(out[0], [[0, 0], [1, 0]])
    tt.update(np.array([1]), np.array([[2.0, 0]]))
    out = tt.update(np.array([1, 2]), np.array([[3.0, 0], [6, 6]]))     # 2 came back: new trail
    assert len(out) == 1 and np.array_equal(out[0], [[1, 0], [2, 0], [3, 0]])


def test_landmark_map_accumulates_leavers_in_bounded_chunks():
    m = LandmarkMap(max_points=4, chunk_size=2)
    up = m.update(np.array([1, 2, 3]), np.eye(3))
    assert up.chunk is None and len(up.window) == 3
    up = m.update(np.array([3, 4]), np.ones((2, 3)))                        # 1 and 2 left
    assert up.chunk[0] == 0 and np.array_equal(up.chunk[1], np.eye(3)[:2]) and up.dropped == ()
    up = m.update(np.array([5]), np.zeros((1, 3)))                          # 3 and 4 left
    assert up.chunk[0] == 1 and len(up.chunk[1]) == 2
    up = m.update(np.array([6]), np.zeros((1, 3)))                          # 5 left: evicts chunk 0
    assert up.chunk[0] == 2 and up.dropped == (0,) and m.n_marginalized == 3
    with pytest.raises(ValueError):
        LandmarkMap(max_points=1, chunk_size=2)


def test_segments_share_end_points():
    s = Segments(3)
    got = [s.append(np.full(3, float(i))) for i in range(5)]
    assert [k for k, _ in got] == [0, 0, 0, 1, 1]
    np.testing.assert_array_equal(got[-1][1][:, 0], [2, 3, 4])
