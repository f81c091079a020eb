"""What the estimator reports (a mixin of ``vio.backend.estimator.Estimator``): the
extrinsic, td, the window's landmarks and keyframe poses, all read from the smoother's
``Values`` (``self.values``), the only copy of the state."""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np

from vio.backend import graph

X = graph.X


class EstimatorOutputs:
    """Read-only views of the estimate; the host class provides ``values`` (``gtsam.Values``),
    ``lm`` (``LandmarkManager``), ``kf_t`` (keyframe -> t_ns), ``td_applied_s`` and
    ``_frame_points``."""

    def extrinsic(self) -> gtsam.Pose3:
        return self.values.atPose3(graph.EXTRINSIC)

    def td_obs(self, frame: Any) -> float:
        """The part of the td variable the time of ``frame`` (a ``FramePacket``: ``t_ns``
        = stamp + the sync layer's offset for it) already holds: that offset minus
        ``td_applied_s`` (s); 0 for anything else. Non-zero once the sync layer applies
        the fed-back estimate (``CalibConfig.td_feedback_s``)."""
        t, stamp = getattr(frame, "t_ns", None), getattr(frame, "stamp_ns", None)
        if t is None or stamp is None:
            return 0.0
        return (int(t) - int(stamp)) * 1e-9 - self.td_applied_s

    def td(self) -> float:
        """Total camera-to-IMU offset (s): the sync layer's constant plus the estimate."""
        return self.td_applied_s + float(self.values.atVector(graph.TD)[0])

    def landmarks_w(self) -> tuple[np.ndarray, np.ndarray]:
        """Ids (N,) and world points (N, 3) of the landmarks in the window."""
        return self.lm.points_w(self.values)

    def check_points(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`landmarks_w` less those that entered without parallax (guessed depths,
        ``LandmarkManager.weak_ids``): what the IMU check's PnP stands on."""
        ids, pts = self.landmarks_w()
        keep = ~np.isin(ids, self.lm.weak_ids())
        return ids[keep], pts[keep]

    def frame_points(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`check_points` once per estimate (kept until ``values`` is replaced; the
        factors' refined depths may move by a fraction of a mm meanwhile): what the frames
        between keyframes check their prediction against (1.1 -> 0.1 ms a frame on real
        MH_01 stereo)."""
        if self._frame_points[0] is not self.values:
            self._frame_points = (self.values, self.check_points())
        return self._frame_points[1]

    def window_poses(self) -> dict[int, tuple[int, gtsam.Pose3]]:
        """Smoothed poses of the keyframes in the window: k -> (t_ns, T_w_b)."""
        return {k: (t, self.values.atPose3(X(k))) for k, t in self.kf_t.items()
                if self.values.exists(X(k))}
