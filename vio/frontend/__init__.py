"""Image front end: VINS-style KLT tracking on cam0, optional LK stereo matching to cam1.

``Frontend(cam0, cam1, cfg).process(t_ns, img0, img1, R_prev_cur) -> TrackedFrame``.
Uses no gtsam API besides ``CameraCalib.T_b_c.matrix()`` (gtsam is loaded only
transitively, by ``vio.io.types``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.frontend.camera import Camera, camera_rotation, epipolar_distance, essential_from_pose
from vio.frontend.config import FrontendConfig
from vio.frontend.stereo import StereoMatch, StereoMatcher, neighbour_depths, triangulate_depth
from vio.frontend.tracker import KltTracker, MonoTracks, Preprocess
from vio.io.types import CameraCalib, FeatureFrame

__all__ = ["Camera", "FrontendConfig", "Frontend", "KltTracker", "MonoTracks", "StereoMatch",
           "StereoMatcher", "TrackedFrame", "camera_rotation", "epipolar_distance",
           "essential_from_pose", "neighbour_depths", "triangulate_depth"]


@dataclass(frozen=True)
class TrackedFrame:
    """Features of one (stereo) frame; all arrays row-aligned and read-only.

    ``ids`` (M,) int64 track ids; ``uv`` (M, 2) undistorted normalized cam0;
    ``px`` (M, 2) distorted cam0 pixels; ``velocity`` (M, 2) cam0 normalized-plane
    velocity in 1/s (0 on a track's first frame); ``row`` (M,) cam0 pixel row of the
    observation (rolling shutter); ``track_len`` (M,) frames observed including this
    one; ``right_uv``/``right_px`` (M, 2) cam1 normalized/pixel, NaN where unmatched;
    ``right_velocity`` (M, 2) cam1 normalized velocity in 1/s (0 when the id had no
    right match in the previous frame; see ``Frontend.match`` after a frame without
    matches); ``depth`` (M,) z in cam0 in metres, NaN where
    not triangulated.
    """

    t_ns: int
    ids: np.ndarray
    uv: np.ndarray
    px: np.ndarray
    velocity: np.ndarray
    row: np.ndarray
    track_len: np.ndarray
    right_uv: np.ndarray
    right_px: np.ndarray
    right_velocity: np.ndarray
    depth: np.ndarray

    def __post_init__(self) -> None:
        for name in ("ids", "uv", "px", "velocity", "row", "track_len", "right_uv",
                     "right_px", "right_velocity", "depth"):
            getattr(self, name).setflags(write=False)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def stereo_mask(self) -> np.ndarray:
        """(M,) bool: features with a cam1 observation."""
        return np.isfinite(self.right_uv[:, 0])

    def to_feature_frame(self, camera: int = 0) -> FeatureFrame:
        """cam0 (``camera=0``) or the stereo-matched cam1 rows (``camera=1``) as a FeatureFrame."""
        if camera == 0:
            return FeatureFrame(self.t_ns, self.ids.copy(), self.uv.copy(),
                                self.velocity.copy(), self.row.copy())
        if camera == 1:
            m = self.stereo_mask
            return FeatureFrame(self.t_ns, self.ids[m].copy(), self.right_uv[m].copy(),
                                self.right_velocity[m].copy(), self.right_px[m, 1].copy())
        raise ValueError(f"camera must be 0 or 1, got {camera!r}")


class Frontend:
    """Tracks cam0 and, with a second camera and ``cfg.stereo``, matches into cam1."""

    def __init__(self, cam0: CameraCalib, cam1: CameraCalib | None = None,
                 cfg: FrontendConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else FrontendConfig()
        self.cam0 = Camera(cam0)
        self.cam1 = Camera(cam1) if cam1 is not None else None
        self.tracker = KltTracker(self.cam0, self.cfg)
        self.stereo = (StereoMatcher(self.cam0, self.cam1, self.cfg)
                       if self.cam1 is not None and self.cfg.stereo else None)
        self._preprocess1 = Preprocess(self.cam1, self.cfg) if self.stereo is not None else None
        self._prev: TrackedFrame | None = None      # the previous frame
        self._matched: TrackedFrame | None = None   # the last frame matched in cam1

    def process(self, t_ns: int, img0: np.ndarray, img1: np.ndarray | None = None,
                R_prev_cur: np.ndarray | None = None) -> TrackedFrame:
        """Process one frame: grayscale uint8 (H, W) images taken at ``t_ns`` (int ns).

        ``R_prev_cur`` (3, 3), optional: cam0 rotation ``R_c0(k-1)_c0(k)`` for LK
        prediction (see ``camera_rotation`` to build it from a gyro rotation).
        ``img1`` is ignored unless a cam1 was given and ``cfg.stereo`` is set.
        """
        return self.match(self.track(t_ns, img0, R_prev_cur), img1)

    def track(self, t_ns: int, img0: np.ndarray, R_prev_cur: np.ndarray | None = None) -> MonoTracks:
        """The cam0 half of ``process``: KLT tracking and detection."""
        return self.tracker.track(t_ns, img0, R_prev_cur)

    def match(self, mono: MonoTracks, img1: np.ndarray | None = None) -> TrackedFrame:
        """The cam1 half of ``process`` for ``track``'s result. It shares no state with
        ``track`` (its own cam1 preprocessing, the previous frame's matches), so frame k's
        ``match`` may run in another thread while frame k+1 is tracked; calls must come in
        frame order. Without ``img1`` the frame has no cam1 matches (a frame skipped by
        ``FrontendConfig.stereo_at``): the next match starts its tracks at their depths
        in the last matched frame."""
        m = len(mono.ids)
        right_uv, right_px, depth = np.full((m, 2), np.nan), np.full((m, 2), np.nan), np.full(m, np.nan)
        found, idx = self._lookup(mono.ids, self._prev)
        stereo = self.stereo is not None and img1 is not None
        if stereo:
            img1 = self._preprocess1(img1, f"cam {self.cam1.calib.name} image at t={mono.t_ns} ns")
            last = self._matched
            mfound, midx = (found, idx) if last is self._prev else self._lookup(mono.ids, last)
            match = self.stereo.match(mono.image, img1, mono.px, mono.uv,
                                      self._depth_guess(last, mfound, midx, mono.px))
            right_uv, right_px, depth = match.right_uv, match.right_px, match.depth
        frame = TrackedFrame(
            t_ns=mono.t_ns, ids=mono.ids, uv=mono.uv, px=mono.px, velocity=mono.velocity,
            row=mono.px[:, 1].copy(), track_len=mono.track_len, right_uv=right_uv, right_px=right_px,
            right_velocity=self._right_velocity(mono, found, idx, right_uv), depth=depth)
        self._prev = frame
        if stereo:
            self._matched = frame
        return frame

    @staticmethod
    def _lookup(ids: np.ndarray, prev: TrackedFrame | None) -> tuple[np.ndarray, np.ndarray]:
        """Rows of ``ids`` in frame ``prev``: (found (M,) bool, index (M,))."""
        if prev is None or len(prev.ids) == 0:
            return np.zeros(len(ids), dtype=bool), np.zeros(len(ids), dtype=np.int64)
        order = np.argsort(prev.ids)
        pos = np.clip(np.searchsorted(prev.ids, ids, sorter=order), 0, len(order) - 1)
        idx = order[pos]
        return prev.ids[idx] == ids, idx

    def _depth_guess(self, last: TrackedFrame | None, found: np.ndarray, idx: np.ndarray,
                     px: np.ndarray) -> np.ndarray:
        """(M,) m: each track's depth in frame ``last`` (``_lookup``'s rows there), else its
        neighbours' there."""
        if not found.any():
            return np.full(len(found), np.nan)
        return neighbour_depths(px, np.where(found, last.depth[idx], np.nan),
                                self.cfg.stereo_guess_neighbours)

    def _right_velocity(self, mono: MonoTracks, found: np.ndarray, idx: np.ndarray,
                        right_uv: np.ndarray) -> np.ndarray:
        """(M, 2) cam1 velocity (1/s) from the previous frame (``_lookup``'s rows); 0 where
        the id or either match is missing. After a frame without cam1 matches
        (``FrontendConfig.stereo_at``) the cam0 velocity stands in for the matched rows:
        the two cameras look the same way, and their image velocities differ by the rate
        of the disparity alone (a point at 1 m approached at 0.3 m/s: 0.03/s of normalized
        velocity against the td gate's 5/s, ``VisionConfig.td_velocity_gate``)."""
        vel = np.zeros_like(right_uv)
        if not found.any():
            return vel
        if self._prev is not self._matched:
            ok = np.all(np.isfinite(right_uv), axis=1)
            vel[ok] = mono.velocity[ok]
            return vel
        dt = (mono.t_ns - self._prev.t_ns) * 1e-9
        diff = (right_uv - self._prev.right_uv[idx]) / dt
        ok = found & np.all(np.isfinite(diff), axis=1)
        vel[ok] = diff[ok]
        return vel
