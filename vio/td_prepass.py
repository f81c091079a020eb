"""The photometric modes' camera-to-IMU offset from a stereo pre-pass
(``PipelineConfig.td_prepass_s``).

The photometric term takes each image as taken at its keyframe's time, so in ``direct``
and ``hybrid`` mode td stays where the sync layer puts it: hybrid's KLT landmarks carry
td, but thousands of photometric residuals at the keyframe times pin it there (renders
with td 8 / 10 ms: hybrid's estimate -0.18 / 0.16 ms). Estimating td inside the
photometric factors (``direct.points.exposure_td``) is fragile: on seven unseen renders
hybrid gave 2.1-8.7 mm, worse than with td held at 0 on four (benchmarks/README.md, stop
72). The KLT stereo front end and its td factors estimate td within ~0.6 ms in the first
seconds, so these modes first run ``stereo`` mode over the first ``td_prepass_s`` of the
data and then start with the sync layer at its estimate, as ``--td`` would (real MH_01
with its camera stamps moved by -20 / +12 / +25 ms: hybrid 6.4 / 8.5 / 14.3 -> 4.6 / 4.4 /
4.9 mm; unmoved 4.6 mm either way).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import numpy as np

from vio.io.euroc import EurocDataset
from vio.pipeline import PipelineConfig

log = logging.getLogger(__name__)


def prepass_config(cfg: PipelineConfig, stereo: PipelineConfig) -> PipelineConfig:
    """The pre-pass's configuration: ``stereo`` (stereo mode's defaults) with the run's
    sync layer (td, IMU lookahead and screening), IMU noise and front-end worker settings,
    td estimated, and no pre-pass of its own."""
    backend = dataclasses.replace(stereo.backend, imu=cfg.backend.imu,
                                  calib=dataclasses.replace(stereo.backend.calib, estimate_td=True))
    frontend = dataclasses.replace(stereo.frontend, worker_process=cfg.frontend.worker_process,
                                   worker_nice=cfg.frontend.worker_nice)
    return dataclasses.replace(stereo, td_s=cfg.td_s, imu_lookahead_s=cfg.imu_lookahead_s,
                               imu_screen=cfg.imu_screen, tune_heap=cfg.tune_heap, td_prepass_s=0.0,
                               backend=backend, frontend=frontend)


def prepass_td(data: EurocDataset, cfg: PipelineConfig, stereo: PipelineConfig, t: np.ndarray,
               run: Callable) -> float | None:
    """td (s, the sync layer's offset plus the estimate) from ``run`` (``vio.run.run_dataset``)
    in stereo mode over the cam0 frames of the first ``cfg.td_prepass_s`` seconds of ``t``
    (the run's cam0 stamps, ns); None, with a warning, when that run has no pose for at
    least half of that time (the pre-pass did not initialize early enough to estimate td)."""
    if len(t) < 2:
        return None
    n = int(np.searchsorted(t, t[0] + int(cfg.td_prepass_s * 1e9), side="right"))
    res = run(data, prepass_config(cfg, stereo), max_frames=n, mode="stereo")
    span = (res.outputs[-1].t_ns - res.outputs[0].t_ns) * 1e-9 if res.outputs else 0.0
    if span < 0.5 * cfg.td_prepass_s:
        have = (t[n - 1] - t[0]) * 1e-9
        log.warning("td pre-pass: stereo mode posed %.1f s of the first %.1f s of frames (td needs %.1f s "
                    "posed); td stays at the sync layer's %.2f ms", span, have, 0.5 * cfg.td_prepass_s,
                    cfg.td_s * 1e3)
        return None
    td = float(res.outputs[-1].td_s)
    log.info("td pre-pass: stereo mode over the first %.1f s estimates td %.2f ms; the photometric "
             "run starts with the sync layer there", cfg.td_prepass_s, td * 1e3)
    return td
