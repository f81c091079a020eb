"""Our pipeline's decisions, recorded for the GTSAM-native baselines to replay:
the initial state, the keyframes (IMU-clock ns) with their still flags, and the sync
layer's constant td (``Schedule``, JSON round trip), recorded by ``record_schedule``.
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import gtsam
import numpy as np

from vio.backend.estimator import Estimator
from vio.backend.init import InitialState
from vio.io.euroc import EurocDataset
from vio.pipeline import FrameOutput, PipelineConfig
from vio.run import RunResult, run_dataset


@dataclass(frozen=True)
class Schedule:
    """Our pipeline's decisions: initial state, keyframe stamps (IMU clock, ns) with
    their still flags, and the sync layer's constant td (s)."""

    init: InitialState
    keyframes: dict[int, bool]
    td_s: float

    def to_json(self) -> dict:
        s = self.init
        return {"td_s": self.td_s, "keyframes": [[t, bool(f)] for t, f in sorted(self.keyframes.items())],
                "init": {"t_ns": s.t_ns, "T_w_b": s.T_w_b.matrix().tolist(), "v_w": list(map(float, s.v_w)),
                         "bias": s.bias.vector().tolist(), "method": s.method}}

    @cached_property
    def _times(self) -> np.ndarray:
        return np.array(sorted(self.keyframes), np.int64)

    def keyframe_at(self, t_ns: int, tol_ns: int = 10_000_000) -> bool | None:
        """The still flag of the keyframe scheduled at frame time ``t_ns``, or None. Our
        sync layer may have moved a frame's stamp by its td feedback (a few ms,
        ``CalibConfig.td_feedback_s``) where the replay applies the constant ``td_s``, so
        the nearest scheduled keyframe within ``tol_ns`` (well under a frame period) matches."""
        times = self._times
        i = int(np.searchsorted(times, t_ns))
        near = [int(times[j]) for j in (i - 1, i) if 0 <= j < len(times)]
        best = min(near, key=lambda t: abs(t - t_ns), default=None)
        return None if best is None or abs(best - t_ns) > tol_ns else self.keyframes[best]

    @staticmethod
    def from_json(d: dict) -> "Schedule":
        i = d["init"]
        b = np.asarray(i["bias"], float)
        init = InitialState(int(i["t_ns"]), gtsam.Pose3(np.asarray(i["T_w_b"], float)),
                            np.asarray(i["v_w"], float), gtsam.imuBias.ConstantBias(b[:3], b[3:]),
                            i["method"])
        return Schedule(init, {int(t): bool(f) for t, f in d["keyframes"]}, float(d["td_s"]))


@contextmanager
def _capture_init(states: list[InitialState]):
    """Record every ``Estimator.initialize`` state (our pipeline's initialization)."""
    orig = Estimator.initialize

    def spy(self, state, *a, **k):
        states.append(state)
        return orig(self, state, *a, **k)
    Estimator.initialize = spy
    try:
        yield
    finally:
        Estimator.initialize = orig


def record_schedule(data: EurocDataset, cfg: PipelineConfig,
                    max_frames: int | None = None) -> tuple[RunResult, Schedule]:
    """Run our pipeline (``vio.run.run_dataset``) on feature tracks and record its
    decisions, each at its frame's camera stamp plus the sync layer's constant ``cfg.td_s``
    (the time the replay gives that frame): our own frame times also carry the td fed back
    since the initialization (``CalibConfig``; up to the whole offset on data with one),
    which would match no replayed frame, and would not move with ``with_known_td``."""
    kfs: dict[int, bool] = {}
    states: list[InitialState] = []
    frame_of: dict[int, int] = {}         # our frame time -> frame index
    stamps = data.cam0.t_ns
    td_ns = int(round(cfg.td_s * 1e9))

    def sink(o: FrameOutput) -> None:
        frame_of[int(o.t_ns)] = o.index
        if o.keyframe:
            kfs[int(stamps[o.index]) + td_ns] = bool(o.still)
    with _capture_init(states):
        res = run_dataset(data, cfg, max_frames, sinks=[sink])
    if not states:
        raise RuntimeError(f"{data.root}: our pipeline never initialized")
    init = states[0]
    if init.t_ns in frame_of:
        init = dataclasses.replace(init, t_ns=int(stamps[frame_of[init.t_ns]]) + td_ns)
    kfs.setdefault(init.t_ns, True)
    return res, Schedule(init, kfs, cfg.td_s)
