"""Live operation: the backend's keyframe updates off the frame path.

``PipelineConfig.live`` (``vio run --live``): the whole ``Pipeline`` (initialization,
keyframe updates, outlier removal) runs in a worker process (``vio.overlap``'s
protocol) and is fed every packet in order, so the smoother sees exactly the input of
the default, in-process run and computes the same keyframe states. The frame path in
the main process never waits for it: each frame's pose is the newest keyframe state the
worker has reported, propagated with the IMU received since (a
``PreintegratedCombinedMeasurements`` from that keyframe at its bias). What it costs:
the online pose of a keyframe frame is this prediction rather than the updated
estimate, and while the worker lags behind, frames are predicted from an older
keyframe; which state a frame sees depends on timing, so the online trajectory is not
deterministic (the keyframe states are). The reported state carries its window's
landmarks, and a frame whose prediction vision contradicts is output at its PnP pose, as
in-process (:func:`checked`; real MH_01 stereo, +6 m/s^2 over frames 40-59: 22.2 ->
6.5 mm). Frames before the worker's first state get no output. A recorded dataset is
replayed at its camera rate (real time). The default (``live = False``) stays
deterministic.

The GIL is held through ``ISAM2.update`` (measured: a 0.47 s update blocks another
thread for 0.47 s), which is why the backend needs its own process, not a thread.
"""

from __future__ import annotations

import dataclasses
import fcntl
import logging
import queue
import select
import threading
import time
from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np

from vio.backend.bridge import frame_state, shift_by
from vio.imu import combined_params, integrate
from vio.io.types import CameraCalib, ImuCalib, ImuData
from vio.overlap import WorkerError, _recv, _send, _shutdown, _worker_process
from vio.pipeline import FrameOutput, Pipeline, PipelineConfig
from vio.sync import FramePacket

log = logging.getLogger(__name__)

_PIPE_BYTES = 1 << 20   # Linux F_SETPIPE_SZ: ~1 MB of packets may queue before the frame path blocks


@dataclass(frozen=True)
class KeyState:
    """The newest keyframe estimate after one worker step (picklable, small): time (ns),
    ``T_w_b`` (4, 4), ``v_w`` (3,) m/s, bias [accel, gyro] (6,), td (s), ``T_b_c`` (4, 4),
    landmarks in the window, keyframes and solver recoveries so far; the ids (N,) and world
    points (N, 3) the frames' check stands on (:func:`checked`, ``Estimator.frame_points``)."""

    t_ns: int
    T_w_b: np.ndarray
    v_w: np.ndarray
    bias: np.ndarray
    td_s: float
    T_b_c: np.ndarray
    n_landmarks: int
    n_keyframes: int
    recoveries: int
    landmark_ids: np.ndarray | None = None
    landmarks_w: np.ndarray | None = None


class BackendStage:
    """The worker's stage: a ``Pipeline``; each packet -> the newest ``KeyState`` (None
    until initialized, and unchanged states are sent again: one reply per packet)."""

    def __init__(self, imu_calib: ImuCalib, cam: CameraCalib, cfg: PipelineConfig,
                 cam1: CameraCalib | None) -> None:
        self.pipe = Pipeline(imu_calib, cam, cfg, cam1)
        self.state: KeyState | None = None

    def __call__(self, pkt: FramePacket) -> KeyState | None:
        outs = self.pipe.process(pkt)
        kfs = [o for o in outs if o.keyframe]
        if kfs:
            o = kfs[-1]
            est = self.pipe.est
            self.state = KeyState(o.t_ns, o.T_w_b.matrix(), np.asarray(o.v_w, float), o.bias.vector(),
                                  o.td_s, o.T_b_c.matrix(), o.n_landmarks, self.pipe.n_keyframes,
                                  est.recoveries, *est.frame_points())
        return self.state


class LivePipeline:
    """``Pipeline``'s ``process`` interface with the backend in a worker process (see the
    module docstring). Call ``close`` at the end (it waits for the worker's last state)."""

    def __init__(self, imu_calib: ImuCalib, cam: CameraCalib, cfg: PipelineConfig,
                 cam1: CameraCalib | None = None) -> None:
        self.cfg, self.cam = cfg, cam
        self.params = combined_params(imu_calib, cfg.backend.imu)
        self.sinks: list = []
        self.frame_contradictions = 0   # frames output at their PnP pose (checked)
        self.state: KeyState | None = None
        self._segments: deque[tuple[int, ImuData]] = deque()   # packets after state.t_ns
        self._pim: gtsam.PreintegratedCombinedMeasurements | None = None
        self._pending = 0
        self._clock: tuple[float, int] | None = None   # (wall s, data ns) of the first packet
        self._proc = _worker_process()
        for stream in (self._proc.stdin, self._proc.stdout):
            try:
                fcntl.fcntl(stream.fileno(), 1031, _PIPE_BYTES)   # F_SETPIPE_SZ
            except OSError:
                pass
        _send(self._proc.stdin, (BackendStage, (imu_calib, cam, cfg, cam1)))
        # a writer thread feeds the worker: when it lags and its pipe is full, the frame
        # path queues the packet instead of blocking (the write releases the GIL)
        self._outbox: queue.Queue = queue.Queue()
        self._write_error: BaseException | None = None
        self._writer = threading.Thread(target=self._write_loop, name="vio-live-writer", daemon=True)
        self._writer.start()

    def _write_loop(self) -> None:
        while (pkt := self._outbox.get()) is not None:
            if self._write_error is None:
                try:
                    _send(self._proc.stdin, pkt)
                except (BrokenPipeError, OSError, ValueError) as exc:
                    self._write_error = exc   # the worker died: _poll reports why

    @property
    def n_keyframes(self) -> int:
        return 0 if self.state is None else self.state.n_keyframes

    @property
    def recoveries(self) -> int:
        return 0 if self.state is None else self.state.recoveries

    def process(self, pkt: FramePacket) -> list[FrameOutput]:
        """Hand the packet to the worker, take any state it has finished, and return this
        frame's IMU-propagated estimate (none before the first state). Packets are released
        at their data time (a recorded dataset replays at the camera rate, as it was taken:
        read faster, every frame would be predicted from a state far behind)."""
        if self._clock is None:
            self._clock = (time.perf_counter(), pkt.t_ns)
        due = self._clock[0] + (pkt.t_ns - self._clock[1]) * 1e-9
        time.sleep(max(0.0, due - time.perf_counter()))
        t0 = time.perf_counter()
        self._outbox.put(_light(pkt))
        self._pending += 1
        self._segments.append((pkt.t_ns, pkt.imu))
        if self._pim is not None:
            integrate(self._pim, pkt.imu)
        self._poll(0.0)
        nav = self.predict()
        if nav is None:
            return []
        s = self.state
        nav = checked(self, nav, pkt)
        bias = gtsam.imuBias.ConstantBias(s.bias[:3], s.bias[3:])
        n_feat = 0 if pkt.features is None else len(pkt.features.ids)
        out = FrameOutput(pkt.index, pkt.t_ns, nav.pose(), np.asarray(nav.velocity()), bias, False, False,
                          time.perf_counter() - t0, n_feat, s.n_landmarks, s.td_s, gtsam.Pose3(s.T_b_c),
                          features=pkt.features, packet=pkt)
        for sink in self.sinks:
            sink(out)
        return [out]

    def predict(self) -> gtsam.NavState | None:
        """The newest reported keyframe state propagated with the IMU of every packet
        since (``Estimator.predict`` of that keyframe); None before the first state."""
        if self.state is None:
            return None
        s = self.state
        bias = gtsam.imuBias.ConstantBias(s.bias[:3], s.bias[3:])
        return self._pim.predict(gtsam.NavState(gtsam.Pose3(s.T_w_b), s.v_w), bias)

    def _poll(self, timeout_s: float | None) -> None:
        """Read the worker's finished replies (waiting up to ``timeout_s``; None: forever)."""
        while self._pending:
            ready, _, _ = select.select([self._proc.stdout], [], [], timeout_s)
            if not ready:
                return
            try:
                kind, payload = _recv(self._proc.stdout)
            except EOFError:
                raise WorkerError(f"backend worker died (exit code {self._proc.wait(5.0)})") from None
            if kind == "error":
                exc, tb = payload
                log.debug("backend worker traceback:\n%s", tb)
                raise exc
            self._pending -= 1
            if payload is not None and (self.state is None or payload.t_ns != self.state.t_ns):
                self._new_state(payload)

    def _new_state(self, s: KeyState) -> None:
        """Re-anchor the propagation at keyframe state ``s``: the IMU since its time."""
        self.state = s
        while self._segments and self._segments[0][0] <= s.t_ns:
            self._segments.popleft()
        self._pim = gtsam.PreintegratedCombinedMeasurements(
            self.params, gtsam.imuBias.ConstantBias(s.bias[:3], s.bias[3:]))
        for _, seg in self._segments:
            integrate(self._pim, seg)

    def close(self, wait: bool = True) -> None:
        """Stop the worker; with ``wait``, after its remaining replies (the final state)."""
        self._outbox.put(None)
        try:
            self._writer.join()
            if wait:
                self._poll(None)
        finally:
            _shutdown(self._proc)


class _StateView:
    """What ``vio.backend.bridge.frame_state`` reads of an estimator, from a reported
    ``KeyState`` (its landmarks, its extrinsic) and the pipeline's config and camera."""

    def __init__(self, pipe: "LivePipeline") -> None:
        s = pipe.state
        self.cfg, self.cam, self.check_fired_t = pipe.cfg.backend, pipe.cam, None
        self.frame_contradictions = 0
        self._T_b_c, self._points = gtsam.Pose3(s.T_b_c), (s.landmark_ids, s.landmarks_w)

    def extrinsic(self) -> gtsam.Pose3:
        return self._T_b_c

    def frame_points(self) -> tuple[np.ndarray, np.ndarray]:
        return self._points


def checked(pipe: "LivePipeline", nav: gtsam.NavState, pkt: FramePacket) -> gtsam.NavState:
    """The live frame path's ``vio.backend.bridge.frame_state``: ``nav`` (the IMU
    prediction of ``pkt``), or where vision contradicts it on the reported state's window
    landmarks, the PnP pose; the exposure shift from the reported td (its total less the
    sync layer's offset in the packet's time), the rolling shutter and the last gyro
    reading."""
    s = pipe.state
    if s.landmark_ids is None or pkt.features is None or not len(pkt.imu.gyro):
        return nav
    bias = gtsam.imuBias.ConstantBias(s.bias[:3], s.bias[3:])
    d = s.td_s - (int(pkt.t_ns) - int(pkt.stamp_ns)) * 1e-9
    view = _StateView(pipe)
    out = frame_state(view, pkt.features, nav, shift_by(d, nav, bias, pkt.imu.gyro[-1], pkt.features,
                                                        pipe.cam.line_time_s))
    pipe.frame_contradictions += view.frame_contradictions
    return out


def _light(pkt: FramePacket) -> FramePacket:
    """The packet without decoded images (the worker needs features and IMU only)."""
    return pkt if not pkt.images else dataclasses.replace(pkt, images=())   # IMU gaps, drops kept
