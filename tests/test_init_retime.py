"""A dynamic initialization's window replayed at the td it found (``vio.init_retime``):
the packets cut again equal what a sync layer told that td serves, the first packet after
the window continues the IMU from the window's last frame, and a generated mid-flight start
at a large offset needs no td re-anchoring restart."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared
from vio.imu import concat
from vio.init_retime import retime_packets, stitch
from vio.io.types import ImuData
from vio.sync import packets

LOOK = 20_000_000     # ns, the default lookahead


def _imu() -> ImuData:
    t = np.arange(0, 3_000_000_001, 5_000_000, dtype=np.int64) + 1_000_000_000
    k = np.arange(len(t))
    w = np.stack([np.sin(k * 0.05), np.cos(k * 0.03), 0.1 * np.ones(len(t))], 1)
    a = np.stack([np.sin(k * 0.02), k * 0.001, 9.81 + 0.1 * np.cos(k * 0.07)], 1)
    return ImuData(t, w, a)


def _stamps() -> np.ndarray:
    return np.arange(1_300_000_000, 3_500_000_001, 50_000_000, dtype=np.int64) + 1_234_567


def _same_signal(a: ImuData, b: ImuData) -> None:
    """The same endpoints and piecewise-linear readings: the joined stream keeps the
    packets' interpolated endpoints as extra knots on the same lines, so the samples may
    differ, their trapezoid integrals and the readings at each other's times do not."""
    assert a.t_ns[0] == b.t_ns[0] and a.t_ns[-1] == b.t_ns[-1]
    assert np.all(np.diff(a.t_ns) > 0)
    for x, y in ((a.gyro, b.gyro), (a.accel, b.accel)):
        np.testing.assert_allclose(np.trapezoid(x, a.t_ns * 1e-9, axis=0),
                                   np.trapezoid(y, b.t_ns * 1e-9, axis=0), rtol=0, atol=1e-12)
        at_b = np.stack([np.interp(b.t_ns, a.t_ns, x[:, k]) for k in range(3)], 1)
        np.testing.assert_allclose(at_b, y, atol=1e-12)


@pytest.mark.parametrize("td_ms", [-15.0, -30.0, 12.0, 18.0])
def test_retimed_window_equals_a_sync_layer_told_the_offset(td_ms):
    imu, stamps, d = _imu(), _stamps(), int(td_ms * 1e6)
    at0 = list(packets(imu, stamps, 0.0, lookahead_s=LOOK * 1e-9))
    told = list(packets(imu, stamps, td_ms * 1e-3, lookahead_s=LOOK * 1e-9))
    win, rest = at0[2:30], told[30:]     # a window after the stream's first packet
    moved, joined = retime_packets(win, d, LOOK)
    assert [p.t_ns for p in moved] == [p.t_ns for p in told[2:30]]
    assert [p.stamp_ns for p in moved] == [p.stamp_ns for p in win]
    for a, b in zip(moved[1:], told[3:30]):          # the same IMU signal over the same interval
        _same_signal(a.imu, b.imu)
    for a, b in zip(moved[:-1], told[2:29]):         # and lookahead (the last frame's is cut
        _same_signal(a.imu_ahead, b.imu_ahead)       # where the window's IMU ends)
    assert moved[-1].imu_ahead.t_ns[0] == moved[-1].t_ns
    # the first packet after the window, served at the new offset from the sync layer's
    # own last time (the window's last frame at offset 0), continues from the moved window
    served: list = []
    for pkt in packets(imu, stamps, 0.0, lookahead_s=LOOK * 1e-9,
                       td_source=lambda: td_ms * 1e-3 if len(served) >= 30 else 0.0):
        served.append(pkt)
    nxt = served[30]
    assert nxt.imu.t_ns[0] == win[-1].t_ns
    _same_signal(stitch(nxt, moved[-1].t_ns, joined).imu, rest[0].imu)


def test_edges_of_the_imu_stream():
    """The stream's first packet (one sample) is moved earlier with its reading held; a
    frame the lookahead does not reach keeps its time; times that would not increase and
    IMU gaps are refused; a frame not after the window's last is not stitched."""
    imu, stamps = _imu(), _stamps()
    at0 = list(packets(imu, stamps, 0.0, lookahead_s=LOOK * 1e-9))
    moved, joined = retime_packets(at0, -15_000_000, LOOK)
    assert moved[0].t_ns == at0[0].t_ns - 15_000_000 and len(moved[0].imu) == 1
    assert joined.t_ns[0] == moved[0].t_ns
    np.testing.assert_array_equal(joined.gyro[0], joined.gyro[1])
    assert moved[1].imu.t_ns[0] == moved[0].t_ns and moved[1].imu.t_ns[-1] == moved[1].t_ns
    late, _ = retime_packets(at0, 30_000_000, LOOK)             # beyond the 20-ms lookahead
    assert late[-1].t_ns == at0[-1].t_ns and late[-2].t_ns == at0[-2].t_ns + 30_000_000
    assert np.all(np.diff(concat([p.imu for p in late]).t_ns) > 0)
    with pytest.raises(ValueError, match="increase"):
        retime_packets(at0, 60_000_000, 80_000_000)
    gap = at0[:5]
    gap[3] = gap[3].__class__(**{**gap[3].__dict__, "imu_gaps": ((1, 2),)})
    with pytest.raises(ValueError, match="gap"):
        retime_packets(gap, 10_000_000, LOOK)
    assert stitch(at0[3], at0[3].t_ns, joined) is None


def test_midflight_start_at_30ms_needs_no_reanchoring(tmp_path, caplog):
    """Generated MH_04 tracks 65 s into the flight (seed 81), camera 30 ms late, sync layer
    at 0: the window is aligned at the found remainder and replayed there, so the td
    re-anchoring restart that came 0.4 s after the initialization (the first 3 s 12 %
    too long, 0.43 % of the path over 30 s) does not happen."""
    from vio.io.euroc import load_euroc
    from vio.run import default_config, run_dataset
    from vio.sim.tracks import TrackGenConfig, generate_tracks
    src = shared("euroc_imu_gt", "MH_04_difficult")
    generate_tracks(src, tmp_path, TrackGenConfig(start_s=65.0, duration_s=6.0, seed=81, td_s=0.03))
    d = load_euroc(tmp_path)
    with caplog.at_level("INFO", logger="vio.backend.td_reanchor"):
        res = run_dataset(d, default_config("features"), mode="features")
    assert res.init.decided_s <= 1.5 + 1e-6 and abs(res.init.td_s - 0.03) < 0.003
    assert "td re-anchored" not in caplog.text
    first = res.outputs[0]
    assert abs((first.t_ns - first.packet.stamp_ns) * 1e-9 - res.init.td_s) < 1e-6
