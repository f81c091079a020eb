"""The pipeline loop: synchronized packets -> initialization -> keyframes -> backend.

Stages exchange frozen dataclasses; the estimator never calls a visualization
sink: sinks observe ``FrameOutput`` objects (``Pipeline.sinks``).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import gtsam
import numpy as np

from vio.backend.config import BackendConfig
from vio.backend.estimator import Estimator
from vio.backend.init import imu_stillness
from vio.camera_gaps import CameraGapConfig, CameraGaps
from vio.config import check_ranges
from vio.direct.config import DirectConfig
from vio.faults import ImuScreenConfig
from vio.frontend.config import FrontendConfig
from vio.imu import concat
from vio.init_retime import stitch
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib, ImuData
from vio.keyframes import KeyframePolicy, flow_px
from vio.memory import trim_heap, tune_heap
from vio.outputs import FrameOutput, InitInfo
from vio.reinit import Reinit
from vio.start import Start
from vio.sync import FramePacket, carry_imu

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineConfig:
    """``td_s``: camera-to-IMU offset applied by the sync layer (s);
    ``backend``: estimator parameters; ``frontend``: KLT tracking (image modes);
    ``direct``: photometric points (``--mode direct|hybrid``); ``trim_heap_every_s``:
    return freed heap memory to the OS every so many seconds of data (0: never; see
    ``vio.memory``), which keeps the resident size of long runs flat; ``tune_heap``:
    glibc malloc tuned for per-frame image-sized arrays (``vio.memory.tune_heap``: 6x
    fewer page faults in the image modes; a process-wide setting, made at construction).
    ``imu_lookahead_s``: IMU the sync layer serves past each frame (s): the td term
    needs the gyro over [t, t + td] (``vio.imu.KeyframeRates``); costs that latency.
    ``imu_screen``: IMU fault screening and gap detection in the sync layer (``vio.faults``).
    ``camera_gaps``: stretches without camera frames, warned about and counted
    (``vio.camera_gaps``).
    ``live``: the backend in its own process, each frame's pose from IMU propagation of
    its newest state without waiting (``vio.live``; not deterministic; off by default).
    ``td_prepass_s`` > 0 (the photometric modes' default, ``vio.modes``): a ``direct`` or
    ``hybrid`` run first runs ``stereo`` mode over that many seconds of the data and
    starts with the sync layer at its td estimate (``vio.td_prepass``)."""

    td_s: float = 0.0
    td_prepass_s: float = 0.0
    live: bool = False
    imu_lookahead_s: float = 0.02
    imu_screen: ImuScreenConfig = field(default_factory=ImuScreenConfig)
    camera_gaps: CameraGapConfig = field(default_factory=CameraGapConfig)
    trim_heap_every_s: float = 60.0
    tune_heap: bool = True
    backend: BackendConfig = field(default_factory=BackendConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    direct: DirectConfig = field(default_factory=DirectConfig)

    def __post_init__(self) -> None:
        check_ranges(self, signed=("td_s",))


def _tracks(fr: FeatureFrame | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A frame's track ids (M,) and normalized ``uv`` (M, 2), as ``vio.keyframes`` takes
    them (None, None without features)."""
    return (None, None) if fr is None else (fr.ids, fr.uv)


class Pipeline:
    """VIO on feature packets: feed ``FramePacket``s with ``features`` in time order to
    ``process`` (image packets go through ``vio.tracking.ImageStage`` first). With
    ``cam1`` the packets' ``right_uv`` observations add stereo factors."""

    def __init__(self, imu_calib: ImuCalib, cam: CameraCalib, cfg: PipelineConfig,
                 cam1: CameraCalib | None = None) -> None:
        self.cfg = cfg
        self.cam = cam
        self.imu_calib = imu_calib
        if cfg.tune_heap:
            tune_heap()
        self.cam1 = cam1
        self.est = Estimator(imu_calib, cam, cfg.backend, cfg.td_s, cam1)
        self.reinit = Reinit(self)   # after a divergence (HealthConfig.reinit)
        # attaches fresh factor sources to a re-initialization's new estimator (None: the
        # estimator has none, or they cannot be rebuilt, and the re-initialization is off)
        self.sources_factory: Callable[[Estimator], None] | None = None
        self.muted = False           # replaying a re-initialization's buffer: no outputs
        self.init = Start(self)      # the first initialization
        self.sinks: list[Callable[[FrameOutput], None]] = []
        self.recent: deque[FramePacket] = deque()
        self.keyframes = KeyframePolicy(cfg.backend.keyframe, cam.intrinsics[0])
        self._trim_t: int | None = None
        self.n_keyframes = 0
        self.imu_gaps: set[tuple[int, int]] = set()   # (last sample before, first after), ns
        self.imu_dropped = 0
        self.frames_dropped = 0                          # images missing, unreadable or blank
        self.camera_gaps = CameraGaps(cfg.camera_gaps)   # stretches without frames
        self._held: FramePacket | None = None           # a dropped frame (FramePacket.dropped)
        self._dropped_run, self._dropped_since = 0, 0   # dropped frames in a row, the first's time (ns)
        # the packet stream's sync layer follows the estimator's td (vio.run.td_feedback)
        self.td_fed_back = False

    @property
    def init_info(self) -> InitInfo | None:
        """How the first initialization went (None: not reached; ``vio.start``)."""
        return self.init.info

    @property
    def init_wait(self) -> str:
        """Why there is no initialization yet (the run summary's)."""
        return self.init.wait

    # -------------------------------------------------------------- helpers
    def window_imu(self) -> tuple[ImuData, float]:
        """IMU of the recent packets (the deque holds ``static_window_s`` of them) and its span (s)."""
        segs = [p.imu for p in self.recent]
        imu = concat(segs)
        if len(imu) == 0:
            return imu, 0.0
        return imu, (imu.t_ns[-1] - imu.t_ns[0]) * 1e-9

    def still_now(self) -> bool:
        """The recent packets are still: their IMU (``imu_stillness``, no gap) and the median
        image flow between the first and the newest (``InitConfig.max_still_flow_px``)."""
        ic = self.cfg.backend.init
        if any(p.imu_gaps for p in self.recent):   # interpolated across a gap: looks still
            return False
        imu, span = self.window_imu()
        if span < 0.8 * ic.static_window_s:
            return False
        if not imu_stillness(imu, ic).still:
            return False
        flow, n = flow_px(*_tracks(self.recent[0].features), *_tracks(self.recent[-1].features),
                          self.keyframes.fx, median=True)
        return n == 0 or flow < ic.max_still_flow_px

    # ------------------------------------------------------------ main loop
    def process(self, pkt: FramePacket) -> list[FrameOutput]:
        """Consume one packet; returns the online estimates it produced: none while
        initializing, this frame's once initialized, and at a dynamic initialization
        every frame of the aligned window (replayed through the estimator)."""
        t0 = time.perf_counter()
        self.camera_gaps.frame(pkt.t_ns)
        if pkt.dropped:       # no vision for this frame: its IMU goes with the next one
            # the first of a run of dropped frames is warned about, the run's length at its end
            first = self._dropped_run == 0
            (log.warning if first else log.debug)(
                "t=%d ns: frame dropped (%s); its IMU carries over to the next frame", pkt.t_ns, pkt.dropped)
            self.frames_dropped += 1
            self._dropped_since = pkt.t_ns if first else self._dropped_since
            self._held = pkt if self._held is None else carry_imu(self._held, pkt)
            self._dropped_run += 1
            return []
        if self._held is not None:
            if self._dropped_run > 1:
                log.warning("t=%d ns: %d frames in a row dropped since t=%d ns (%.2f s without vision)",
                            pkt.t_ns, self._dropped_run, self._dropped_since, (pkt.t_ns - self._dropped_since) * 1e-9)
            pkt, self._held, self._dropped_run = carry_imu(self._held, pkt), None, 0
        if self.init.stitch is not None:   # the first packet after a window replayed at its td
            st = stitch(pkt, *self.init.stitch)
            if st is None:
                log.warning("t=%d ns: frame at or before the retimed initialization window's last "
                            "frame: dropped, its IMU carries over to the next frame", pkt.t_ns)
                self.frames_dropped += 1
                self._held = pkt
                return []
            pkt, self.init.stitch = st, None
        ic = self.cfg.backend.init
        self._count_faults(pkt)
        self.recent.append(pkt)
        while len(self.recent) > 1 and (pkt.t_ns - self.recent[0].t_ns) * 1e-9 > ic.static_window_s:
            self.recent.popleft()
        if not self.est.initialized:
            return self.init.initialize(pkt, t0)
        out = self.step(pkt, t0)
        self.reinit.after_step(pkt, out)
        return [out]

    def step(self, pkt: FramePacket, t0: float) -> FrameOutput:
        self._maybe_trim(pkt.t_ns)
        self.est.flush_outliers()    # the last keyframe's outlier update (SolverConfig.outlier_update)
        self.est.add_imu(pkt.imu, pkt.imu_ahead, gap=bool(pkt.imu_gaps))
        still = self.still_now()
        # the IMU resumed in this packet: a keyframe here ends the bridge, the next interval
        # gets an IMU factor again
        if self.takes_keyframe(pkt):
            self.est.add_keyframe(pkt.t_ns, self._features(pkt), still, pkt.imu.gyro[-1], pkt)
            self._keyframe_taken(pkt)
            self.n_keyframes += 1
            return self.emit(pkt, True, still, t0)
        out = self.emit(pkt, False, still, t0)
        self.est.prefetch(pkt.t_ns)   # the next update's farewells, once this frame has its pose
        return out

    def _count_faults(self, pkt: FramePacket) -> None:
        """Count the IMU gaps (distinct) and dropped samples of a packet (``vio.faults``)."""
        self.imu_dropped += pkt.imu_dropped
        for g in pkt.imu_gaps:
            self.imu_gaps.add(g)

    def _maybe_trim(self, t_ns: int) -> None:
        every = self.cfg.trim_heap_every_s
        if every <= 0:
            return
        if self._trim_t is None:
            self._trim_t = t_ns
        elif (t_ns - self._trim_t) * 1e-9 >= every:
            trim_heap()
            self._trim_t = t_ns

    def _features(self, pkt: FramePacket) -> FeatureFrame:
        if pkt.features is not None:
            return pkt.features
        return FeatureFrame.empty(pkt.t_ns)

    def first_keyframe(self, pkt: FramePacket) -> None:
        """The observations of the keyframe an estimator was just initialized at."""
        self.est.first_keyframe(pkt)
        self.est.lm.observe(0, self._features(pkt))
        for src in self.est.sources:
            src.observe(0, pkt)
        self._keyframe_taken(pkt)

    def _keyframe_taken(self, pkt: FramePacket) -> None:
        self.keyframes.reset(pkt.t_ns, *_tracks(pkt.features))

    def adopt(self, est: Estimator, buf: list[FramePacket]) -> None:
        """Let ``est``, initialized at ``buf[0]``, take over: ``buf[1:]`` is replayed
        through it without outputs (``vio.reinit``); the keyframe count stays."""
        n = self.n_keyframes
        self.est = est
        self.first_keyframe(buf[0])
        self.muted = True
        try:
            for p in buf[1:]:
                self.step(p, time.perf_counter())
        finally:
            self.muted = False
        self.n_keyframes = n

    def takes_keyframe(self, pkt: FramePacket) -> bool:
        """Whether ``step`` makes this packet a keyframe (state unchanged): where the IMU
        resumes, else the image stage's decision where it made one
        (``FramePacket.keyframe``: it matched cam1 there), else ``KeyframeConfig``'s policy."""
        if pkt.imu_resumed:
            return True
        if pkt.keyframe is not None:
            return pkt.keyframe
        return self.keyframes.due(pkt.t_ns, *_tracks(pkt.features))

    def emit(self, pkt: FramePacket, is_kf: bool, still: bool, t0: float) -> FrameOutput:
        if is_kf:
            T, v, b = self.est.latest()
            ids, pts = self.est.landmarks_w()
        else:
            nav = self.est.frame_state(pkt.features, pkt.imu.gyro[-1] if len(pkt.imu.gyro) else None, pkt)
            T, v = nav.pose(), nav.velocity()
            b, ids, pts = self.est.latest()[2], None, None
        return self.output(pkt, T, np.asarray(v), b, is_kf, still, time.perf_counter() - t0, ids, pts)

    def output(self, pkt: FramePacket, T: gtsam.Pose3, v: np.ndarray, b, is_kf: bool, still: bool,
                seconds: float, ids: np.ndarray | None = None, pts: np.ndarray | None = None) -> FrameOutput:
        """The output of ``pkt`` at state ``T``, ``v``, ``b``, given to the sinks (unless muted)."""
        out = FrameOutput(pkt.index, pkt.t_ns, T, v, b, is_kf, still, seconds,
                          0 if pkt.features is None else len(pkt.features.ids),
                          self.est.lm.n_active(), self.est.td(), self.est.extrinsic(), ids, pts,
                          pkt.features, pkt)
        for sink in ([] if self.muted else self.sinks):
            sink(out)
        return out
