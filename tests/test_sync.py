"""Sensor sync: packet tiling, push-API outcomes, and IMU fidelity on real V1_02 data."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from conftest import shared
from vio.faults import ImuScreen, ImuScreenConfig
from vio.imu import integrate
from vio.io.euroc import load_euroc
from vio.io.types import ImuData
from vio.sync import Synchronizer, SyncStatus, packets
from vio.trajectory import interpolate_pose, interpolate_vector


def _imu(n: int = 101, rate: float = 200.0) -> ImuData:
    t = (np.arange(n) * (1e9 / rate)).astype(np.int64) + 1_000_000_000
    w = np.stack([np.sin(np.arange(n) * 0.1), np.zeros(n), np.ones(n)], 1)
    a = np.stack([np.arange(n) * 0.01, np.zeros(n), 9.81 * np.ones(n)], 1)
    return ImuData(t, w, a)


def test_packets_tile_the_imu_axis_with_exact_endpoints():
    imu = _imu()
    stamps = np.array([1_000_000_000 + k * 50_000_000 + 1_234_567 for k in range(9)])
    pk = list(packets(imu, stamps, td_s=0.002))
    assert len(pk) == 9
    assert pk[0].t_ns == stamps[0] + 2_000_000 and len(pk[0].imu) == 1
    for prev, cur in zip(pk[:-1], pk[1:]):
        assert cur.imu.t_ns[0] == prev.t_ns and cur.imu.t_ns[-1] == cur.t_ns
        assert np.all(np.diff(cur.imu.t_ns) > 0)
    # interpolated endpoint values are exact for a linear signal
    t = pk[3].imu.t_ns[-1]
    expect = (t - imu.t_ns[0]) / 5e6 * 0.01
    assert pk[3].imu.accel[-1, 0] == pytest.approx(expect, abs=1e-12)


def test_frames_a_td_moves_past_the_imu_are_skipped_with_a_warning(caplog):
    """A td that puts the last frames after the last IMU sample (the photometric modes'
    pre-pass, td feedback): those frames are not served, and each is named in a warning."""
    import logging
    imu = _imu()                                   # 1.0 .. 1.5 s
    stamps = np.array([1_000_000_000 + k * 50_000_000 for k in range(11)])   # .. 1.5 s
    with caplog.at_level(logging.WARNING, logger="vio.sync"):
        pk = list(packets(imu, stamps, td_s=0.03))
    assert len(pk) == 10 and pk[-1].stamp_ns == stamps[-2]
    assert f"frame {stamps[-1]}: IMU ended before" in caplog.text and "not processed" in caplog.text


def test_push_api_waiting_then_ready_and_dropped():
    imu = _imu(21)
    sync = Synchronizer()
    sync.add_frame(int(imu.t_ns[0]) - 1)          # before the IMU stream: never served
    sync.add_frame(int(imu.t_ns[10]) + 7)
    assert sync.poll().status is SyncStatus.WAITING
    for k in range(5):
        sync.add_imu(imu.t_ns[k], imu.gyro[k], imu.accel[k])
    assert sync.poll().status is SyncStatus.DROPPED
    assert sync.poll().status is SyncStatus.WAITING   # frame 2 needs IMU up to t10+7
    for k in range(5, 21):
        sync.add_imu(imu.t_ns[k], imu.gyro[k], imu.accel[k])
    res = sync.poll()
    assert res.status is SyncStatus.READY and res.packet.t_ns == imu.t_ns[10] + 7
    sync.add_frame(int(imu.t_ns[-1]) + 10)
    assert sync.poll().status is SyncStatus.WAITING
    sync.close()
    assert sync.poll().status is SyncStatus.DROPPED
    assert sync.poll().status is SyncStatus.EMPTY


def test_lookahead_waits_for_imu_past_the_frame_and_serves_it():
    imu = _imu(40)
    dt = int(imu.t_ns[1] - imu.t_ns[0])
    # the fault screen's own delay (3 samples) would exceed this lookahead: off here
    sync = Synchronizer(lookahead_s=2.5 * dt * 1e-9, screen=ImuScreen(ImuScreenConfig(enabled=False)))
    sync.add_frame(int(imu.t_ns[10]))
    sync.add_frame(int(imu.t_ns[38]))
    for k in range(13):                               # up to t10 + 2 dt: not enough
        sync.add_imu(imu.t_ns[k], imu.gyro[k], imu.accel[k])
    assert sync.poll().status is SyncStatus.WAITING
    sync.add_imu(imu.t_ns[13], imu.gyro[13], imu.accel[13])
    res = sync.poll()
    assert res.status is SyncStatus.READY
    ahead = res.packet.imu_ahead
    assert ahead.t_ns[0] == imu.t_ns[10] and ahead.t_ns[-1] == imu.t_ns[10] + int(2.5 * dt)
    np.testing.assert_allclose(ahead.gyro[1:3], imu.gyro[11:13])
    for k in range(14, 40):
        sync.add_imu(imu.t_ns[k], imu.gyro[k], imu.accel[k])
    assert sync.poll().status is SyncStatus.WAITING   # t38 + 2.5 dt is past the stream
    sync.close()                                      # closed: served with what there is
    res = sync.poll()
    assert res.status is SyncStatus.READY and res.packet.imu_ahead.t_ns[-1] == imu.t_ns[39]
    with pytest.raises(ValueError, match="lookahead"):
        Synchronizer(lookahead_s=-1.0)


def test_push_api_rejects_bad_samples():
    sync = Synchronizer()
    sync.add_imu(10, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="does not increase"):
        sync.add_imu(10, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        sync.add_imu(11, np.array([np.nan, 0, 0]), np.zeros(3))


def test_preintegrated_packets_match_ground_truth_on_real_v1_02():
    """Packets' IMU, preintegrated with GT biases, predicts GT motion between frames.

    Measured on 300 consecutive 50-ms intervals of real V1_02: position error max
    0.31 mm (median 0.09 mm), rotation error max 0.056 deg (median 0.013 deg);
    asserted: max < 1 mm / 0.1 deg, median < 0.2 mm / 0.03 deg.
    """
    data = load_euroc(shared("euroc_imu_gt", "V1_02_medium"))
    gt = data.groundtruth
    t0 = gt.t_ns[0] + 2_000_000_000
    stamps = t0 + np.arange(301, dtype=np.int64) * 50_000_000
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(9.81)
    pos_err, rot_err = [], []
    prev = None
    for pkt in packets(data.imu, stamps):
        if prev is not None:
            bias = gtsam.imuBias.ConstantBias(interpolate_vector(gt.t_ns, gt.ba, prev),
                                              interpolate_vector(gt.t_ns, gt.bg, prev))
            pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
            integrate(pim, pkt.imu)
            state = gtsam.NavState(interpolate_pose(gt, prev),
                                   interpolate_vector(gt.t_ns, gt.v_w, prev))
            pred = pim.predict(state, bias).pose()
            truth = interpolate_pose(gt, pkt.t_ns)
            err = truth.between(pred)
            pos_err.append(np.linalg.norm(pred.translation() - truth.translation()))
            rot_err.append(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(err.rotation()))))
        prev = pkt.t_ns
    assert len(pos_err) == 300
    assert max(pos_err) < 1e-3 and np.median(pos_err) < 2e-4
    assert max(rot_err) < 0.1 and np.median(rot_err) < 0.03


def test_td_source_shifts_the_frames_served_after_it_changes():
    """``packets(..., td_source=)``: each frame gets the td the source returns when it is
    served (the estimator's fed-back estimate); the IMU segments still tile the axis."""
    t = np.arange(0, 2_000_000_001, 5_000_000, dtype=np.int64)
    imu = ImuData(t, np.zeros((len(t), 3)), np.zeros((len(t), 3)))
    stamps = np.arange(100_000_000, 1_000_000_001, 50_000_000, dtype=np.int64)
    tds = iter([0.0] * 5 + [0.012] * 5 + [-0.007] * 100)
    pk = list(packets(imu, stamps, 0.0, td_source=lambda: next(tds)))
    assert len(pk) == len(stamps)
    off = np.array([p.t_ns - p.stamp_ns for p in pk])
    np.testing.assert_array_equal(off[:5], 0)
    np.testing.assert_array_equal(off[5:10], 12_000_000)
    np.testing.assert_array_equal(off[10:], -7_000_000)
    for a, b in zip(pk[:-1], pk[1:]):
        assert b.imu.t_ns[0] == a.t_ns and b.imu.t_ns[-1] == b.t_ns
    with pytest.raises(ValueError):
        Synchronizer().set_td(float("nan"))
