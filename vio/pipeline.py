"""The pipeline loop: synchronized packets -> initialization -> keyframes -> backend.

Stages exchange frozen dataclasses; the estimator never calls a visualization
sink: sinks observe ``FrameOutput`` objects (``Pipeline.sinks``).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Callable

import gtsam
import numpy as np

from vio.backend.config import BackendConfig
from vio.backend.estimator import Estimator
from vio.backend.dynamic_init import align, init_window
from vio.backend.init import imu_stillness, static_init
from vio.backend.stereo_init import stereo_align
from vio.config import check_ranges
from vio.direct.config import DirectConfig
from vio.errors import one_line
from vio.faults import ImuScreenConfig
from vio.frontend.config import FrontendConfig
from vio.imu import combined_params, concat
from vio.init_retime import replay_at_td, stitch
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib, ImuData
from vio.keyframes import KeyframePolicy, flow_px
from vio.memory import trim_heap, tune_heap
from vio.outputs import FrameOutput, InitInfo
from vio.reinit import Reinit
from vio.sync import FramePacket, carry_imu
from vio.window_outputs import window_estimates

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
    ``live``: the backend in its own process, each frame's pose from IMU propagation of
    its newest state without waiting (``vio.live``; not deterministic; off by default)."""

    td_s: float = 0.0
    live: bool = False
    imu_lookahead_s: float = 0.02
    imu_screen: ImuScreenConfig = field(default_factory=ImuScreenConfig)
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
        self._init_buf: list[FramePacket] = []
        self.sinks: list[Callable[[FrameOutput], None]] = []
        self._recent: deque[FramePacket] = deque()
        self.keyframes = KeyframePolicy(cfg.backend.keyframe, cam.intrinsics[0])
        self._trim_t: int | None = None
        self.n_keyframes = 0
        self._t_first: int | None = None
        self._next_try: int | None = None
        self.init_info: InitInfo | None = None
        self.init_wait = "no frame"       # why no initialization yet (the run summary's)
        self.imu_gaps: set[tuple[int, int]] = set()   # (last sample before, first after), ns
        self.imu_dropped = 0
        self.frames_dropped = 0                          # images missing or unreadable
        self._held: FramePacket | None = None           # a dropped frame (FramePacket.dropped)
        # (last frame time, IMU) of a window replayed at its found td (vio.init_retime)
        self._stitch: tuple[int, ImuData] | None = None
        # the packet stream's sync layer follows the estimator's td (vio.run.td_feedback)
        self.td_fed_back = False

    # -------------------------------------------------------------- helpers
    def _window_imu(self):
        """IMU of the recent packets (the deque holds ``static_window_s`` of them) and its span (s)."""
        segs = [p.imu for p in self._recent]
        imu = concat(segs)
        if len(imu) == 0:
            return imu, 0.0
        return imu, (imu.t_ns[-1] - imu.t_ns[0]) * 1e-9

    def _still(self) -> bool:
        ic = self.cfg.backend.init
        if any(p.imu_gaps for p in self._recent):   # interpolated across a gap: looks still
            return False
        imu, span = self._window_imu()
        if span < 0.8 * ic.static_window_s:
            return False
        if not imu_stillness(imu, ic).still:
            return False
        flow, n = flow_px(*_tracks(self._recent[0].features), *_tracks(self._recent[-1].features),
                          self.keyframes.fx, median=True)
        return n == 0 or flow < ic.max_still_flow_px

    # ------------------------------------------------------------ main loop
    def process(self, pkt: FramePacket) -> list[FrameOutput]:
        """Consume one packet; returns the online estimates it produced: none while
        initializing, this frame's once initialized, and at a dynamic initialization
        every frame of the aligned window (replayed through the estimator)."""
        t0 = time.perf_counter()
        if pkt.dropped:       # no vision for this frame: its IMU goes with the next one
            log.warning("t=%d ns: frame dropped (%s); its IMU carries over to the next frame", pkt.t_ns,
                        pkt.dropped)
            self.frames_dropped += 1
            self._held = pkt if self._held is None else carry_imu(self._held, pkt)
            return []
        if self._held is not None:
            pkt, self._held = carry_imu(self._held, pkt), None
        if self._stitch is not None:   # the first packet after a window replayed at its td
            st = stitch(pkt, *self._stitch)
            if st is None:
                log.warning("t=%d ns: frame at or before the retimed initialization window's last "
                            "frame: dropped, its IMU carries over to the next frame", pkt.t_ns)
                self.frames_dropped += 1
                self._held = pkt
                return []
            pkt, self._stitch = st, None
        ic = self.cfg.backend.init
        self._count_faults(pkt)
        self._recent.append(pkt)
        while len(self._recent) > 1 and (pkt.t_ns - self._recent[0].t_ns) * 1e-9 > ic.static_window_s:
            self._recent.popleft()
        if not self.est.initialized:
            return self._initialize(pkt, t0)
        out = self._step(pkt, t0)
        self.reinit.after_step(pkt, out)
        return [out]

    def _step(self, pkt: FramePacket, t0: float) -> FrameOutput:
        self._maybe_trim(pkt.t_ns)
        self.est.flush_outliers()    # the last keyframe's outlier update (SolverConfig.outlier_update)
        self.est.add_imu(pkt.imu, pkt.imu_ahead, gap=bool(pkt.imu_gaps))
        still = self._still()
        # the IMU resumed in this packet: a keyframe here ends the bridge, the next interval
        # gets an IMU factor again
        if pkt.imu_resumed or self._is_keyframe(pkt):
            self.est.add_keyframe(pkt.t_ns, self._features(pkt), still, pkt.imu.gyro[-1], pkt)
            self._keyframe_taken(pkt)
            self.n_keyframes += 1
            return self._emit(pkt, True, still, t0)
        out = self._emit(pkt, False, still, t0)
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

    def _initialize(self, pkt: FramePacket, t0: float) -> list[FrameOutput]:
        """With cam1 the stereo-inertial alignment over the first frames; otherwise (or
        when it fails for ``max_window_s``) static initialization when still, else
        dynamic alignment over a buffered window. Stereo and dynamic initialization
        replay their window through the estimator."""
        ic = self.cfg.backend.init
        if self._t_first is None:
            self._t_first = pkt.t_ns
        if pkt.imu_gaps and self._init_buf:
            # no alignment may preintegrate across the gap: the window starts again here
            # (this packet's IMU, which spans the gap, is not used as the first of a window)
            log.warning("t=%d ns: IMU gap before initialization: the initialization window "
                        "restarts after it (%d buffered frames dropped)", pkt.t_ns, len(self._init_buf))
            self._init_buf = []
            self._next_try = None
        self._init_buf.append(pkt)
        if self.est.T_c0_c1 is not None and ic.stereo.enabled:
            outs = self._stereo_initialize(pkt, t0)
            if outs is not None:
                return outs
        imu, span = self._window_imu()
        if span >= ic.static_window_s - 1e-3 and self._still():
            if not self._start(static_init(imu, pkt.t_ns), pkt, pkt):
                return []
            self._init_buf = []
            return self._still_window() + [self._emit(pkt, True, True, t0)]
        return self._dynamic_initialize(t0)

    def _still_window(self) -> list[FrameOutput]:
        """Outputs of the still window's earlier frames (``_recent`` before the newest, judged
        still together with it by ``_still``: IMU and image flow) at the static initial
        state, which is theirs too: the body did not move beyond the stillness thresholds.
        The initialization's first pose moves back to the window's first frame."""
        T, _, b = self.est.latest()
        newest = self._recent[-1]
        outs = [self._output(p, T, np.zeros(3), b, False, True, 0.0)
                for p in self._recent if p.t_ns < newest.t_ns]
        if outs and self.init_info is not None:
            t_first = self._t_first if self._t_first is not None else newest.t_ns
            self.init_info = replace(self.init_info, state_s=(outs[0].t_ns - t_first) * 1e-9)
        return outs

    def _dynamic_initialize(self, t0: float) -> list[FrameOutput]:
        """Dynamic alignment of the buffer once it spans ``window_s``. A refused window
        grows (one more attempt every ``retry_s``: the excitation that fixes scale and
        gravity accumulates, and the first frames keep their poses) up to
        ``max_window_s``; then the oldest frames are dropped to ``0.7 window_s``."""
        dc = self.cfg.backend.init.dynamic
        buf = self._init_buf
        span = (buf[-1].t_ns - buf[0].t_ns) * 1e-9
        if span < dc.window_s or (self._next_try is not None and buf[-1].t_ns < self._next_try):
            if self._next_try is None:
                self.init_wait = (f"{span:.2f} s of frames buffered; the dynamic alignment needs {dc.window_s:.2f} s"
                                  f" (a still start {self.cfg.backend.init.static_window_s:.2f} s)")
            return []
        res = align(init_window(buf, dc.step_s), self.cam, self.imu_calib, self.cfg.backend)
        if res.ok:
            self._next_try = None
            return self._replay(res.state, t0)
        log.info("dynamic initialization over %.2f s not yet possible: %s", span, res.reason)
        self.init_wait = f"the last dynamic alignment (over {span:.2f} s) was refused: {res.reason}"
        if span + dc.retry_s > dc.max_window_s + 1e-6:
            keep = buf[-1].t_ns - int(dc.window_s * 0.7e9)
            self._init_buf = [p for p in buf if p.t_ns >= keep]
            self._next_try = None
        else:
            self._next_try = buf[-1].t_ns + int(dc.retry_s * 1e9)
        return []

    def _stereo_initialize(self, pkt: FramePacket, t0: float) -> list[FrameOutput] | None:
        """Stereo-inertial alignment of the buffered frames (``vio.backend.stereo_init``):
        the outputs of the replayed window, [] while waiting, None when the window has
        grown past ``max_window_s`` without success (then the other initializations try)."""
        sc = self.cfg.backend.init.stereo
        # a first frame the image stage did not match in cam1 (FrontendConfig.stereo_at: a
        # window that starts after its first seconds) cannot give the structure: the window
        # starts at the next keyframe
        buf = self._init_buf
        while len(buf) > 1 and buf[0].keyframe is False and not buf[0].stereo_matched:
            buf.pop(0)
        span = (buf[-1].t_ns - buf[0].t_ns) * 1e-9
        if span < sc.window_s - 1e-6:
            self.init_wait = f"{span:.2f} s of stereo frames buffered; the stereo alignment needs {sc.window_s:.2f} s"
            return []
        if span > sc.max_window_s + 1e-6:
            return None
        res = stereo_align(init_window(buf, 0.0), self.cam, self.est.T_c0_c1, self.imu_calib,
                           self.cfg.backend)
        if not res.ok:
            log.info("stereo initialization not yet possible over %.2f s: %s", span, res.reason)
            self.init_wait = f"the last stereo alignment (over {span:.2f} s) was refused: {res.reason}"
            if span + 1e-6 >= sc.max_window_s:
                log.warning("stereo initialization failed for %.1f s (%s); trying the IMU-based "
                            "initializations", span, res.reason)
            return []
        return self._replay(res.state, t0)

    def _replay(self, state, t0: float) -> list[FrameOutput]:
        """Start at the buffer's first frame and replay the rest of the buffer."""
        buf, now = self._init_buf, self._init_buf[-1]
        self._init_buf = []
        buf, state, joined = self._at_found_td(buf, state)
        if not self._start(state, buf[0], now):
            return []
        self._stitch = None if joined is None else (buf[-1].t_ns, joined)
        # the alignment's cost is charged to the window's first frame; the outputs leave after
        # the whole window is in, at the estimate it ended with (vio.window_outputs)
        muted, self.muted = self.muted, True
        try:
            outs = [self._emit(buf[0], True, False, t0)] + [self._step(p, time.perf_counter()) for p in buf[1:]]
        finally:
            self.muted = muted
        outs = window_estimates(self.est, outs, buf)
        for out in ([] if self.muted else outs):
            for sink in self.sinks:
                sink(out)
        return outs

    def _at_found_td(self, buf: list[FramePacket], state) -> tuple[list[FramePacket], object, ImuData | None]:
        """A dynamic initialization's window and state moved to the td remainder it found
        (``vio.init_retime.replay_at_td``) when the sync layer takes that td for the frames
        after it (``CalibConfig.td_init_retime``, ``td_feedback_at_init``), with the
        window's joined IMU; else unchanged, and None."""
        cc = self.cfg.backend.calib
        if not (state.td_s and state.method == "dynamic" and cc.td_init_retime
                and cc.td_feedback_at_init and self.td_fed_back):
            return buf, state, None
        return replay_at_td(buf, state, combined_params(self.imu_calib, self.cfg.backend.imu),
                            int(round(self.cfg.imu_lookahead_s * 1e9)))

    def _start(self, state, pkt: FramePacket, now: FramePacket) -> bool:
        """Initialize the estimator at ``pkt`` (decided at packet ``now``); False (and
        still uninitialized) if the solver refuses."""
        try:
            self.est.initialize(state)
        except RuntimeError as exc:
            log.error("initialization at t=%d failed (%s); will retry", pkt.t_ns,
                      one_line(exc))
            self.est.smoother = None
            return False
        self._first_keyframe(pkt)
        self.n_keyframes = 1
        t_first = self._t_first if self._t_first is not None else pkt.t_ns
        # the first pose's time in the sync layer's clock at the start (a window replayed
        # at its found td holds that td, vio.init_retime)
        state_s = (pkt.t_ns - t_first) * 1e-9 - self.est.td_obs(pkt)
        self.init_info = InitInfo(state.method, (now.t_ns - t_first) * 1e-9, state_s,
                                  state.td_s or 0.0, state.scale_sigma)
        log.info("%s initialization at t=%d: gyro bias %s", state.method, pkt.t_ns,
                 np.round(state.bias.gyroscope(), 4))
        return True

    def _first_keyframe(self, pkt: FramePacket) -> None:
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
        self._first_keyframe(buf[0])
        self.muted = True
        try:
            for p in buf[1:]:
                self._step(p, time.perf_counter())
        finally:
            self.muted = False
        self.n_keyframes = n

    def _is_keyframe(self, pkt: FramePacket) -> bool:
        """The image stage's decision where it made one (``FramePacket.keyframe``: it
        matched cam1 there), else ``KeyframeConfig``'s policy."""
        if pkt.keyframe is not None:
            return pkt.keyframe
        return self.keyframes.due(pkt.t_ns, *_tracks(pkt.features))

    def _emit(self, pkt: FramePacket, is_kf: bool, still: bool, t0: float) -> FrameOutput:
        if is_kf:
            T, v, b = self.est.latest()
            ids, pts = self.est.landmarks_w()
        else:
            nav = self.est.frame_state(pkt.features, pkt.imu.gyro[-1] if len(pkt.imu.gyro) else None, pkt)
            T, v = nav.pose(), nav.velocity()
            b, ids, pts = self.est.latest()[2], None, None
        return self._output(pkt, T, np.asarray(v), b, is_kf, still, time.perf_counter() - t0, ids, pts)

    def _output(self, pkt: FramePacket, T: gtsam.Pose3, v: np.ndarray, b, is_kf: bool, still: bool,
                seconds: float, ids: np.ndarray | None = None, pts: np.ndarray | None = None) -> FrameOutput:
        """The output of ``pkt`` at state ``T``, ``v``, ``b``, given to the sinks (unless muted)."""
        out = FrameOutput(pkt.index, pkt.t_ns, T, v, b, is_kf, still, seconds,
                          0 if pkt.features is None else len(pkt.features.ids),
                          self.est.lm.n_active(), self.est.td(), self.est.extrinsic(), ids, pts,
                          pkt.features, pkt)
        for sink in ([] if self.muted else self.sinks):
            sink(out)
        return out
