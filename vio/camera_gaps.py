"""Camera stream gaps: stretches without frames (a driver that stalled, a recording that
lost frames, a camera unplugged for a moment).

Nothing is lost for the estimator: the IMU is continuous, so the next frame's packet
carries every sample since the last frame and the state is preintegrated across the gap
(an IMU gap is the other case, ``vio.faults``); the front end predicts the next frame's
tracks from that IMU's rotation. What a gap costs is vision for its length, so the run
says so: a warning naming the gap's time and length, and a count in the run summary.

A *gap* is an interval between consecutive frames longer than ``max_gap_periods``
nominal periods, the nominal period being the median of the last ``history`` intervals
that were not gaps (the stream's own rate: a decimated or 10-Hz recording whose
``sensor.yaml`` says 20 Hz is not a stream of gaps). A single missing frame (two periods)
is not one; a frame whose image could not be read arrived and counts as a frame
(``vio.pipeline`` warns about it itself).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np

from vio.config import check_ranges

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraGapConfig:
    """See the module docstring. ``max_gap_periods`` 0 turns the check off; at least
    ``min_history`` intervals are needed before the first judgement."""

    max_gap_periods: float = 2.5
    history: int = 25
    min_history: int = 5

    def __post_init__(self) -> None:
        check_ranges(self, positive=("history", "min_history"))


class CameraGaps:
    """Feed every frame's stamp in time order to :meth:`frame`; ``gaps`` lists the gaps
    found as ``(last frame before, first frame after)`` stamps (ns)."""

    def __init__(self, cfg: CameraGapConfig = CameraGapConfig()) -> None:
        self.cfg = cfg
        self.gaps: list[tuple[int, int]] = []
        self._dt: deque[int] = deque(maxlen=cfg.history)
        self._last: int | None = None
        self._first: int | None = None

    def frame(self, t_ns: int) -> tuple[int, int] | None:
        """Record a frame at ``t_ns``; the gap it ends (and a warning), or None."""
        last = self._last
        if last is None:
            self._first = self._last = t_ns
            return None
        if t_ns <= last:                       # a repeated or earlier stamp: not an interval
            return None
        self._last, dt = t_ns, t_ns - last
        if self.cfg.max_gap_periods > 0 and len(self._dt) >= self.cfg.min_history:
            period = float(np.median(self._dt))
            if dt > self.cfg.max_gap_periods * period:
                self.gaps.append((last, t_ns))
                log.warning("t=%d ns (%.2f s after the first frame): no camera frame for %.2f s (about %d "
                            "missing at %.1f Hz); the IMU carried the state across the gap", t_ns,
                            (t_ns - self._first) * 1e-9, dt * 1e-9, round(dt / period) - 1, 1e9 / period)
                return last, t_ns
        self._dt.append(dt)
        return None

    @property
    def seconds(self) -> float:
        """Total length of the gaps (s)."""
        return sum(b - a for a, b in self.gaps) * 1e-9
