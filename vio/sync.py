"""Sensor synchronization: IMU stream + camera stream -> ordered frame packets.

Each packet carries one camera frame (feature observations or image files) and
the IMU samples between the previous frame and this one, with samples linearly
interpolated exactly at both frame times, so consecutive packets tile the IMU
time axis without gaps or overlaps.

Time offset: a camera stamp plus ``td`` is the frame time in the IMU clock (VINS
convention, ``t_imu = t_stamp + td``). A constant ``td`` is applied here; an
estimated td is refined by the td projection factor on top of it.

Lookahead: with ``lookahead_s > 0`` a frame is served only once the IMU reaches
``lookahead_s`` past it (or the stream is closed), and its packet also carries those
samples (``imu_ahead``). They are not preintegrated; the estimator uses them for the
gyro over [t, t + td] when td > 0 (``vio.imu.KeyframeRates``). Cost: that much latency.

Push API (live feeds): ``add_imu`` / ``add_frame`` in any interleaving, then
``poll()`` returns the next packet, ``WAITING`` (IMU not yet available past the
frame) or ``DROPPED`` (the frame can never be served: it precedes the IMU stream,
or the IMU stream was closed before reaching it). ``packets(dataset)`` iterates
a whole dataset through the same code path.

IMU faults (``vio.faults``): every sample passes the screen before it is buffered;
impossible ones are dropped (so the interpolation between their neighbours stands in
for them) and counted in the packet that covers them (``imu_dropped``). A frame waits
for the screen's delay (``half_window`` samples) past it, like the lookahead. A packet
whose interval touches a gap (accepted samples further apart than ``max_gap_periods``
nominal periods) lists it in ``imu_gaps``: its ``imu`` is then interpolated across the
gap and must not be preintegrated (``vio.backend.estimator`` bridges it).
"""

from __future__ import annotations

import enum
import logging
import math
from collections import deque
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from vio.faults import ImuScreen, ImuScreenConfig
from vio.imu import concat
from vio.io.types import FeatureFrame, ImuData

log = logging.getLogger(__name__)


class SyncStatus(enum.Enum):
    READY = "ready"
    WAITING = "waiting"      # data not yet available: push more IMU
    DROPPED = "dropped"      # data never available for this frame
    EMPTY = "empty"          # no frame queued


@dataclass(frozen=True)
class FramePacket:
    """One synchronized camera frame.

    ``t_ns``: frame time in the IMU clock (stamp + td). ``stamp_ns``: the camera's
    own stamp. ``imu``: samples on ``[t_prev, t_ns]`` (first packet: the single
    sample at ``t_ns``), endpoints interpolated. ``imu_ahead``: samples on
    ``[t_ns, t_ns + lookahead]`` (see the module docstring). ``features``: observations
    (feature-track datasets, or a front end's output); ``image_files`` /
    ``images``: per-camera files or arrays (cam0 first). ``imu_gaps``: (last sample
    before, first sample after) in ns of each IMU gap the interval ``[t_prev, t_ns]``
    overlaps (``imu`` is not to be preintegrated then); ``imu_dropped``: impossible
    samples dropped in that interval (``vio.faults``). ``dropped``: why the frame's
    vision could not be used (an image that does not decode); its IMU then carries over
    to the next frame (:func:`carry_imu`). ``keyframe``: the image stage's keyframe
    decision where it made one (stereo matched at keyframes only,
    ``FrontendConfig.stereo_at``), else None (the pipeline decides).
    """

    index: int
    t_ns: int
    stamp_ns: int
    imu: ImuData
    features: FeatureFrame | None = None
    image_files: tuple[Path, ...] = ()
    images: tuple[np.ndarray, ...] = ()
    imu_ahead: ImuData | None = None
    imu_gaps: tuple[tuple[int, int], ...] = ()
    imu_dropped: int = 0
    dropped: str = ""
    keyframe: bool | None = None

    @property
    def imu_resumed(self) -> bool:
        """Whether the IMU resumes after a gap within this packet's interval (a gap's first
        sample after it is no later than ``t_ns``): the pipeline makes such a frame a
        keyframe, which ends the gap's bridge."""
        return any(end <= self.t_ns for _, end in self.imu_gaps)

    @property
    def dt_s(self) -> float:
        """Duration covered by ``imu`` in seconds."""
        return float(self.imu.t_ns[-1] - self.imu.t_ns[0]) * 1e-9

    @property
    def stereo_matched(self) -> bool:
        """Whether the packet's features have any cam1 match."""
        fr = self.features
        return fr is not None and fr.right_uv is not None and bool(np.isfinite(fr.right_uv).any())


@dataclass(frozen=True)
class SyncResult:
    status: SyncStatus
    packet: FramePacket | None = None
    reason: str = ""


@dataclass(frozen=True)
class _Frame:
    stamp_ns: int
    features: FeatureFrame | None
    image_files: tuple[Path, ...]
    images: tuple[np.ndarray, ...]


class Synchronizer:
    """Push-style synchronizer. ``td_s``: constant camera-to-IMU time offset (s);
    ``lookahead_s``: IMU served past each frame (s, see the module docstring);
    ``screen``: the IMU fault screen (default: ``ImuScreenConfig()`` at 200 Hz)."""

    def __init__(self, td_s: float = 0.0, lookahead_s: float = 0.0,
                 screen: ImuScreen | None = None) -> None:
        if not (np.isfinite(lookahead_s) and lookahead_s >= 0):
            raise ValueError(f"lookahead_s must be >= 0, got {lookahead_s}")
        self.td_ns = int(round(td_s * 1e9))
        self.ahead_ns = int(round(lookahead_s * 1e9))
        self.screen = ImuScreen() if screen is None else screen
        self._gaps_logged: set[tuple[int, int]] = set()
        self._t = np.zeros(0, dtype=np.int64)   # buffered IMU samples (consolidated)
        self._w = np.zeros((0, 3))
        self._a = np.zeros((0, 3))
        self._pending: list[ImuData] = []        # appended since the last consolidation
        self._t_last_imu: int | None = None
        self._frames: deque[_Frame] = deque()
        self._last_t: int | None = None     # time of the last emitted frame (IMU clock)
        self._closed = False
        self._index = 0

    def add_imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Append one IMU sample; stamps must strictly increase and values be finite."""
        gyro, accel = np.asarray(gyro, float).reshape(1, 3), np.asarray(accel, float).reshape(1, 3)
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            raise ValueError(f"non-finite IMU sample at t={t_ns}")
        self.add_imu_block(ImuData(np.array([int(t_ns)], dtype=np.int64), gyro, accel))

    def add_imu_block(self, imu: ImuData) -> None:
        """Append samples (stamps strictly increasing, continuing the stream)."""
        if len(imu) == 0:
            return
        if self._t_last_imu is not None and imu.t_ns[0] <= self._t_last_imu:
            raise ValueError(f"IMU stamp {imu.t_ns[0]} does not increase (last {self._t_last_imu})")
        if len(imu) > 1 and (np.diff(imu.t_ns) <= 0).any():
            raise ValueError("IMU block stamps do not strictly increase")
        self._pending.append(imu)
        self._t_last_imu = int(imu.t_ns[-1])

    def _consolidate(self) -> None:
        """Screen the new samples (``vio.faults``) and buffer the accepted ones."""
        for p in self._pending:
            self.screen.push(p)
        self._pending = []
        ok = self.screen.pop(self._closed)
        if len(ok):
            self._t = np.concatenate([self._t, ok.t_ns])
            self._w = np.concatenate([self._w, ok.gyro])
            self._a = np.concatenate([self._a, ok.accel])

    def add_frame(self, stamp_ns: int, features: FeatureFrame | None = None,
                  image_files: tuple[Path, ...] = (), images: tuple[np.ndarray, ...] = ()) -> None:
        """Queue a camera frame (stamps must strictly increase)."""
        stamp_ns = int(stamp_ns)
        if self._frames and stamp_ns <= self._frames[-1].stamp_ns:
            raise ValueError(f"frame stamp {stamp_ns} does not increase")
        self._frames.append(_Frame(stamp_ns, features, tuple(image_files), tuple(images)))

    def set_td(self, td_s: float) -> None:
        """Apply ``td_s`` (s) to the frames served from now on (the estimator's fed-back
        estimate, see ``vio.backend.config.CalibConfig.td_feedback_s``); a frame it would
        put at or before the previous one is dropped as usual."""
        if not np.isfinite(td_s):
            raise ValueError(f"td must be finite, got {td_s}")
        self.td_ns = int(round(td_s * 1e9))

    def close(self) -> None:
        """No more IMU will come: frames beyond the last sample become DROPPED."""
        self._closed = True

    def poll(self) -> SyncResult:
        """Serve the oldest queued frame if the IMU covers it (see module docstring)."""
        if not self._frames:
            return SyncResult(SyncStatus.EMPTY)
        fr = self._frames[0]
        t = fr.stamp_ns + self.td_ns
        self._consolidate()
        if self._t.size == 0 or t > self._t[-1]:
            if self._closed:
                self._frames.popleft()
                return SyncResult(SyncStatus.DROPPED, reason=f"frame {fr.stamp_ns}: IMU ended "
                                  f"before t={t}")
            return SyncResult(SyncStatus.WAITING, reason=f"need IMU up to t={t}")
        if not self._closed and t + self.ahead_ns > self._t[-1]:
            return SyncResult(SyncStatus.WAITING, reason=f"need IMU up to t={t + self.ahead_ns}")
        if t < self._t[0] or (self._last_t is not None and t <= self._last_t):
            self._frames.popleft()
            return SyncResult(SyncStatus.DROPPED, reason=f"frame {fr.stamp_ns}: t={t} precedes "
                              f"the IMU stream or the previous frame")
        self._frames.popleft()
        t0 = t if self._last_t is None else self._last_t
        seg = self._segment(t0, t)
        ahead = self._segment(t, min(t + self.ahead_ns, int(self._t[-1]))) if self.ahead_ns else None
        self._last_t = t
        gaps = self._gaps(t0, t)
        self._trim(t0)
        pkt = FramePacket(self._index, t, fr.stamp_ns, seg, fr.features, fr.image_files, fr.images,
                          ahead, gaps, self._take_dropped(t))
        self._index += 1
        return SyncResult(SyncStatus.READY, pkt)

    def _segment(self, t0: int, t1: int) -> ImuData:
        return ImuData(self._t, self._w, self._a).segment(t0, t1)

    def _gaps(self, t0: int, t1: int) -> tuple[tuple[int, int], ...]:
        """The IMU gaps overlapping [t0, t1] (each logged once)."""
        i0 = max(int(np.searchsorted(self._t, t0, side="right")) - 1, 0)
        i1 = int(np.searchsorted(self._t, t1, side="left")) + 1
        gaps = tuple(self.screen.gaps(self._t[i0:i1]))
        for g in gaps:
            if g not in self._gaps_logged:
                self._gaps_logged.add(g)
                log.warning("t=%d ns (%.3f s into the run): IMU gap of %.3f s (no sample until "
                            "t=%d ns): not preintegrated; bridged with vision and a motion prior",
                            g[0], self.screen.seconds(g[0]), (g[1] - g[0]) * 1e-9, g[1])
        return gaps

    def _take_dropped(self, t: int) -> int:
        """How many dropped samples precede ``t`` since the last packet (forgotten then)."""
        d = self.screen.dropped
        n = int(np.searchsorted(np.asarray(d, np.int64), t, side="right")) if d else 0
        del d[:n]
        return n

    def _trim(self, t_keep: int) -> None:
        """Forget samples no longer needed (keep the one bracketing ``t_keep``)."""
        i = int(np.searchsorted(self._t, t_keep, side="right")) - 1
        if i > 0:
            self._t, self._w, self._a = self._t[i:], self._w[i:], self._a[i:]


def carry_imu(held: FramePacket, pkt: FramePacket) -> FramePacket:
    """``pkt`` with the IMU of ``held``, a dropped frame just before it, prepended: the
    interval then runs from the last frame used, as if the camera had dropped the frame."""
    return dataclasses.replace(pkt, imu=concat([held.imu, pkt.imu]), imu_gaps=held.imu_gaps + pkt.imu_gaps,
                               imu_dropped=held.imu_dropped + pkt.imu_dropped)


def packets(imu: ImuData, frame_stamps: np.ndarray, td_s: float = 0.0,
            features: list[FeatureFrame] | None = None,
            image_files: list[tuple[Path, ...]] | None = None,
            lookahead_s: float = 0.0, screen: ImuScreenConfig = ImuScreenConfig(),
            rate_hz: float | None = None, accel_range: float = math.inf,
            gyro_range: float = math.inf,
            td_source: Callable[[], float] | None = None) -> Iterator[FramePacket]:
    """Iterate a recorded dataset as packets (frames the sync layer cannot serve, which the
    applied td moved outside the IMU stream or to before the previous frame, are skipped,
    each with a warning).

    ``features[k]`` / ``image_files[k]`` belong to ``frame_stamps[k]``. ``screen``,
    ``rate_hz`` (nominal IMU rate, ``sensor.yaml``), ``accel_range`` / ``gyro_range``:
    the IMU fault screen (``vio.faults``). The nominal period used for gaps is the
    longer of ``1/rate_hz`` and the recording's median sample interval (a mislabelled
    rate must not turn every interval into a gap). ``td_source``: called before each
    frame is served, returns the td (s) to apply to it (td feedback).
    """
    period = float(np.median(np.diff(imu.t_ns))) * 1e-9 if len(imu) > 1 else 0.0
    rates = [r for r in (rate_hz, 1.0 / period if period > 0 else None) if r]
    rate = min(rates) if rates else 200.0
    sync = Synchronizer(td_s, lookahead_s, ImuScreen(screen, rate, accel_range, gyro_range))
    sync.add_imu_block(imu)
    sync.close()
    for k, stamp in enumerate(frame_stamps):
        if td_source is not None:
            sync.set_td(td_source())
        sync.add_frame(int(stamp), features[k] if features is not None else None,
                       image_files[k] if image_files is not None else ())
        res = sync.poll()
        if res.status is SyncStatus.READY:
            yield res.packet
        elif res.status is SyncStatus.DROPPED:   # its reason says where td moved it
            log.warning("%s: not processed", res.reason)
