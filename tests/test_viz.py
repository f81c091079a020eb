"""Rerun sink: entity paths and contents read back from .rrd files, track lengths,
ground-truth alignment, and the ``vio run --rrd`` / ``vio plan`` wiring."""

from __future__ import annotations

import dataclasses
import math
import re
from collections import defaultdict
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest
from rerun.chunk import RrdReader

from conftest import shared
from vio.conventions import quat_wxyz_from_rot
from vio.frontend.camera import Camera
from vio.io.types import CameraCalib, FeatureFrame, GroundTruth, ImuData
from vio.pipeline import FrameOutput
from vio.sync import FramePacket
from vio.viz import (ENTITIES, GroundTruthAligner, RerunConfig, RerunSink, TrackLengths,
                     fit_yaw_translation)

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
    with RerunSink(rrd=rrd, groundtruth=gt, cam=CAM, cfg=RerunConfig(strip_every=7)) as sink:
        for o in outs:
            sink(o)
    rows = read_rrd(rrd)
    missing = [e for e in ENTITIES if not rows.get(e)]
    assert not missing, f"entities absent from the .rrd: {missing}"
    assert sorted(r["frame"] for r in rows["world/body"]) == list(range(30))
    assert len(rows["metrics/time_ms"]) == 30 and len(rows["metrics/keyframe"]) == 10 + 1  # + style
    np.testing.assert_allclose(latest(rows["metrics/accel_bias/x"], "Scalars:scalars"), [0.029])
    # the estimate strip at close holds every position, in order
    strip = np.array(latest(rows["world/trajectory/estimate"], "LineStrips3D:strips")[0])
    np.testing.assert_allclose(strip, [o.T_w_b.translation() for o in outs], atol=1e-6)
    # ground truth (exact rigid copy in another world) lands on the estimate
    gt_strip = np.array(latest(rows["world/trajectory/groundtruth"], "LineStrips3D:strips")[0])
    np.testing.assert_allclose(gt_strip, strip, atol=1e-5)
    np.testing.assert_allclose(sink.aligner.R, _rz(YAW_GT), atol=1e-9)
    np.testing.assert_allclose(sink.aligner.t, T_GT, atol=1e-9)
    # features of the last frame in distorted pixels, coloured by track length
    last = rows["world/body/cam0/image/features"]
    px = np.array(latest(last, "Points2D:positions"))
    np.testing.assert_allclose(px, Camera(CAM).project_normalized(outs[-1].features.uv), atol=1e-3)
    assert len(rows["world/body/cam0/image"]) == 30


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
    with RerunSink(rrd=rrd, cam=CAM, cfg=RerunConfig(jpeg_quality=80)) as sink:
        for o, f in zip(outs, files):
            pkt = FramePacket(o.packet.index, o.t_ns, o.t_ns, o.packet.imu, o.features, image_files=f)
            sink(dataclasses.replace(o, packet=pkt))
    rows = read_rrd(rrd)
    assert sorted(r["frame"] for r in rows["world/body/cam0/image"]) == [0, 1]  # stops after the error
    assert "not logging images" in caplog.text


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
    missing = [e for e in ENTITIES if e != "world/body/cam0/image" and not rows.get(e)]
    assert not missing, f"entities absent from the .rrd: {missing}"
    assert "world/body/cam0/image" not in rows            # feature-only dataset
    est = np.array(latest(rows["world/trajectory/estimate"], "LineStrips3D:strips")[0])
    gt = np.array(latest(rows["world/trajectory/groundtruth"], "LineStrips3D:strips")[0])
    np.testing.assert_allclose(est, res.arrays()[1], atol=1e-5)   # float32 in the file
    # the logged ground truth is the aligner's final mapping of the true positions
    al = sink.aligner
    i0 = np.searchsorted(data.groundtruth.t_ns, res.outputs[0].t_ns)
    np.testing.assert_allclose(gt[0], al.R @ data.groundtruth.p_w[i0] + al.t, atol=1e-5)
    # 4-DoF aligned ground truth lies on the estimate: the estimator's own SE3-aligned
    # ATE over these 200 frames was 0.008 m; 0.05 m leaves room for the yaw-only fit.
    d = np.array([np.linalg.norm(al.R @ al.position(o.t_ns) + al.t - o.T_w_b.translation())
                  for o in res.outputs])
    ate = evaluate(*res.arrays(), data.groundtruth).ate_rmse
    rms = float(np.sqrt(np.mean(d ** 2)))
    assert rms < 0.05, f"aligned GT {rms:.3f} m RMS from the estimate (SE3 ATE {ate:.3f} m)"
    assert rms < 1.5 * ate + 0.01, (rms, ate)
    err = np.array([r["Scalars:scalars"][0] for r in rows["metrics/gt_error_m"]])
    assert len(err) == len(res.outputs) and np.median(err) < 0.05


def test_cli_run_writes_rrd(tmp_path, capsys):
    from vio.cli import main
    ds = shared("euroc_V1_01_30s_features")
    rrd = tmp_path / "cli.rrd"
    assert main(["run", str(ds), "--rrd", str(rrd), "--max-frames", "100", "--no-progress"]) == 0
    n_est = int(re.search(r"(\d+) estimated", capsys.readouterr().out).group(1))
    assert rrd.stat().st_size > 10_000
    rows = read_rrd(rrd)
    needed = ["world/trajectory/estimate", "world/trajectory/groundtruth", "world/landmarks",
              "world/body", "world/body/cam0", "metrics/time_ms", "metrics/n_features",
              "metrics/gyro_bias/z", "metrics/td_ms", "metrics/keyframe"]
    missing = [e for e in needed if not rows.get(e)]
    assert not missing, f"entities absent from the .rrd: {missing}"
    # the buffered tail reached the file although cmd_run never closes the sink explicitly
    assert len(rows["metrics/time_ms"]) == len(rows["world/body"]) == n_est > 50
