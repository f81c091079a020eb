"""The keyframe policy (``KeyframeConfig``), shared by the pipeline and the image stage.

A frame becomes a keyframe when the mean feature parallax since the last keyframe reaches
``min_parallax_px``, when ``max_interval_s`` has elapsed, or when fewer than
``min_tracked`` features remain tracked, never sooner than ``min_interval_s`` after the
last one. The pipeline applies it to every packet; in stereo and hybrid mode the image stage
applies the same policy to its own features (``FrontendConfig.stereo_at = "keyframe"``) and
matches cam1 only at the frames it chooses, which the pipeline then takes as its keyframes
(``FramePacket.keyframe``), so every keyframe has its stereo matches.
"""

from __future__ import annotations

import numpy as np

from vio.backend.config import KeyframeConfig


def flow_px(ids_a: np.ndarray | None, uv_a: np.ndarray | None, ids_b: np.ndarray | None,
            uv_b: np.ndarray | None, fx: float, median: bool = False) -> tuple[float, int]:
    """Mean (or median) displacement in pixels (normalized ``uv`` (M, 2) times ``fx``)
    of the features common to two frames (track ids ``ids_*`` (M,)), and their count."""
    if ids_a is None or ids_b is None:
        return 0.0, 0
    common, ia, ib = np.intersect1d(ids_a, ids_b, return_indices=True)
    if common.size == 0:
        return 0.0, 0
    d = np.linalg.norm(uv_a[ia] - uv_b[ib], axis=1) * fx
    return float(np.median(d) if median else d.mean()), int(common.size)


class KeyframePolicy:
    """``KeyframeConfig`` applied to a stream of frames. ``fx``: cam0's focal length in
    pixels (parallax is measured on the normalized plane)."""

    def __init__(self, cfg: KeyframeConfig, fx: float) -> None:
        self.cfg, self.fx = cfg, float(fx)
        self._ids: np.ndarray | None = None
        self._uv: np.ndarray | None = None
        self._t: int | None = None            # no keyframe yet

    def reset(self, t_ns: int, ids: np.ndarray | None, uv: np.ndarray | None) -> None:
        """The frame at ``t_ns`` (ns) with features ``ids`` (M,) / ``uv`` (M, 2) is a keyframe."""
        self._t, self._ids, self._uv = int(t_ns), ids, uv

    def due(self, t_ns: int, ids: np.ndarray | None, uv: np.ndarray | None) -> bool:
        """Whether the frame at ``t_ns`` with these features is a keyframe (state unchanged;
        the first frame is one)."""
        if self._t is None:
            return True
        kc = self.cfg
        dt = (t_ns - self._t) * 1e-9
        if dt < kc.min_interval_s:
            return False
        if dt >= kc.max_interval_s:
            return True
        flow, n = flow_px(self._ids, self._uv, ids, uv, self.fx)
        return flow >= kc.min_parallax_px or n < kc.min_tracked
