"""A pipeline's first initialization: which alignment, over which buffered frames, and the
replay of its window.

With cam1 the stereo-inertial alignment over the first frames
(``vio.backend.stereo_init``); otherwise, or when it fails for ``max_window_s``, the
static initialization when still (``vio.backend.init.static_init``), else the dynamic
alignment over a buffered window (``vio.backend.dynamic_init``). Stereo and dynamic
initializations replay their window through the estimator; a dynamic one is first moved
to the td remainder it found when the sync layer takes that td (``vio.init_retime``).
A re-initialization after a divergence is ``vio.reinit``'s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from vio.backend.dynamic_init import align, init_window
from vio.backend.init import InitialState, static_init
from vio.backend.stereo_init import stereo_align
from vio.errors import one_line
from vio.imu import combined_params
from vio.init_retime import replay_at_td
from vio.io.types import ImuData
from vio.outputs import FrameOutput, InitInfo
from vio.sync import FramePacket
from vio.window_outputs import window_estimates

log = logging.getLogger(__name__)


class Start:
    """The first initialization of a ``vio.pipeline.Pipeline`` (module docstring): the
    frames buffered for it, when it was reached (``info``) or why not yet (``wait``), and
    the IMU a window replayed at its found td hands to the next packet (``stitch``:
    (last frame time in ns, the window's joined IMU), ``vio.init_retime.stitch``)."""

    def __init__(self, pipe) -> None:
        self.pipe = pipe
        self.buf: list[FramePacket] = []
        self.t_first: int | None = None          # the stream's first frame time (ns)
        self.next_try: int | None = None         # a refused dynamic window's next attempt (ns)
        self.info: InitInfo | None = None
        self.wait = "no frame"
        self.stitch: tuple[int, ImuData] | None = None

    def initialize(self, pkt: FramePacket, t0: float) -> list[FrameOutput]:
        """Buffer ``pkt`` and try the initializations (module docstring); the outputs of
        the frames it started with, or [] while waiting. ``t0``: the packet's arrival
        (``time.perf_counter``)."""
        pipe, ic = self.pipe, self.pipe.cfg.backend.init
        if self.t_first is None:
            self.t_first = pkt.t_ns
        if pkt.imu_gaps and self.buf:
            # no alignment may preintegrate across the gap: the window starts again here
            # (this packet's IMU, which spans the gap, is not used as the first of a window)
            log.warning("t=%d ns: IMU gap before initialization: the initialization window "
                        "restarts after it (%d buffered frames dropped)", pkt.t_ns, len(self.buf))
            self.buf = []
            self.next_try = None
        self.buf.append(pkt)
        if pipe.est.T_c0_c1 is not None and ic.stereo.enabled:
            outs = self._stereo(t0)
            if outs is not None:
                return outs
        imu, span = pipe.window_imu()
        if span >= ic.static_window_s - 1e-3 and pipe.still_now():
            if not self.start(static_init(imu, pkt.t_ns), pkt, pkt):
                return []
            self.buf = []
            return self._still_window() + [pipe.emit(pkt, True, True, t0)]
        return self._dynamic(t0)

    def _still_window(self) -> list[FrameOutput]:
        """Outputs of the still window's earlier frames (``Pipeline.recent`` before the
        newest, judged still together with it by ``Pipeline.still_now``: IMU and image flow)
        at the static initial state, which is theirs too: the body did not move beyond the
        stillness thresholds. The initialization's first pose moves back to the window's
        first frame."""
        pipe = self.pipe
        T, _, b = pipe.est.latest()
        newest = pipe.recent[-1]
        outs = [pipe.output(p, T, np.zeros(3), b, False, True, 0.0)
                for p in pipe.recent if p.t_ns < newest.t_ns]
        if outs and self.info is not None:
            t_first = self.t_first if self.t_first is not None else newest.t_ns
            self.info = replace(self.info, state_s=(outs[0].t_ns - t_first) * 1e-9)
        return outs

    def _dynamic(self, t0: float) -> list[FrameOutput]:
        """Dynamic alignment of the buffer once it spans ``window_s``. A refused window
        grows (one more attempt every ``retry_s``: the excitation that fixes scale and
        gravity accumulates, and the first frames keep their poses) up to
        ``max_window_s``; then the oldest frames are dropped to ``0.7 window_s``."""
        pipe, buf = self.pipe, self.buf
        dc = pipe.cfg.backend.init.dynamic
        span = (buf[-1].t_ns - buf[0].t_ns) * 1e-9
        if span < dc.window_s or (self.next_try is not None and buf[-1].t_ns < self.next_try):
            if self.next_try is None:
                self.wait = (f"{span:.2f} s of frames buffered; the dynamic alignment needs {dc.window_s:.2f} s"
                             f" (a still start {pipe.cfg.backend.init.static_window_s:.2f} s)")
            return []
        res = align(init_window(buf, dc.step_s), pipe.cam, pipe.imu_calib, pipe.cfg.backend)
        if res.ok:
            self.next_try = None
            return self._replay(res.state, t0)
        log.info("dynamic initialization over %.2f s not yet possible: %s", span, res.reason)
        self.wait = f"the last dynamic alignment (over {span:.2f} s) was refused: {res.reason}"
        if span + dc.retry_s > dc.max_window_s + 1e-6:
            keep = buf[-1].t_ns - int(dc.window_s * 0.7e9)
            self.buf = [p for p in buf if p.t_ns >= keep]
            self.next_try = None
        else:
            self.next_try = buf[-1].t_ns + int(dc.retry_s * 1e9)
        return []

    def _stereo(self, t0: float) -> list[FrameOutput] | None:
        """Stereo-inertial alignment of the buffered frames (``vio.backend.stereo_init``):
        the outputs of the replayed window, [] while waiting, None when the window has
        grown past ``max_window_s`` without success (then the other initializations try)."""
        pipe = self.pipe
        sc = pipe.cfg.backend.init.stereo
        # a first frame the image stage did not match in cam1 (FrontendConfig.stereo_at: a
        # window that starts after its first seconds) cannot give the structure: the window
        # starts at the next keyframe
        buf = self.buf
        while len(buf) > 1 and buf[0].keyframe is False and not buf[0].stereo_matched:
            buf.pop(0)
        span = (buf[-1].t_ns - buf[0].t_ns) * 1e-9
        if span < sc.window_s - 1e-6:
            self.wait = f"{span:.2f} s of stereo frames buffered; the stereo alignment needs {sc.window_s:.2f} s"
            return []
        if span > sc.max_window_s + 1e-6:
            return None
        res = stereo_align(init_window(buf, 0.0), pipe.cam, pipe.est.T_c0_c1, pipe.imu_calib,
                           pipe.cfg.backend)
        if not res.ok:
            log.info("stereo initialization not yet possible over %.2f s: %s", span, res.reason)
            self.wait = f"the last stereo alignment (over {span:.2f} s) was refused: {res.reason}"
            if span + 1e-6 >= sc.max_window_s:
                log.warning("stereo initialization failed for %.1f s (%s); trying the IMU-based "
                            "initializations", span, res.reason)
            return []
        return self._replay(res.state, t0)

    def _replay(self, state: InitialState, t0: float) -> list[FrameOutput]:
        """Start at the buffer's first frame and replay the rest of the buffer."""
        pipe = self.pipe
        buf, now = self.buf, self.buf[-1]
        self.buf = []
        buf, state, joined = self._at_found_td(buf, state)
        if not self.start(state, buf[0], now):
            return []
        self.stitch = None if joined is None else (buf[-1].t_ns, joined)
        # the alignment's cost is charged to the window's first frame; the outputs leave after
        # the whole window is in, at the estimate it ended with (vio.window_outputs)
        muted, pipe.muted = pipe.muted, True
        try:
            outs = [pipe.emit(buf[0], True, False, t0)] + [pipe.step(p, time.perf_counter()) for p in buf[1:]]
        finally:
            pipe.muted = muted
        outs = window_estimates(pipe.est, outs, buf)
        for out in ([] if pipe.muted else outs):
            for sink in pipe.sinks:
                sink(out)
        return outs

    def _at_found_td(self, buf: list[FramePacket], state: InitialState
                     ) -> tuple[list[FramePacket], InitialState, ImuData | None]:
        """A dynamic initialization's window and state moved to the td remainder it found
        (``vio.init_retime.replay_at_td``) when the sync layer takes that td for the frames
        after it (``CalibConfig.td_init_retime``, ``td_feedback_at_init``), with the
        window's joined IMU; else unchanged, and None."""
        pipe = self.pipe
        cc = pipe.cfg.backend.calib
        if not (state.td_s and state.method == "dynamic" and cc.td_init_retime
                and cc.td_feedback_at_init and pipe.td_fed_back):
            return buf, state, None
        return replay_at_td(buf, state, combined_params(pipe.imu_calib, pipe.cfg.backend.imu),
                            int(round(pipe.cfg.imu_lookahead_s * 1e9)))

    def start(self, state: InitialState, pkt: FramePacket, now: FramePacket) -> bool:
        """Initialize the estimator at ``pkt`` (decided at packet ``now``); False (and
        still uninitialized) if the solver refuses."""
        pipe = self.pipe
        try:
            pipe.est.initialize(state)
        except RuntimeError as exc:
            log.error("initialization at t=%d failed (%s); will retry", pkt.t_ns, one_line(exc))
            pipe.est.smoother = None
            return False
        pipe.first_keyframe(pkt)
        pipe.n_keyframes = 1
        t_first = self.t_first if self.t_first is not None else pkt.t_ns
        # the first pose's time in the sync layer's clock at the start (a window replayed
        # at its found td holds that td, vio.init_retime)
        state_s = (pkt.t_ns - t_first) * 1e-9 - pipe.est.td_obs(pkt)
        self.info = InitInfo(state.method, (now.t_ns - t_first) * 1e-9, state_s,
                             state.td_s or 0.0, state.scale_sigma)
        log.info("%s initialization at t=%d: gyro bias %s", state.method, pkt.t_ns,
                 np.round(state.bias.gyroscope(), 4))
        return True
