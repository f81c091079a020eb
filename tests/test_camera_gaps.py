"""``vio.camera_gaps``: stretches without camera frames are warned about and counted."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from vio.camera_gaps import CameraGapConfig, CameraGaps

T0 = 1_600_000_000_000_000_000
P = 50_000_000        # 20 Hz


def _feed(g: CameraGaps, stamps) -> list:
    return [gap for t in stamps if (gap := g.frame(int(t))) is not None]


def test_a_regular_stream_with_jitter_and_single_missing_frames_has_no_gap():
    rng = np.random.default_rng(3)
    t = T0 + np.arange(200) * P + rng.integers(-2_000_000, 2_000_000, 200)
    t = np.delete(t, [40, 90, 91 + 40])        # three single frames missing: two periods each
    g = CameraGaps()
    assert _feed(g, t) == [] and g.gaps == [] and g.seconds == 0.0


def test_a_one_second_hole_is_one_gap_with_its_stamps_and_a_warning(caplog):
    t = [T0 + k * P for k in range(100) if not 40 <= k < 60]
    g = CameraGaps()
    with caplog.at_level(logging.WARNING, logger="vio.camera_gaps"):
        gaps = _feed(g, t)
    assert gaps == g.gaps == [(T0 + 39 * P, T0 + 60 * P)]
    assert g.seconds == pytest.approx(1.05)
    assert "no camera frame for 1.05 s (about 20 missing at 20.0 Hz)" in caplog.text
    assert "t=%d ns (3.00 s after the first frame)" % (T0 + 60 * P) in caplog.text


def test_the_nominal_period_is_the_stream_s_own():
    """A 10-Hz stream (a decimated recording) is not a stream of gaps; a hole in it is."""
    t = [T0 + 2 * k * P for k in range(60) if not 30 <= k < 34]
    g = CameraGaps()
    assert _feed(g, t) == [(T0 + 58 * P, T0 + 68 * P)]


def test_repeated_or_early_stamps_and_the_switch():
    g = CameraGaps()
    assert _feed(g, [T0, T0 + P, T0 + P, T0, T0 + 2 * P]) == []
    off = CameraGaps(CameraGapConfig(max_gap_periods=0.0))
    assert _feed(off, [T0 + k * P for k in (*range(10), 40)]) == [] and off.gaps == []
    few = CameraGaps()            # fewer than min_history intervals: no judgement yet
    assert _feed(few, [T0, T0 + P, T0 + 2 * P, T0 + 30 * P]) == []
    with pytest.raises(ValueError, match="history"):
        CameraGapConfig(history=0)
