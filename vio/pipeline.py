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
from vio.backend.dynamic_init import align, init_window
from vio.backend.init import imu_stillness, static_init
from vio.direct.config import DirectConfig
from vio.frontend.config import FrontendConfig
from vio.imu import concat
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib
from vio.memory import trim_heap
from vio.sync import FramePacket

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineConfig:
    """``td_s``: camera-to-IMU offset applied by the sync layer (s);
    ``backend``: estimator parameters; ``frontend``: KLT tracking (image modes);
    ``direct``: photometric points (``--mode direct|hybrid``); ``trim_heap_every_s``:
    return freed heap memory to the OS every so many seconds of data (0: never; see
    ``vio.memory``), which keeps the resident size of long runs flat.
    ``imu_lookahead_s``: IMU the sync layer serves past each frame (s): the td term
    needs the gyro over [t, t + td] (``vio.imu.KeyframeRates``); costs that latency.
    ``live``: the backend in its own process, each frame's pose from IMU propagation of
    its newest state without waiting (``vio.live``; not deterministic; off by default)."""

    td_s: float = 0.0
    live: bool = False
    imu_lookahead_s: float = 0.02
    trim_heap_every_s: float = 60.0
    backend: BackendConfig = field(default_factory=BackendConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    direct: DirectConfig = field(default_factory=DirectConfig)


@dataclass(frozen=True)
class FrameOutput:
    """The online estimate at one frame (``T_w_b`` body in world, ``v_w`` m/s)."""

    index: int
    t_ns: int
    T_w_b: gtsam.Pose3
    v_w: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    keyframe: bool
    still: bool
    seconds: float
    n_features: int
    n_landmarks: int
    td_s: float
    T_b_c: gtsam.Pose3
    landmark_ids: np.ndarray | None = None
    landmarks_w: np.ndarray | None = None
    features: FeatureFrame | None = None
    packet: FramePacket | None = None


class Pipeline:
    """VIO on feature packets: feed ``FramePacket``s with ``features`` in time order to
    ``process`` (image packets go through ``vio.tracking.ImageStage`` first). With
    ``cam1`` the packets' ``right_uv`` observations add stereo factors."""

    def __init__(self, imu_calib: ImuCalib, cam: CameraCalib, cfg: PipelineConfig,
                 cam1: CameraCalib | None = None) -> None:
        self.cfg = cfg
        self.cam = cam
        self.imu_calib = imu_calib
        self.est = Estimator(imu_calib, cam, cfg.backend, cfg.td_s, cam1)
        self._init_buf: list[FramePacket] = []
        self.sinks: list[Callable[[FrameOutput], None]] = []
        self._recent: deque[FramePacket] = deque()
        self._kf_features: FeatureFrame | None = None
        self._kf_t: int = 0
        self._trim_t: int | None = None
        self.n_keyframes = 0

    # -------------------------------------------------------------- helpers
    def _window_imu(self):
        """IMU of the recent packets (the deque holds ``static_window_s`` of them) and its span (s)."""
        segs = [p.imu for p in self._recent]
        imu = concat(segs)
        if len(imu) == 0:
            return imu, 0.0
        return imu, (imu.t_ns[-1] - imu.t_ns[0]) * 1e-9

    def _flow_px(self, a: FeatureFrame | None, b: FeatureFrame | None,
                 median: bool = False) -> tuple[float, int]:
        """Mean (or median) displacement (px) of features common to two frames, and their count."""
        if a is None or b is None:
            return 0.0, 0
        common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
        if common.size == 0:
            return 0.0, 0
        d = np.linalg.norm(a.uv[ia] - b.uv[ib], axis=1) * self.cam.intrinsics[0]
        return float(np.median(d) if median else d.mean()), int(common.size)

    def _still(self) -> bool:
        ic = self.cfg.backend.init
        imu, span = self._window_imu()
        if span < 0.8 * ic.static_window_s:
            return False
        if not imu_stillness(imu, ic).still:
            return False
        first, last = self._recent[0].features, self._recent[-1].features
        flow, n = self._flow_px(first, last, median=True)
        return n == 0 or flow < ic.max_still_flow_px

    # ------------------------------------------------------------ main loop
    def process(self, pkt: FramePacket) -> list[FrameOutput]:
        """Consume one packet; returns the online estimates it produced: none while
        initializing, this frame's once initialized, and at a dynamic initialization
        every frame of the aligned window (replayed through the estimator)."""
        t0 = time.perf_counter()
        ic = self.cfg.backend.init
        self._recent.append(pkt)
        while len(self._recent) > 1 and (pkt.t_ns - self._recent[0].t_ns) * 1e-9 > ic.static_window_s:
            self._recent.popleft()
        if not self.est.initialized:
            return self._initialize(pkt, t0)
        return [self._step(pkt, t0)]

    def _step(self, pkt: FramePacket, t0: float) -> FrameOutput:
        self._maybe_trim(pkt.t_ns)
        self.est.add_imu(pkt.imu, pkt.imu_ahead)
        still = self._still()
        if self._is_keyframe(pkt):
            self.est.add_keyframe(pkt.t_ns, self._features(pkt), still, pkt.imu.gyro[-1], pkt)
            self._kf_features, self._kf_t = pkt.features, pkt.t_ns
            self.n_keyframes += 1
            return self._emit(pkt, True, still, t0)
        return self._emit(pkt, False, still, t0)

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
        return FeatureFrame(pkt.t_ns, np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)),
                            np.zeros(0))

    def _initialize(self, pkt: FramePacket, t0: float) -> list[FrameOutput]:
        """Static initialization when still, else dynamic alignment over a buffered
        window, which is then replayed through the estimator."""
        ic = self.cfg.backend.init
        self._init_buf.append(pkt)
        imu, span = self._window_imu()
        if span >= ic.static_window_s - 1e-3 and self._still():
            if not self._start(static_init(imu, pkt.t_ns), pkt):
                return []
            self._init_buf = []
            return [self._emit(pkt, True, True, t0)]
        buf = self._init_buf
        if (buf[-1].t_ns - buf[0].t_ns) * 1e-9 < ic.dynamic.window_s:
            return []
        res = align(init_window(buf, ic.dynamic.step_s), self.cam, self.imu_calib, self.cfg.backend)
        if not res.ok:
            log.info("dynamic initialization not yet possible: %s", res.reason)
            keep = buf[-1].t_ns - int(ic.dynamic.window_s * 0.7e9)
            self._init_buf = [p for p in buf if p.t_ns >= keep]
            return []
        self._init_buf = []
        if not self._start(res.state, buf[0]):
            return []
        # the alignment's cost is charged to the window's first frame
        outs = [self._emit(buf[0], True, False, t0)]
        return outs + [self._step(p, time.perf_counter()) for p in buf[1:]]

    def _start(self, state, pkt: FramePacket) -> bool:
        """Initialize the estimator; False (and still uninitialized) if the solver refuses."""
        try:
            self.est.initialize(state)
        except RuntimeError as exc:
            log.error("initialization at t=%d failed (%s); will retry", pkt.t_ns,
                      str(exc).splitlines()[0][:120])
            self.est.smoother = None
            return False
        self.est.rates.add_keyframe(0, pkt.t_ns, pkt.imu.gyro[-1])
        self.est.lm.observe(0, self._features(pkt))
        for src in self.est.sources:
            src.observe(0, pkt)
        self._kf_features, self._kf_t = pkt.features, pkt.t_ns
        self.n_keyframes = 1
        log.info("%s initialization at t=%d: gyro bias %s", state.method, pkt.t_ns,
                 np.round(state.bias.gyroscope(), 4))
        return True

    def _is_keyframe(self, pkt: FramePacket) -> bool:
        kc = self.cfg.backend.keyframe
        dt = (pkt.t_ns - self._kf_t) * 1e-9
        if dt < kc.min_interval_s:
            return False
        if dt >= kc.max_interval_s:
            return True
        flow, n = self._flow_px(self._kf_features, pkt.features)
        return flow >= kc.min_parallax_px or n < kc.min_tracked

    def _emit(self, pkt: FramePacket, is_kf: bool, still: bool, t0: float) -> FrameOutput:
        if is_kf:
            T, v, b = self.est.latest()
            ids, pts = self.est.landmarks_w()
        else:
            nav = self.est.predict()
            T, v = nav.pose(), nav.velocity()
            b, ids, pts = self.est.latest()[2], None, None
        out = FrameOutput(pkt.index, pkt.t_ns, T, np.asarray(v), b, is_kf, still,
                          time.perf_counter() - t0,
                          0 if pkt.features is None else len(pkt.features.ids),
                          self.est.lm.n_active(), self.est.td(), self.est.extrinsic(), ids, pts,
                          pkt.features, pkt)
        for sink in self.sinks:
            sink(out)
        return out
