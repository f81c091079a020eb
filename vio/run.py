"""Running the pipeline over a dataset: dataset -> sync -> pipeline -> outputs (the run's
summary: ``vio.run_summary``; ``vio run`` itself: ``vio.run_cmd``)."""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from vio.config import from_dict, read_yaml
from vio.conventions import quat_wxyz_from_rot
from vio.io.euroc import EurocDataset, image_files, stereo_stamps
from vio import overlap
from vio.modes import KLT_WORKER_MODES, MODE_DEFAULTS, merged
from vio.pipeline import FrameOutput, InitInfo, Pipeline, PipelineConfig
from vio.sync import FramePacket, packets
from vio.td_prepass import prepass_td

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """Everything one run produced (online estimate per processed frame). ``init``: how
    and when the estimator initialized (None: never; then ``init_wait`` says why)."""

    outputs: list[FrameOutput] = field(default_factory=list)
    frames_in: int = 0
    keyframes: int = 0
    wall_s: float = 0.0
    data_s: float = 0.0
    recoveries: int = 0
    qr_resolves: int = 0
    """Updates GTSAM's Cholesky refused and QR re-solved (``vio.backend.smoother``)."""
    point_holds: int = 0
    """Cholesky refusals at a world point re-solved with Cholesky, that point held."""
    restarts: int = 0
    reinits: int = 0
    """Re-initializations after a divergence restart (``vio.reinit``)."""
    realigns: int = 0
    """Gravity re-alignments after a long IMU gap (``vio.backend.realign``)."""
    reiterations: int = 0
    """Keyframe updates iterated again after an overshoot (``SolverConfig.reiterate_chi2``)."""
    imu_contradicted: int = 0
    """Keyframe intervals whose IMU readings vision contradicted, bridged (``BridgeConfig.imu_check``)."""
    frames_contradicted: int = 0
    """Frames between keyframes output at their PnP pose, vision contradicting their IMU
    prediction (``vio.backend.bridge.frame_state``)."""
    imu_gaps: int = 0
    imu_gap_s: float = 0.0
    imu_dropped: int = 0
    frames_dropped: int = 0
    """Frames skipped because their image was missing or unreadable (IMU carried over)."""
    camera_gaps: int = 0
    camera_gap_s: float = 0.0
    """Stretches without camera frames and their total length (``vio.camera_gaps``)."""
    live: bool = False
    """The backend ran in its own process (``PipelineConfig.live``): its fault counters
    (gaps, restarts, ...) stayed there, the fields above are not its counts."""
    smoothed: dict = field(default_factory=dict)
    landmarks: dict = field(default_factory=dict)
    init: InitInfo | None = None
    init_wait: str | None = None
    n_init: int = 0
    """Outputs produced by the call that initialized the pipeline (the aligned window's
    replay at a dynamic start): excluded from the per-frame latency figures."""

    def frame_ms(self) -> np.ndarray:
        """Per-frame backend time (ms) after initialization (``FrameOutput.seconds``)."""
        return np.array([o.seconds for o in self.outputs[self.n_init:]]) * 1e3

    def map_points(self) -> np.ndarray:
        """(N, 3) latest world estimate of every landmark seen in the run."""
        return np.array(list(self.landmarks.values())).reshape(-1, 3)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_ns, p (N,3), q_wxyz (N,4)) of the online trajectory."""
        t = np.array([o.t_ns for o in self.outputs], np.int64)
        p = np.array([o.T_w_b.translation() for o in self.outputs]).reshape(-1, 3)
        q = np.array([quat_wxyz_from_rot(o.T_w_b.rotation()) for o in self.outputs]).reshape(-1, 4)
        return t, p, q


def default_config(mode: str = "features") -> PipelineConfig:
    """The defaults of one ``--mode`` (``MODE_DEFAULTS`` on top of the dataclass defaults)."""
    return from_dict(PipelineConfig, MODE_DEFAULTS.get(mode, {}))


def load_config(path: Path | None, td: float | None = None, mode: str = "features") -> PipelineConfig:
    """The mode's defaults, overridden by a YAML file (strict keys) and by ``--td``."""
    raw = merged(MODE_DEFAULTS.get(mode, {}), read_yaml(path) if path else {})
    cfg = from_dict(PipelineConfig, raw, str(path) if path else "defaults")
    if td is not None:
        cfg = dataclasses.replace(cfg, td_s=td)
    return cfg


MODES = ("features", "mono", "stereo", "direct", "hybrid")
STEREO_MODES = ("stereo", "direct", "hybrid")
PHOTOMETRIC_MODES = ("direct", "hybrid")
# the cyclic collector's thresholds while a run loops (restored after): a young-generation
# pass every 20,000 net container allocations instead of 700 (the factor callbacks allocate
# Pose3s and arrays by the hundred per keyframe, few of them in cycles)
RUN_GC_THRESHOLDS = (20000, 20, 20)


def resolve_mode(data: EurocDataset, mode: str) -> str:
    """``auto`` -> features when tracks exist, else stereo/mono by the images present."""
    if mode == "auto":
        mode = "features" if data.features is not None else data.kind
        if mode not in MODES:     # an IMU (and ground truth) recording without camera data
            raise ValueError(f"{data.root}: no camera data to run on (neither cam0/data.csv with "
                             f"images nor cam0/features.csv); `vio tracks {data.root} OUT` generates "
                             f"feature tracks from its IMU and ground truth")
    if mode not in MODES:
        raise ValueError(f"mode {mode!r} is not available (choose from {MODES})")
    if mode == "features" and data.features is None:
        raise ValueError(f"{data.root}: no cam0/features.csv for --mode features")
    if mode != "features" and not data.cam0.has_images():
        raise ValueError(f"{data.root}: no cam0 images for --mode {mode}")
    if mode in STEREO_MODES and (data.cam1 is None or not data.cam1.has_images()):
        raise ValueError(f"{data.root}: no cam1 images for --mode {mode}")
    return mode


def td_feedback(pipe: Pipeline, cfg: PipelineConfig) -> Callable[[], float] | None:
    """The td the sync layer applies to the next frame: the estimator's estimate once it
    differs from the applied one by ``backend.calib.td_feedback_s``, in steps of at most
    ``td_feedback_step_s``, from ``td_feedback_after_s`` after initialization on, and the
    initialization's own estimate at once with ``td_feedback_at_init`` (see
    ``CalibConfig``); None when td is not estimated, the feedback is off, or the estimator
    runs in the live backend process (``cfg.live``: its estimate is not here)."""
    cc = cfg.backend.calib
    if cfg.live or not (cc.estimate_td and cfg.backend.vision.use_td and cc.td_feedback_s > 0):
        return None
    applied, start = [float(cfg.td_s)], []
    pipe.td_fed_back = True

    def source() -> float:
        if not pipe.est.initialized:
            return applied[0]
        t = pipe.est.kf_t[pipe.est.k] * 1e-9
        if not start and cc.td_feedback_at_init:   # the initialization's offset, at once
            applied[0] = float(pipe.est.td())
        start[:] = start or [t]
        if t - start[0] >= cc.td_feedback_after_s:
            d = pipe.est.td() - applied[0]
            if abs(d) >= cc.td_feedback_s:
                applied[0] += float(np.clip(d, -cc.td_feedback_step_s, cc.td_feedback_step_s))
        return applied[0]
    return source


def _packet_stream(data: EurocDataset, cfg: PipelineConfig, mode: str, stamps: np.ndarray,
                   pipe: Pipeline | None) -> tuple[Iterator[FramePacket], Callable | None]:
    """The packets of a run and the stage applied to each in this process (None when
    there is none, or when the KLT front end runs in a worker process, ``vio.overlap``)."""
    ic = data.imu_calib
    screen = dict(lookahead_s=cfg.imu_lookahead_s, screen=cfg.imu_screen, rate_hz=ic.rate_hz,
                  accel_range=ic.accel_range, gyro_range=ic.gyro_range)
    if mode == "features":
        return packets(data.imu, stamps, cfg.td_s, data.features[:len(stamps)], **screen,
                       td_source=td_feedback(pipe, cfg)), None
    stereo = mode in STEREO_MODES
    # the photometric factors with exposure times (direct.points.exposure_td) get the td
    # feedback, which brings the keyframe times to the exposure times; the KLT modes do not
    # (tried: renders moved both ways, benchmarks/README.md, td in the photometric modes)
    timed = mode in PHOTOMETRIC_MODES and cfg.direct.points.exposure_td
    it = packets(data.imu, stamps, cfg.td_s, image_files=image_files(data, stereo, stamps),
                 **screen, td_source=td_feedback(pipe, cfg) if timed else None)
    from vio.tracking import ImageStage
    args = (data.cam0.calib, data.cam1.calib if stereo else None, cfg.frontend)
    if mode in ("stereo", "hybrid"):   # cam1 matched at the keyframes (FrontendConfig.stereo_at), the
        # stereo initialization's frames (vio.modes: stereo and hybrid)
        sc = cfg.backend.init.stereo
        args += (cfg.backend.keyframe, sc.max_window_s + 0.1 if sc.enabled else 0.0)
    worker = cfg.frontend.worker_process and overlap.SUPPORTED
    if mode in PHOTOMETRIC_MODES:
        from vio.direct.mode import attach
        # hybrid tracks KLT on every frame: in the worker process, like stereo mode (direct
        # needs KLT only until it is initialized, so it stays in this process)
        klt_worker = worker and mode in KLT_WORKER_MODES
        if klt_worker:   # the images stay in the worker (a decoded pair, ~0.7 MB, would fill
            # the pipe and stall it: real MH_01 hybrid wall 15.9 -> 20.5 s when sent back;
            # decoding direct mode's images there cost 8.8 -> 10.6 s and +150 MB)
            it = overlap.overlapped(ImageStage, args, it, nice=cfg.frontend.worker_nice)
        return it, attach(pipe, data, cfg, hybrid=mode == "hybrid", klt=not klt_worker)
    if not worker:
        return it, ImageStage(*args)
    return overlap.overlapped(ImageStage, args, it, nice=cfg.frontend.worker_nice, prime=PRIME), None


# KLT packets sent to the worker before the pipeline starts up (its Numba kernels load in
# ~0.5 s, the worker tracks a frame in ~15 ms): real MH_05 mono waited 0.6 s for the
# worker's frames in the loop, most of it in the first 40 frames
PRIME = 32


def _early_stream(data: EurocDataset, cfg: PipelineConfig, mode: str,
                  stamps: np.ndarray) -> tuple[Iterator[FramePacket], Callable | None] | None:
    """The packet stream of the modes whose stream needs no pipeline (mono, stereo: no td
    feedback, no photometric source), built before the pipeline so that the KLT worker,
    where there is one, tracks while the pipeline loads; None otherwise."""
    if cfg.live or mode not in KLT_WORKER_MODES or mode in PHOTOMETRIC_MODES:
        return None
    return _packet_stream(data, cfg, mode, stamps, None)


def run_dataset(data: EurocDataset, cfg: PipelineConfig | None = None, max_frames: int | None = None,
                sinks: list | None = None, progress: bool = False, mode: str = "auto") -> RunResult:
    """Run the pipeline over a loaded dataset (feature tracks, or images through the
    KLT front end in ``mono``/``stereo`` mode, or the photometric ``direct``/``hybrid``
    modes). ``cfg`` None: ``default_config(mode)``."""
    mode = resolve_mode(data, mode)
    cfg = default_config(mode) if cfg is None else cfg
    stamps = data.cam0.t_ns[:max_frames] if max_frames else data.cam0.t_ns
    if mode in PHOTOMETRIC_MODES and cfg.td_prepass_s > 0 and not cfg.live:
        td = prepass_td(data, cfg, default_config("stereo"), stamps, run_dataset)
        cfg = cfg if td is None else dataclasses.replace(cfg, td_s=td)
    cam1 = data.cam1.calib if mode in STEREO_MODES else None
    if mode in STEREO_MODES:
        stamps = stereo_stamps(data, stamps)
    early = _early_stream(data, cfg, mode, stamps)
    if cfg.live:
        if mode in PHOTOMETRIC_MODES:
            raise ValueError(f"live operation (PipelineConfig.live) is not available in mode {mode}")
        from vio.live import LivePipeline
        pipe = LivePipeline(data.imu_calib, data.cam0.calib, cfg, cam1)
    else:
        pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg, cam1)
    pipe.sinks.extend(sinks or [])
    res = RunResult(live=cfg.live)
    it, stage = early if early is not None else _packet_stream(data, cfg, mode, stamps, pipe)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(stamps), unit="frame", leave=False)
    # start-up objects leave the cyclic collector's view (its full collections rescanned them: ~5 %
    # of the backend's time on real MH_01 stereo) until the run ends; collected first, so an earlier
    # run's garbage is not frozen too (4 direct runs in one process: peak RSS 764 -> 1546 MB without)
    gc.collect()
    gc.freeze()
    thresholds, enabled = gc.get_threshold(), gc.isenabled()
    gc.set_threshold(*RUN_GC_THRESHOLDS)
    gc.enable()   # (`vio run` keeps it off during its start-up)
    t0 = time.perf_counter()
    try:
        with _log_above(bar):
            _loop(it, stage, pipe, res, bar, cfg.live)
    except BaseException:
        if cfg.live:
            pipe.close(wait=False)
        raise
    finally:
        gc.set_threshold(*thresholds)
        if not enabled:
            gc.disable()
        gc.unfreeze()
    if bar is not None:
        bar.close()
    res.wall_s = time.perf_counter() - t0
    if cfg.live:
        pipe.close()     # the backend's last state (after the frame path's wall time)
    res.data_s = (stamps[-1] - stamps[0]) * 1e-9 if len(stamps) > 1 else 0.0
    _counters(res, pipe)
    return res


class _AboveBar:
    """A console stream whose writes go above the progress bars (``tqdm.write``)."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        from tqdm import tqdm
        tqdm.write(text.rstrip("\n"), file=self.stream)
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


@contextlib.contextmanager
def _log_above(bar):
    """With a progress bar, the root logger's console handlers write above it instead of
    into its line (their levels, formats and filters unchanged); without one, nothing."""
    handlers = [] if bar is None else [
        h for h in logging.getLogger().handlers
        if type(h) is logging.StreamHandler and h.stream in (sys.stderr, sys.stdout)]
    old = [h.setStream(_AboveBar(h.stream)) for h in handlers]
    try:
        yield
    finally:
        for h, stream in zip(handlers, old):
            h.setStream(stream)


def _counters(res: RunResult, pipe) -> None:
    """The run's counters from the pipeline into ``res`` (keyframes, solver recoveries and
    the frames placed by PnP only when ``res.live``: the live backend's other counters stay
    in its process)."""
    res.keyframes = pipe.n_keyframes
    res.recoveries = pipe.recoveries if res.live else pipe.est.recoveries
    if res.live:
        res.frames_contradicted = pipe.frame_contradictions
        return
    res.init = pipe.init_info
    res.init_wait = pipe.init_wait
    res.restarts = pipe.est.divergences
    res.reinits = pipe.reinit.count
    res.realigns = pipe.est.realigned
    res.reiterations = pipe.est.reiterations
    res.imu_contradicted = pipe.est.imu_contradictions
    res.frames_contradicted = pipe.est.frame_contradictions
    res.qr_resolves = pipe.est.qr_resolves
    res.point_holds = pipe.est.point_holds
    res.imu_gaps = len(pipe.imu_gaps)
    res.imu_gap_s = sum(b - a for a, b in pipe.imu_gaps) * 1e-9
    res.imu_dropped = pipe.imu_dropped
    res.frames_dropped = pipe.frames_dropped
    res.camera_gaps, res.camera_gap_s = len(pipe.camera_gaps.gaps), pipe.camera_gaps.seconds


def _loop(it: Iterator[FramePacket], stage: Callable | None, pipe, res: RunResult, bar,
          live: bool) -> None:
    """The run loop: stage, pipeline, results."""
    for pkt in it:
        res.frames_in += 1
        if stage is not None:
            pkt = stage(pkt)
        outs = pipe.process(pkt)
        if outs and not res.outputs:
            res.n_init = len(outs)
        res.outputs.extend(outs)
        for out in outs:
            if out.landmark_ids is not None:
                res.landmarks.update(zip(out.landmark_ids.tolist(), out.landmarks_w))
        if outs and not live:
            for k, (t, T) in pipe.est.window_poses().items():
                res.smoothed[k] = (t, T)
        if bar is not None:
            bar.update(1)
