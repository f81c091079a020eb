"""IMU stream screening: impossible samples and gaps (before any preintegration).

Impossible samples are dropped (the sync layer's linear interpolation between the
neighbours then stands in for them):

- *range*: a reading beyond the sensor's range (``accelerometer_range`` m/s^2 /
  ``gyroscope_range`` rad/s in ``imu0/sensor.yaml``, per axis; none when not given);
- *spike*: a Hampel test per axis, ``|x_i - median(x_{i-H..i+H})| > k * spread`` where
  ``spread`` is the local robust spread: the larger of 1.4826 MAD of the axis over the
  previous ``spread_window`` samples and the next ``H``, and over the ``2H+1`` samples
  around the median (a sudden violent but coherent motion, a landing, widens this one
  first), floored at ``accel_floor`` / ``gyro_floor`` (a still IMU's quantized readings
  have a MAD of 0). A sample is judged once ``H`` later samples are in (15 ms at 200 Hz,
  within the sync layer's default 20-ms lookahead, so no added latency).

Calibration on the clean real IMU files in ``../shared/data`` (all eight full
``euroc_imu_gt`` sequences, MH_05, V1_01, the static V1_01, the synthesized MH_01,
``benchmarks/bench_faults.py``): the largest score ``|x - median| / spread`` is 7.7 for
the accelerometer (MH_05) and 3.6 for the gyro (V1_03); typical flight maxima are 4-5
(without the short-window term the Machine Hall landings, 37 m/s^2 swings, scored 16).
``k = 15`` keeps a 2x margin and catches, in V1_01's flight, one accelerometer sample
about 22 m/s^2 off (200 m/s^2 scores 138) or one gyro sample 1.5 rad/s off.

A *gap* is an interval between consecutive accepted samples longer than
``max_gap_periods`` nominal periods (``rate_hz`` of ``sensor.yaml``): the estimator must
not preintegrate across it (``vio.sync`` marks the packets it touches).

Each fault is logged as a warning naming its time (ns, and seconds after the first IMU
sample) and what was done; after ``max_warnings`` samples the rest are counted only.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from vio.config import check_ranges
from vio.io.types import ImuData

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImuScreenConfig:
    """See the module docstring. ``enabled`` False: samples pass unchanged (gaps are
    still detected)."""

    enabled: bool = True
    max_gap_periods: float = 2.5
    half_window: int = 3
    spread_window: int = 50
    spike_k: float = 15.0
    accel_floor: float = 1.0
    gyro_floor: float = 0.1
    max_warnings: int = 20

    def __post_init__(self) -> None:
        check_ranges(self, positive=("max_gap_periods", "half_window", "spread_window", "spike_k",
                                     "accel_floor", "gyro_floor"))


def _hampel(x: np.ndarray, lo: int, hi: int, h: int, s: int, floor: float, k: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Spike flags and scores (n,) of rows ``lo..hi-1`` of ``x`` (N, 3); rows outside are
    context (edges padded with the edge row). Score: worst axis of |x - median| / spread."""
    pad = np.pad(x, ((max(h, s), h), (0, 0)), mode="edge")
    off = max(h, s)
    idx = np.arange(lo, hi) + off
    med_w = sliding_window_view(pad, 2 * h + 1, axis=0)          # (N', 3, 2h+1), starts at row-h
    med = np.median(med_w[idx - h], axis=-1)
    spr_w = sliding_window_view(pad, s + h + 1, axis=0)          # rows [i-s, i+h]
    win = spr_w[idx - s]
    mad = 1.4826 * np.median(np.abs(win - np.median(win, axis=-1, keepdims=True)), axis=-1)
    short = med_w[idx - h]      # a sudden violent motion (a landing) widens the short window first
    mad = np.maximum(mad, 1.4826 * np.median(np.abs(short - med[..., None]), axis=-1))
    score = (np.abs(x[lo:hi] - med) / np.maximum(mad, floor)).max(axis=1)
    return score > k, score


class ImuScreen:
    """Streaming screen: ``push`` raw samples, ``pop`` the accepted ones that can be judged
    (``half_window`` later samples present, or all when ``final``). ``rate_hz``: nominal
    rate; ``accel_range`` / ``gyro_range``: sensor ranges (inf: unknown)."""

    def __init__(self, cfg: ImuScreenConfig = ImuScreenConfig(), rate_hz: float = 200.0,
                 accel_range: float = math.inf, gyro_range: float = math.inf) -> None:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"IMU rate must be positive, got {rate_hz}")
        if not (cfg.max_gap_periods > 1 and cfg.spike_k > 0 and cfg.half_window >= 1
                and cfg.spread_window >= 1 and cfg.accel_floor > 0 and cfg.gyro_floor > 0):
            raise ValueError(f"imu_screen: need max_gap_periods > 1, spike_k, floors > 0 and "
                             f"windows >= 1, got {cfg}")
        self.cfg = cfg
        self.period_ns = int(round(1e9 / rate_hz))
        self.max_gap_ns = cfg.max_gap_periods * 1e9 / rate_hz   # float: inf disables gaps
        self.ranges = (accel_range, gyro_range)
        self._t = np.zeros(0, np.int64)
        self._w = np.zeros((0, 3))
        self._a = np.zeros((0, 3))
        self._next = 0            # first row of the buffer not yet judged
        self.t_first: int | None = None
        self.n_dropped = 0
        self.dropped: list[int] = []   # stamps (ns) of dropped samples, for the sync layer to report
        self._warned = 0

    def push(self, imu: ImuData) -> None:
        if len(imu) == 0:
            return
        if self.t_first is None:
            self.t_first = int(imu.t_ns[0])
        self._t = np.concatenate([self._t, imu.t_ns])
        self._w = np.concatenate([self._w, imu.gyro])
        self._a = np.concatenate([self._a, imu.accel])

    def pop(self, final: bool = False) -> ImuData:
        """Accepted samples judged by this call (time order)."""
        c = self.cfg
        n = self._t.shape[0]
        hi = n if (final or not c.enabled) else max(n - c.half_window, self._next)
        lo = self._next
        keep = np.ones(hi - lo, bool)
        if c.enabled and hi > lo:
            keep = self._judge(lo, hi)
        out = ImuData(self._t[lo:hi][keep], self._w[lo:hi][keep], self._a[lo:hi][keep])
        self._next = hi
        ctx = max(c.spread_window, c.half_window)
        cut = max(0, self._next - ctx)
        if cut > 0:
            self._t, self._w, self._a = self._t[cut:], self._w[cut:], self._a[cut:]
            self._next -= cut
        return out

    def _judge(self, lo: int, hi: int) -> np.ndarray:
        c = self.cfg
        a_rng, w_rng = self.ranges
        out_a = (np.abs(self._a[lo:hi]) > a_rng).any(axis=1)
        out_w = (np.abs(self._w[lo:hi]) > w_rng).any(axis=1)
        sp_a, sc_a = _hampel(self._a, lo, hi, c.half_window, c.spread_window, c.accel_floor, c.spike_k)
        sp_w, sc_w = _hampel(self._w, lo, hi, c.half_window, c.spread_window, c.gyro_floor, c.spike_k)
        bad = out_a | out_w | sp_a | sp_w
        for j in np.flatnonzero(bad):
            i = lo + j
            what = ("beyond the sensor range" if out_a[j] or out_w[j] else
                    f"an implausible jump ({'accelerometer' if sc_a[j] >= sc_w[j] else 'gyro'} "
                    f"{max(sc_a[j], sc_w[j]):.0f}x the local spread)")
            self._warn(int(self._t[i]), f"IMU sample {np.round(self._a[i], 2)} m/s^2, "
                       f"{np.round(self._w[i], 3)} rad/s is {what}: dropped (interpolated "
                       f"from its neighbours)")
        self.n_dropped += int(bad.sum())
        self.dropped.extend(int(t) for t in self._t[lo:hi][bad])
        return ~bad

    def _warn(self, t_ns: int, msg: str) -> None:
        self._warned += 1
        if self._warned <= self.cfg.max_warnings:
            log.warning("t=%d ns (%.3f s into the run): %s", t_ns, self.seconds(t_ns), msg)
        elif self._warned == self.cfg.max_warnings + 1:
            log.warning("more IMU faults: counted, no longer logged one by one")

    def seconds(self, t_ns: int) -> float:
        """Seconds since the first IMU sample."""
        return (t_ns - (self.t_first or t_ns)) * 1e-9

    def gaps(self, t: np.ndarray) -> list[tuple[int, int]]:
        """(last sample before, first sample after) of every gap between consecutive
        accepted stamps ``t`` (ns)."""
        if t.shape[0] < 2:
            return []
        i = np.flatnonzero(np.diff(t) > self.max_gap_ns)
        return [(int(t[j]), int(t[j + 1])) for j in i]


def screen_imu(imu: ImuData, cfg: ImuScreenConfig = ImuScreenConfig(), rate_hz: float = 200.0,
               accel_range: float = math.inf, gyro_range: float = math.inf
               ) -> tuple[ImuData, list[tuple[int, int]], int]:
    """Screen a whole recording: (accepted samples, gaps, number dropped)."""
    s = ImuScreen(cfg, rate_hz, accel_range, gyro_range)
    s.push(imu)
    out = s.pop(final=True)
    return out, s.gaps(out.t_ns), s.n_dropped
