"""Sensor faults: IMU screening and gaps (synthetic), the gap bridge and the divergence
monitor (units), and fault injection on a short real V1_01 stretch with bounded errors."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

from conftest import shared
from vio.backend.health import HealthConfig, HealthMonitor
from vio.faults import ImuScreen, ImuScreenConfig, screen_imu
from vio.imu import ImuNoiseConfig, bridge_params, integrate_still
from vio.io.types import ImuCalib, ImuData
from vio.sync import Synchronizer, SyncStatus, packets

NS = 1_000_000_000
T0 = 1_400_000_000 * NS


def _flight(seconds: float = 4.0, rate: float = 200.0, seed: int = 0) -> ImuData:
    """A vibrating flight: smooth motion, 0.5 m/s^2 / 0.03 rad/s white noise, readings
    quantized like the ADIS16448's."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate) + 1
    t = np.arange(n) / rate
    acc = np.c_[9.81 + 2 * np.sin(2 * t), np.cos(3 * t), 0.5 * np.sin(t)] + rng.normal(0, 0.5, (n, 3))
    gyr = np.c_[0.3 * np.sin(t), 0.2 * np.cos(2 * t), 0.1 + 0 * t] + rng.normal(0, 0.03, (n, 3))
    stamps = T0 + np.round(t * NS).astype(np.int64)
    return ImuData(stamps, np.round(gyr / 1.3e-3) * 1.3e-3, np.round(acc / 8.2e-3) * 8.2e-3)


def _with(imu: ImuData, i: int, accel=None, gyro=None) -> ImuData:
    a, w = imu.accel.copy(), imu.gyro.copy()
    if accel is not None:
        a[i] = accel
    if gyro is not None:
        w[i] = gyro
    return ImuData(imu.t_ns, w, a)


# ------------------------------------------------------------------ screening (synthetic)
def test_clean_vibrating_and_violent_coherent_motion_pass_the_screen():
    imu = _flight()
    _, gaps, n = screen_imu(imu)
    assert n == 0 and gaps == []
    # a landing-like 15-Hz, 30 m/s^2 oscillation is coherent over samples: not a spike
    t = (imu.t_ns - T0) * 1e-9
    shake = imu.accel + np.c_[30 * np.sin(2 * np.pi * 15 * t) * (t > 2), 0 * t, 0 * t]
    assert screen_imu(ImuData(imu.t_ns, imu.gyro, shake))[2] == 0
    # a still IMU (quantized readings, MAD 0) passes too
    still = ImuData(imu.t_ns, np.zeros_like(imu.gyro) + 1.3e-3, np.tile([9.81, 0, 0], (len(imu), 1)))
    assert screen_imu(still)[2] == 0


@pytest.mark.parametrize("accel,gyro", [((200.0, 0.0, 9.8), None), ((9.8, -40.0, 0.0), None),
                                        (None, (0.0, 3.0, 0.1))])
def test_single_spike_is_dropped_with_a_warning_naming_its_time(caplog, accel, gyro):
    imu = _with(_flight(), 401, accel, gyro)
    with caplog.at_level(logging.WARNING, logger="vio.faults"):
        out, gaps, n = screen_imu(imu)
    assert n == 1 and gaps == [] and len(out) == len(imu) - 1
    assert imu.t_ns[401] not in out.t_ns
    msg = caplog.text
    assert f"t={imu.t_ns[401]} ns" in msg and "2.005 s into the run" in msg and "dropped" in msg


def test_sensor_range_drops_out_of_range_samples_and_is_read_from_sensor_yaml(tmp_path):
    from vio.io.calib import read_imu_yaml
    imu = _with(_with(_flight(), 100, accel=(9.0, 0.0, 17.0)), 300, gyro=(0.0, 0.0, 5.0))
    _, _, n = screen_imu(imu, accel_range=16.0, gyro_range=4.0)
    assert n == 2
    y = tmp_path / "sensor.yaml"
    y.write_text("gyroscope_noise_density: 1.7e-4\ngyroscope_random_walk: 2.0e-5\n"
                 "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n"
                 "accelerometer_range: 176.5\ngyroscope_range: 17.45\n")
    c = read_imu_yaml(y)
    assert (c.accel_range, c.gyro_range) == (176.5, 17.45)
    y.write_text(y.read_text().replace("17.45", "-1"))
    with pytest.raises(Exception, match="gyroscope_range"):
        read_imu_yaml(y)


def test_streaming_screen_equals_the_batch_screen():
    imu = _with(_with(_flight(), 250, accel=(150.0, 0, 0)), 600, gyro=(4.0, 0, 0))
    batch, _, nb = screen_imu(imu)
    s, parts = ImuScreen(), []
    for i in range(0, len(imu), 7):            # ragged blocks, as a live feed delivers them
        s.push(ImuData(imu.t_ns[i:i + 7], imu.gyro[i:i + 7], imu.accel[i:i + 7]))
        parts.append(s.pop())
    parts.append(s.pop(final=True))
    t = np.concatenate([p.t_ns for p in parts])
    assert nb == s.n_dropped == 2
    np.testing.assert_array_equal(t, batch.t_ns)


def test_gap_marks_exactly_the_packets_it_touches_and_is_logged_once(caplog):
    imu = _flight(3.0)
    keep = ~((imu.t_ns >= T0 + NS) & (imu.t_ns < T0 + int(1.5 * NS)))
    imu = ImuData(imu.t_ns[keep], imu.gyro[keep], imu.accel[keep])
    stamps = T0 + np.arange(2, 58) * 50_000_000
    with caplog.at_level(logging.WARNING, logger="vio.sync"):
        pk = list(packets(imu, stamps, rate_hz=200.0, lookahead_s=0.02))
    gap = (T0 + NS - 5_000_000, T0 + int(1.5 * NS))
    flagged = [p for p in pk if p.imu_gaps]
    assert all(p.imu_gaps == (gap,) for p in flagged)
    assert [p.t_ns for p in flagged] == [t for t in stamps if gap[0] < t < gap[1] + 50_000_000]
    assert caplog.text.count("IMU gap of 0.505 s") == 1 and "0.995 s into the run" in caplog.text
    # a missing sample (10 ms < 2.5 periods) is no gap: interpolation covers it
    holes = np.ones(len(imu), bool)
    holes[[50, 90]] = False
    hole = ImuData(imu.t_ns[holes], imu.gyro[holes], imu.accel[holes])
    assert not any(p.imu_gaps for p in packets(hole, stamps[:10], rate_hz=200.0))


def test_gap_threshold_uses_the_longer_of_the_stated_and_the_recorded_period():
    imu = _flight(2.0, rate=50.0)   # 50-Hz data in a file that says 200 Hz
    assert not any(p.imu_gaps for p in packets(imu, T0 + np.arange(1, 30) * 50_000_000, rate_hz=200.0))


def test_dropped_samples_are_counted_in_the_packet_that_covers_them():
    imu = _with(_with(_flight(2.0), 101, accel=(300.0, 0, 0)), 301, gyro=(0, 5.0, 0))
    stamps = T0 + np.arange(1, 40) * 50_000_000
    pk = list(packets(imu, stamps, rate_hz=200.0))
    counts = {p.t_ns: p.imu_dropped for p in pk if p.imu_dropped}
    assert counts == {T0 + 550_000_000: 1, T0 + 1_550_000_000: 1}
    # the push API waits for the screen's delay past a frame before serving it
    sync = Synchronizer(screen=ImuScreen(ImuScreenConfig(), 200.0))
    sync.add_frame(int(imu.t_ns[20]))
    for k in range(23):
        sync.add_imu(imu.t_ns[k], imu.gyro[k], imu.accel[k])
    assert sync.poll().status is SyncStatus.WAITING
    sync.add_imu(imu.t_ns[23], imu.gyro[23], imu.accel[23])
    assert sync.poll().status is SyncStatus.READY


@pytest.mark.parametrize("parts", [("euroc_V1_01_30s_features",), ("euroc_MH_05_mono_15s",),
                                   ("euroc_imu_gt", "MH_03_medium"), ("euroc_imu_gt", "MH_04_difficult")])
def test_screen_never_fires_on_clean_real_imu(parts):
    """Real flights, including the Machine Hall landings (37 m/s^2 swings): nothing flagged."""
    from vio.io.euroc import read_imu_csv
    imu = read_imu_csv(shared(*parts, "mav0", "imu0", "data.csv"))
    _, gaps, n = screen_imu(imu)
    assert n == 0 and gaps == []


# ------------------------------------------------------------------ bridge and health (units)
def test_bridge_is_a_constant_velocity_prior_whose_sigmas_grow_with_the_gap():
    calib = ImuCalib(1.7e-4, 2e-5, 2e-3, 3e-3)
    p = bridge_params(calib, ImuNoiseConfig(), 1.0, 0.5)
    R = gtsam.Rot3.Ypr(0.3, -0.2, 0.1)
    bias = gtsam.imuBias.ConstantBias(np.array([0.1, -0.05, 0.2]), np.array([0.01, 0.02, -0.01]))
    covs = []
    for T in (0.5, 3.0):
        pim = gtsam.PreintegratedCombinedMeasurements(p, bias)
        integrate_still(pim, R, bias, 9.81, T, 0.005)
        v0 = np.array([0.5, -0.2, 0.1])
        nav = pim.predict(gtsam.NavState(gtsam.Pose3(R, np.array([1.0, 2.0, 3.0])), v0), bias)
        np.testing.assert_allclose(nav.velocity(), v0, atol=1e-9)
        np.testing.assert_allclose(nav.position(), np.array([1.0, 2.0, 3.0]) + v0 * T, atol=1e-9)
        assert nav.attitude().equals(R, 1e-9)
        covs.append(np.diag(pim.preintMeasCov()))
    # position sigma: q T^1.5 / sqrt(3) from the acceleration (0.2 m at 0.5 s) plus the
    # gravity direction left free by the rotation noise, which dominates long gaps
    assert 0.2 < np.sqrt(covs[0][3]) < 0.4 and np.sqrt(covs[1][3]) > 3.0
    assert np.all(covs[1][:9] > covs[0][:9])


def _monitor(**kw) -> HealthMonitor:
    m = HealthMonitor(HealthConfig(cooldown_keyframes=0, **kw), np.r_[np.full(3, 0.2), np.full(3, 0.01)],
                      np.r_[np.full(3, 0.045), np.full(3, 3e-4)])
    m.reset(0, gtsam.imuBias.ConstantBias(np.zeros(3), np.array([0.0, 0.02, 0.08])))
    return m


def _still_pim(dt: float, bias=gtsam.imuBias.ConstantBias()):
    """Preintegrated readings of a body at constant velocity and level attitude."""
    pim = gtsam.PreintegratedCombinedMeasurements(
        bridge_params(ImuCalib(1.7e-4, 2e-5, 2e-3, 3e-3), ImuNoiseConfig(), 1.0, 0.5), bias)
    integrate_still(pim, gtsam.Rot3(), bias, 9.81, dt, 0.005)
    return pim


def _check(m, t, v, b, kept=30, removed=0, chi2=1.0, T=gtsam.Pose3()):
    return m.check(int(t), T, np.asarray(v, float), b, _still_pim(0.1), kept, removed, chi2, ("calib", t))


def test_health_monitor_flags_each_divergence_and_only_those():
    b0 = gtsam.imuBias.ConstantBias(np.zeros(3), np.array([0.0, 0.02, 0.08]))
    m = _monitor()
    for k in range(20):   # healthy flight
        assert _check(m, k * 1e8, [0.5, 0.1, 0.0], b0, 30, 3, 12.0) is None
    assert "speed" in _check(m, 2 * NS, [40.0, 0, 0], b0)
    bad = gtsam.imuBias.ConstantBias(np.array([2.5, 0, 0]), np.array([0.0, 0.02, 0.08]))
    assert "accelerometer bias" in _check(m, 2 * NS, np.zeros(3), bad)
    # after 100 s the random walk allows more: 2.5 m/s^2 is then within 10 sigmas
    assert _check(m, 100 * NS, np.zeros(3), bad) is None
    assert "IMU factor" in _check(m, 2 * NS, np.zeros(3), b0, chi2=5e4)
    assert "non-finite" in _check(m, 2 * NS, [np.nan, 0, 0], b0)
    m = _monitor()
    reasons = [_check(m, k * 1e8, np.zeros(3), b0, 4, 12) for k in range(5)]
    assert reasons[:4] == [None] * 4 and "inlier ratio" in reasons[4]
    lost = "photometric points lost: ..."   # a factor source's reason (FactorSource.lost)
    m = _monitor()
    assert m.check(0, gtsam.Pose3(), np.zeros(3), b0, _still_pim(0.1), 30, 0, 1.0, (), lost) == lost


def test_photometric_source_lost_needs_five_keyframes_without_pairs():
    """``PhotometricSource.lost``: fewer than 10 % of max_points (point, keyframe) pairs in
    use at five keyframes in a row that had another host; a keyframe with pairs again, or
    one whose window has no other host, does not count; a restart forgets the count."""
    from types import SimpleNamespace
    from vio.direct.config import DirectConfig
    from vio.direct.source import PhotometricSource
    src = PhotometricSource.__new__(PhotometricSource)
    src.cfg, src._coverage, src._levels = DirectConfig(), [], []
    n = src.cfg.points.max_points

    def host(k, targets, used, level=9.0):
        tmask = np.zeros((n, 5), bool)
        tmask[:used, len(targets) - 1] = True
        rms = np.full((n, 5), np.inf)
        rms[:, :len(targets)] = level
        rms[::7, :len(targets)] = -1.0                  # left the image: not part of the level
        return SimpleNamespace(k=k, targets=targets,
                               pts=SimpleNamespace(alive=np.ones(n, bool), tmask=tmask, rms=rms))

    def window(k, used, level=9.0):   # keyframe k observed by host k - 1 with ``used`` pairs; k hosts too
        src.hosts = {k - 1: host(k - 1, [k], used, level), k: host(k, [k + 1], 0)}
        return src.lost(k)

    assert [window(k, 3) for k in range(1, 5)] == [None] * 4
    assert window(5, 14).startswith("photometric points lost")
    assert window(6, 15) is None                        # 15 pairs: 10 % of 150
    assert [window(k, 0) for k in range(7, 11)] == [None] * 4
    src.hosts = {11: host(11, [12], 0)}                 # no other host: no evidence either way
    assert src.lost(11) is None and window(12, 0) is not None
    src._coverage = []                                  # what reset() does
    assert window(13, 0) is None


def test_photometric_source_lost_when_every_pair_fits_badly():
    """``PhotometricSource.lost``: pairs in use, but the window's median pair RMS above
    ``lost_rms`` (25) at five keyframes in a row (a window that ran off while its pairs stay
    in use under the per-target threshold, twice their median); one keyframe at or below it
    breaks the run."""
    from types import SimpleNamespace
    from vio.direct.config import DirectConfig
    from vio.direct.source import PhotometricSource
    src = PhotometricSource.__new__(PhotometricSource)
    src.cfg, src._coverage, src._levels = DirectConfig(), [], []
    n = src.cfg.points.max_points

    def window(k, level):
        rms = np.full((n, 5), np.inf)
        rms[:, 0] = level
        rms[:n // 3, 0] = 1.0                           # a third fits: the median is the level
        tmask = np.ones((n, 5), bool)
        pts = SimpleNamespace(alive=np.ones(n, bool), tmask=tmask, rms=rms)
        src.hosts = {k - 1: SimpleNamespace(k=k - 1, targets=[k], pts=pts),
                     k: SimpleNamespace(k=k, targets=[], pts=SimpleNamespace(alive=np.ones(n, bool)))}
        src.hosts[k].pts.rms, src.hosts[k].pts.tmask = np.full((n, 5), np.inf), tmask
        return src.lost(k)

    assert [window(k, 30.0) for k in range(1, 5)] == [None] * 4
    assert window(5, 30.0).startswith("photometric residuals")
    assert [window(k, 25.0) for k in range(6, 11)] == [None] * 5       # at the limit: not above
    assert [window(k, 40.0) for k in range(11, 15)] == [None] * 4
    assert window(15, 40.0) is not None


def test_health_fallback_propagates_the_healthy_state_a_lookback_old_and_cooldown_holds():
    b0 = gtsam.imuBias.ConstantBias()
    m = _monitor(lookback_s=1.0)
    for k in range(30):   # moving at 1 m/s along x, keyframes every 0.1 s
        T = gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * k, 0, 0]))
        assert _check(m, k * 1e8, [1.0, 0, 0], b0, T=T) is None
    assert _check(m, 30 * 1e8, [50.0, 0, 0], b0, T=gtsam.Pose3(gtsam.Rot3(), np.array([9.0, 0, 0])))
    nav, b, calib = m.fallback()
    # healthy keyframe at 1.9 s (x = 1.9), propagated over the 11 intervals to 3.0 s
    assert calib == ("calib", 19 * 1e8)
    np.testing.assert_allclose(nav.position(), [3.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(nav.velocity(), [1.0, 0, 0], atol=1e-9)
    m = HealthMonitor(HealthConfig(cooldown_keyframes=3), np.ones(6), np.ones(6))
    m.reset(0, b0)
    fast = [_check(m, k, [99.0, 0, 0], b0) for k in range(4)]
    assert fast[:3] == [None] * 3 and "speed" in fast[3]


# ------------------------------------------------------------------ real V1_01 stretch
# The stretch [3.5 s, 12 s] of V1_01: static until ~5.5 s, then flight (path ~1.6 m);
# fault times are seconds after the stretch's first IMU sample. Clean: ATE ~0.017 m.
def _stretch(tmp_path, name: str):
    from vio.inject import copy_dataset
    return copy_dataset(shared("euroc_V1_01_30s_features"), tmp_path / name, start_s=3.5, end_s=12.0)


def _run(root):
    from vio.evaluation import evaluate
    from vio.io.euroc import load_euroc
    from vio.run import run_dataset
    data = load_euroc(root)
    res = run_dataset(data, mode="features")
    return res, evaluate(*res.arrays(), data.groundtruth).ate_rmse


def _steps(res) -> np.ndarray:
    """Output position steps between consecutive frames (m)."""
    _, p, _ = res.arrays()
    return np.linalg.norm(np.diff(p, axis=0), axis=1)


@pytest.mark.parametrize("start,dur,bound", [(5.0, 0.5, 0.04), (4.5, 3.0, 0.08)])
def test_imu_gap_in_flight_is_bridged(tmp_path, caplog, start, dur, bound):
    from vio.inject import imu_gap
    root = _stretch(tmp_path, "gap")
    assert imu_gap(root, start, dur) == int(round(dur * 200))
    with caplog.at_level(logging.WARNING):
        res, ate = _run(root)
    assert res.imu_gaps == 1 and abs(res.imu_gap_s - dur) < 0.011 and res.restarts == 0
    assert len(res.outputs) >= res.frames_in - 10     # every frame after the 0.5-s initialization
    assert ate <= bound, ate
    # frames inside the gap are extrapolated at constant velocity and corrected at the
    # next keyframe: steps stay within a few times the true motion (<= 0.65 m/s at 20 Hz)
    assert _steps(res).max() < 0.2
    assert "IMU gap of" in caplog.text and "s into the run" in caplog.text


def test_imu_gap_while_static_is_bridged(tmp_path):
    from vio.inject import imu_gap
    root = _stretch(tmp_path, "gap_static")
    imu_gap(root, 1.0, 0.5)                   # after the static initialization, before take-off
    res, ate = _run(root)
    assert res.imu_gaps == 1 and res.restarts == 0 and ate <= 0.04, ate


def test_accelerometer_spike_is_dropped(tmp_path):
    from vio.inject import imu_spike
    root = _stretch(tmp_path, "spike")
    imu_spike(root, 5.5, accel=(200.0, 0.0, 0.0))
    res, ate = _run(root)
    assert res.imu_dropped == 1 and res.imu_gaps == 0 and res.restarts == 0
    assert ate <= 0.03, ate


def test_dropped_camera_frames(tmp_path):
    from vio.inject import drop_frames
    root = _stretch(tmp_path, "frames")
    assert drop_frames(root, 5.0, 0.5) == 10
    res, ate = _run(root)
    assert res.imu_gaps == 0 and res.imu_dropped == 0 and res.restarts == 0
    assert ate <= 0.04, ate
    # the hole is reported: the interval from the last frame before it to the first after
    assert res.camera_gaps == 1 and res.camera_gap_s == pytest.approx(0.55, abs=0.01)
    from vio.io.euroc import load_euroc
    from vio.run_summary import summary
    faults = [ln for ln in summary(res, load_euroc(root)) if ln.startswith("faults")]
    assert faults[0].endswith("1 camera gap(s) (0.55 s without frames)"), faults


def test_a_dropped_packet_carries_its_imu_to_the_next_frame(tmp_path, caplog):
    """A frame the image stage could not use (``FramePacket.dropped``: an image that does
    not decode) gives no output and a warning; its IMU is preintegrated with the next
    frame's, so the run is the run of the same data without that frame."""
    import dataclasses

    from vio.inject import drop_frames
    from vio.io.euroc import load_euroc
    from vio.pipeline import Pipeline
    from vio.run import default_config
    root = _stretch(tmp_path, "clean")
    data = load_euroc(root)
    cfg = default_config("features")
    drop = 60

    pipes = []

    def run(pkts):
        pipes.append(Pipeline(data.imu_calib, data.cam0.calib, cfg))
        return [o for p in pkts for o in pipes[-1].process(p)]

    pkts = list(packets(data.imu, data.cam0.t_ns, 0.0, data.features))
    pkts[drop] = dataclasses.replace(pkts[drop], dropped="an image that does not decode")
    with caplog.at_level(logging.WARNING, logger="vio.pipeline"):
        outs = run(pkts)
    assert "frame dropped (an image that does not decode)" in caplog.text
    assert pipes[-1].frames_dropped == 1
    from vio.run import RunResult
    from vio.run_summary import summary
    faults = [ln for ln in summary(RunResult(frames_dropped=1), data) if ln.startswith("faults")]
    assert faults and faults[0].endswith("1 frame(s) dropped (image missing, unreadable or blank)"), faults
    assert pkts[drop].t_ns not in {o.t_ns for o in outs} and pkts[drop + 1].t_ns in {o.t_ns for o in outs}
    t_drop = (pkts[drop].t_ns - data.imu.t_ns[0]) * 1e-9
    assert drop_frames(root, t_drop - 0.01, 0.02) == 1     # the same data without that frame
    d2 = load_euroc(root)
    ref = run(packets(d2.imu, d2.cam0.t_ns, 0.0, d2.features))
    assert [o.t_ns for o in ref] == [o.t_ns for o in outs]
    gap = max(np.linalg.norm(a.T_w_b.translation() - b.T_w_b.translation()) for a, b in zip(outs, ref))
    assert gap < 1e-6, gap


def test_clean_stretch_raises_no_fault_and_cli_exits_zero_on_faults(tmp_path, capsys):
    from vio.cli import main
    from vio.inject import imu_gap, imu_spike
    res, ate = _run(_stretch(tmp_path, "clean"))
    assert (res.imu_gaps, res.imu_dropped, res.restarts, res.recoveries) == (0, 0, 0, 0)
    assert ate <= 0.025, ate
    root = _stretch(tmp_path, "both")
    imu_gap(root, 5.0, 1.0)
    imu_spike(root, 6.5, gyro=(0.0, 8.0, 0.0))
    assert main(["run", str(root), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "1 IMU gap(s) bridged (1.00 s), 1 IMU sample(s) dropped, 0 divergence restart(s)" in out


def test_vio_run_leaves_the_cyclic_collector_as_it_found_it(tmp_path, capsys):
    """`vio run` keeps the collector off during its start-up, freezes the start-up objects and
    raises the young-generation threshold for the loop (vio.cli._run, vio.run.run_dataset):
    called in-process, it must hand the collector back enabled, unfrozen, at its thresholds."""
    import gc

    from vio.cli import main
    root = _stretch(tmp_path, "gc")
    thresholds = gc.get_threshold()
    assert gc.isenabled()
    assert main(["run", str(root), "--no-progress", "--max-frames", "60"]) == 0
    assert "60 in, " in capsys.readouterr().out
    assert gc.isenabled() and gc.get_freeze_count() == 0 and gc.get_threshold() == thresholds


def test_console_script_exits_with_mains_code_and_skips_the_last_collection(monkeypatch):
    """The ``vio`` script (vio.cli.console, pyproject's entry point) exits with ``main``'s
    code, a user error's 2 included, and freezes the heap first: Python's exit-time
    collection over it took ~0.4 s after a real MH_05 mono run."""
    import gc

    from vio import cli
    monkeypatch.setattr(sys, "argv", ["vio", "run", "/nonexistent/folder", "--no-progress"])
    for main, code in ((cli.main, 2), (lambda: 0, 0)):
        monkeypatch.setattr(cli, "main", main)
        try:
            with pytest.raises(SystemExit) as exc:
                cli.console()
            assert exc.value.code == code
            assert gc.get_freeze_count() > 0
        finally:
            gc.unfreeze()
    text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert 'vio = "vio.cli:console"' in text


def test_output_into_a_missing_folder_fails_before_the_run(tmp_path, capsys):
    """--out (and the other output files) into a folder that does not exist: exit 2 at
    once, not after the run."""
    from vio.cli import main
    for flag in ("--out", "--smoothed", "--map"):
        assert main(["run", str(tmp_path / "no-such-dataset"), "--no-progress", flag, str(tmp_path / "nope" / "x")]) == 2
        err = capsys.readouterr().err
        assert f"{flag} {tmp_path / 'nope' / 'x'}: folder {tmp_path / 'nope'} does not exist" in err, err


def test_run_too_short_to_initialize_says_why(tmp_path, capsys):
    """A run that ends before any initialization: exit 0 and the summary says what was
    missing (here: too little data for the dynamic alignment)."""
    from vio.cli import main
    root = _stretch(tmp_path, "short")
    assert main(["run", str(root), "--no-progress", "--max-frames", "8"]) == 0
    out = capsys.readouterr().out
    assert "initialization  not reached (0.35 s of frames buffered; the dynamic alignment needs 1.50 s" in out, out


def test_forced_divergence_restarts_softly_without_a_jump(tmp_path, caplog):
    """A bogus 60 m/s velocity is forced into the smoother mid-flight: the monitor must
    restart it at the current pose (no jump in the output) and the run continue."""
    from vio.backend import graph
    from vio.evaluation import evaluate
    from vio.io.euroc import load_euroc
    from vio.pipeline import Pipeline, PipelineConfig
    from vio.sync import packets as pk_iter
    data = load_euroc(_stretch(tmp_path, "div"))
    cfg = PipelineConfig()
    pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg)
    outs, kicked, restarted = [], False, []
    t_kick = int(data.imu.t_ns[0]) + int(5.0 * NS)
    with caplog.at_level(logging.WARNING):
        for pkt in pk_iter(data.imu, data.cam0.t_ns, cfg.td_s, data.features, lookahead_s=0.02):
            new = pipe.process(pkt)
            outs += new
            restarted += [pipe.est.divergences > 0] * len(new)
            if not kicked and pkt.t_ns >= t_kick and outs and outs[-1].keyframe:
                est = pipe.est
                g = gtsam.NonlinearFactorGraph()
                g.add(gtsam.PriorFactorVector(graph.V(est.k), np.array([60.0, 0, 0]),
                                              gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
                est.smoother.update(g, gtsam.Values(), {})
                est.values = est.smoother.calculateEstimate()
                kicked = True
    assert kicked and pipe.est.divergences >= 1 and pipe.est.recoveries == 0
    assert "divergence at keyframe" in caplog.text and "soft restart" in caplog.text
    # 1.5 s after the restart the dynamic alignment re-initializes the window (vio.reinit)
    assert pipe.reinit.count == 1 and "re-initialized after a divergence restart" in caplog.text
    from vio.conventions import quat_wxyz_from_rot
    t = np.array([o.t_ns for o in outs])
    p = np.array([o.T_w_b.translation() for o in outs])
    q = np.array([quat_wxyz_from_rot(o.T_w_b.rotation()) for o in outs])
    # the bogus velocity moves the frames up to the next keyframe (the divergence itself);
    # from the restart keyframe on the output continues without a jump
    i = restarted.index(True)
    assert np.linalg.norm(np.diff(p[i:], axis=0), axis=1).max() < 0.15   # keyframe corrections
    e = evaluate(t[i:], p[i:], q[i:], data.groundtruth)
    assert e.ate_rmse < 0.06, e.ate_rmse   # 0.036 m over 0.95 m (0.039 m without the re-initialization)


def test_image_fault_alters_only_its_stretch_of_the_copy(tmp_path):
    """``vio.inject.image_fault``: the images of one camera in ``[t, t + dur)`` after the
    first IMU sample are replaced by the fault; the others stay links to the source, which
    is never written; an unknown fault is refused."""
    import cv2
    from vio.inject import copy_dataset, image_fault
    src = tmp_path / "src" / "mav0"
    (src / "imu0").mkdir(parents=True)
    (src / "imu0" / "data.csv").write_text("#t,w,a\n1000000000,0,0,0,0,0,9.8\n")
    (src / "cam1" / "data").mkdir(parents=True)
    rows = ["#timestamp [ns],filename"]
    img = np.tile(np.arange(40, dtype=np.uint8) * 5, (30, 1))
    for i in range(5):
        t = 1_000_000_000 + i * 50_000_000
        cv2.imwrite(str(src / "cam1" / "data" / f"{t}.png"), img)
        rows.append(f"{t},{t}.png")
    (src / "cam1" / "data.csv").write_text("\n".join(rows) + "\n")
    root = copy_dataset(src.parent, tmp_path / "copy")
    assert image_fault(root, "cam1", 0.05, 0.1, "cover") == 2          # frames 1 and 2
    assert image_fault(root, "cam1", 0.2, 1.0, "exposure") == 1        # frame 4
    data = root / "mav0" / "cam1" / "data"
    means = [cv2.imread(str(data / f"{1_000_000_000 + i * 50_000_000}.png"), 0).mean() for i in range(5)]
    assert means[1] == means[2] == 12.0 and means[0] == means[3] == img.mean()
    assert means[4] > 1.5 * img.mean()
    assert all(cv2.imread(str(f), 0).mean() == img.mean() for f in (src / "cam1" / "data").iterdir())
    with pytest.raises(ValueError, match="unknown fault"):
        image_fault(root, "cam1", 0.0, 1.0, "smudge")


@pytest.mark.slow
def test_direct_mode_keeps_its_points_with_the_right_camera_covered(tmp_path):
    """Real MH_01, the right camera covered for 2 s (frames 60-99 of 170): the keyframes'
    points take their depths from the previous keyframe (``vio.direct.temporal``), so
    direct mode goes on without a restart at 3.9 mm (stereo depths alone: 19.5 mm and a
    restart once the points were lost)."""
    res, ate = _real_mh01_fault(tmp_path, "cam1:cover:60:40", "direct", 170)
    assert res.restarts == 0 and len(res.outputs) == 170
    assert ate < 0.008, f"direct, cam1 covered 2 s: ATE {ate:.4f} m"


def test_image_fault_benchmark_drops_frames_from_both_cameras(tmp_path):
    """``bench_image_faults``' ``frames:drop:FRAME:N`` removes exactly cam0 frames
    FRAME..FRAME+N-1 and their cam1 pairs (a camera gap); an unknown kind is refused."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_image_faults import faulty_copy
    from vio.io.euroc import load_euroc
    src = load_euroc(shared("euroc_MH_01_stereo_synimu"))
    cut = load_euroc(faulty_copy(shared("euroc_MH_01_stereo_synimu"), "frames:drop:100:20", tmp_path / "f"))
    keep = np.r_[0:100, 120:len(src.cam0.t_ns)]
    assert np.array_equal(cut.cam0.t_ns, src.cam0.t_ns[keep])
    assert np.array_equal(cut.cam1.t_ns, src.cam1.t_ns[keep])
    with pytest.raises(ValueError, match="unknown frame fault"):
        faulty_copy(shared("euroc_MH_01_stereo_synimu"), "frames:blur:100:20", tmp_path / "g")


def _real_mh01_fault(tmp_path: Path, fault: str, mode: str, frames: int):
    """The first ``frames`` frames of real MH_01 with ``fault`` (``bench_image_faults``'s
    ``CAMS:KIND:FRAME:N``) in ``mode``'s defaults: (RunResult, ATE m)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_image_faults import faulty_copy
    from vio.evaluation import evaluate
    from vio.io.euroc import load_euroc
    from vio.run import default_config, run_dataset
    data = load_euroc(faulty_copy(shared("euroc_MH_01_stereo_synimu"), fault, tmp_path / "fault"))
    res = run_dataset(data, default_config(mode), max_frames=frames, mode=mode)
    return res, evaluate(*res.arrays(), data.groundtruth).ate_rmse


@pytest.mark.slow
def test_frames_between_keyframes_of_an_accelerometer_fault_are_placed_by_vision(tmp_path):
    """Real MH_01 stereo, +6 m/s^2 on the accelerometer over frames 40-59: the keyframe
    check bridges the faulty intervals, and between the keyframes each frame whose IMU
    prediction vision contradicts is output at its PnP pose (``bridge.frame_state``).
    First 100 frames: 6.7 mm, 7 frames placed by PnP (without the frame check 22.3 mm:
    the predictions between keyframes drifted 44-148 mm)."""
    res, ate = _real_mh01_fault(tmp_path, "imu:offset:40:20", "stereo", 100)
    assert res.restarts == 0 and len(res.outputs) == 100
    assert res.imu_contradicted >= 2 and res.frames_contradicted >= 3
    assert ate < 0.012, f"stereo, accelerometer offset from frame 40: ATE {ate:.4f} m"
