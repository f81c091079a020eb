"""Rerun live view of a VIO run (the only module in ``vio/`` that imports rerun).

``RerunSink`` is a pipeline sink (``Pipeline.sinks``): it observes each
``FrameOutput`` and never feeds anything back to the estimator. Ground truth,
when given, is drawn for comparison only.

Timelines: ``frame`` (sequence, ``FrameOutput.index``) and ``time`` (timestamp,
``FrameOutput.t_ns`` as nanoseconds since the Unix epoch).

Entity paths (stable; tests read them back):

- ``world``: ``ViewCoordinates`` right-handed z-up (static).
- ``world/trajectory/estimate``: ``LineStrips3D`` of the online positions so far,
  re-logged every ``RerunConfig.strip_every`` frames and at ``close()``.
- ``world/trajectory/groundtruth``: ``LineStrips3D`` of the ground-truth positions
  over the estimate's time span, mapped into the estimate's world by a 4-DoF
  (yaw + translation) transform (``GroundTruthAligner``), logged with the estimate.
- ``world/landmarks``: ``Points3D`` of the window landmarks (``landmarks_w``) on keyframes.
- ``world/body``: ``Transform3D`` of ``T_w_b`` every frame.
- ``world/body/cam0``: ``Transform3D`` of ``T_b_c`` (when it changes) and a static
  ``Pinhole`` (intrinsics, resolution) when the sink has a ``CameraCalib``.
- ``world/body/cam0/image``: the left image (``packet.images[0]`` or the file
  ``packet.image_files[0]``), every ``image_every`` frames; absent for feature-only data.
- ``world/body/cam0/image/features``: ``Points2D`` of the features in distorted pixel
  coordinates, coloured by track length (red: new, green: ``track_len_full`` frames or more).
- ``world/body/cam0/image/direct_points``: on keyframes of the direct / hybrid modes, the
  photometric points seen in the keyframe (``add_direct_source``), coloured by their
  residual RMSE at the current estimate (green 0 to red ``direct_rmse_full`` intensity units).
- ``metrics/time_ms``, ``metrics/n_features``, ``metrics/n_landmarks``,
  ``metrics/gyro_bias/{x,y,z}`` (rad/s), ``metrics/accel_bias/{x,y,z}`` (m/s^2),
  ``metrics/td_ms``, ``metrics/keyframe`` (1 at keyframes, drawn as points) and, with
  ground truth, ``metrics/gt_error_m`` (distance to the aligned ground truth under the
  alignment current at that frame): ``Scalars``, buffered and sent as columns every
  ``metrics_every`` frames.

``log_plan`` draws an A* plan on an occupancy grid (``vio plan --rrd``).
"""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from vio.errors import DataError
from vio.io.types import CameraCalib, GroundTruth
from vio.viz_align import (BLUE, GREEN, ORANGE, GroundTruthAligner, Rows, TrackLengths,  # noqa: F401
                           fit_yaw_translation, track_colors)

if TYPE_CHECKING:
    from vio.nav.astar import PlanResult
    from vio.nav.grid import MapData, OccupancyGrid
    from vio.pipeline import FrameOutput
    from vio.sync import FramePacket

log = logging.getLogger(__name__)

ENTITIES = ("world/trajectory/estimate", "world/trajectory/groundtruth", "world/landmarks",
            "world/body", "world/body/cam0", "world/body/cam0/image",
            "world/body/cam0/image/features", "metrics/time_ms", "metrics/n_features",
            "metrics/n_landmarks", "metrics/gyro_bias/x", "metrics/gyro_bias/y",
            "metrics/gyro_bias/z", "metrics/accel_bias/x", "metrics/accel_bias/y",
            "metrics/accel_bias/z", "metrics/td_ms", "metrics/keyframe", "metrics/gt_error_m")

_SERIES = ("time_ms", "n_features", "n_landmarks", "gyro_bias/x", "gyro_bias/y", "gyro_bias/z",
           "accel_bias/x", "accel_bias/y", "accel_bias/z", "td_ms")


@dataclass(frozen=True)
class RerunConfig:
    """Logging rates and styling. ``strip_every``: frames between trajectory re-logs
    (and ground-truth refits); ``metrics_every``: frames buffered per metrics send;
    ``image_every``: frames between logged images; ``jpeg_quality``: JPEG-compress
    images (1-100) or ``None`` for raw; ``track_len_full``: track length (frames) drawn
    fully green; ``frustum_m``: drawn image-plane distance; ``gt_max_gap_s``: largest
    ground-truth sample gap interpolated over; ``gt_min_spread_m``: horizontal RMS spread
    of matched positions before the yaw is fitted from positions; ``port``: viewer port."""

    strip_every: int = 10
    metrics_every: int = 20
    image_every: int = 1
    jpeg_quality: int | None = None
    track_len_full: int = 20
    frustum_m: float = 0.25
    landmark_radius_m: float = 0.02
    feature_radius_px: float = 2.5
    gt_max_gap_s: float = 0.1
    gt_min_spread_m: float = 0.3
    direct_rmse_full: float = 20.0
    port: int = 9876

    def __post_init__(self) -> None:
        for name in ("strip_every", "metrics_every", "image_every", "track_len_full"):
            if getattr(self, name) < 1:
                raise ValueError(f"RerunConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"RerunConfig.jpeg_quality must be in 1..100, got {self.jpeg_quality}")


def default_blueprint() -> rrb.Blueprint:
    """3D world view beside the camera image and the metrics plots."""
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="world"),
        rrb.Vertical(rrb.Spatial2DView(origin="world/body/cam0/image", name="cam0"),
                     rrb.TimeSeriesView(origin="metrics", name="metrics")),
        column_shares=[3, 2]))


class RerunSink:
    """Pipeline sink logging each ``FrameOutput`` to Rerun (entities: module docstring).

    ``spawn``: spawn (or connect to) a viewer on ``cfg.port``; ``rrd``: record to
    this file; both may be set. ``recording``: log into this stream instead of a
    new one (spawn/rrd still attach to it); with none of the three, the sink
    records into memory (``self.memory``). ``cam``: camera calibration for the
    frustum and the feature pixel coordinates. Call ``close()`` (or use ``with``)
    to send the buffered tail; it also runs when the sink is garbage-collected.
    """

    def __init__(self, spawn: bool = False, rrd: Path | None = None,
                 groundtruth: GroundTruth | None = None, cam: CameraCalib | None = None,
                 app_id: str = "vio", recording: rr.RecordingStream | None = None,
                 cfg: RerunConfig = RerunConfig()) -> None:
        self._closed = True          # until fully constructed (see __del__)
        self.cfg = cfg
        self.cam = cam
        self._camera = None
        if cam is not None:
            from vio.frontend.camera import Camera
            self._camera = Camera(cam)
        self._owned = recording is None
        self.rec = recording if recording is not None else rr.RecordingStream(
            app_id, recording_id=uuid.uuid4())
        self.memory: rr.MemoryRecording | None = None
        self._connect(spawn, None if rrd is None else Path(rrd))
        self.aligner = None
        if groundtruth is not None and len(groundtruth) >= 2:
            self.aligner = GroundTruthAligner(groundtruth, cfg.gt_max_gap_s, cfg.gt_min_spread_m)
        self._tracks = TrackLengths()
        self._lut = track_colors(cfg.track_len_full)
        self._traj = Rows(3)
        self._rows: list[tuple] = []
        self._n = 0
        self._strip_n = 0
        self._T_b_c: np.ndarray | None = None
        self._image_error = False
        self._direct = None
        self._log_static()
        self._closed = False

    # ----------------------------------------------------------------- setup
    def _connect(self, spawn: bool, rrd: Path | None) -> None:
        if rrd is not None and not rrd.parent.is_dir():
            raise ValueError(f"{rrd}: directory {rrd.parent} does not exist")
        bp, port = default_blueprint(), self.cfg.port
        if spawn and rrd is not None:
            rr.spawn(port=port, connect=False)
            self.rec.set_sinks(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"),
                               rr.FileSink(str(rrd)), default_blueprint=bp)
        elif spawn:
            self.rec.spawn(port=port, default_blueprint=bp)
        elif rrd is not None:
            self.rec.save(str(rrd), default_blueprint=bp)
        elif self._owned:
            self.memory = self.rec.memory_recording()

    def _log_static(self) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("metrics/keyframe", rr.SeriesPoints(markers="diamond", marker_sizes=4.0,
                                                     names="keyframe"), static=True)
        if self.cam is not None:
            rec.log("world/body/cam0", rr.Pinhole(image_from_camera=self.cam.K,
                                                  resolution=[self.cam.width, self.cam.height],
                                                  image_plane_distance=self.cfg.frustum_m),
                    static=True)

    # ------------------------------------------------------------- per frame
    def __call__(self, out: FrameOutput) -> None:
        """Log one frame (see the module docstring for what goes where)."""
        if self._closed:
            raise RuntimeError("RerunSink is closed")
        rec = self.rec
        rec.set_time("frame", sequence=int(out.index))
        rec.set_time("time", timestamp=np.datetime64(int(out.t_ns), "ns"))
        p = np.asarray(out.T_w_b.translation(), float)
        rec.log("world/body", rr.Transform3D(translation=p, mat3x3=out.T_w_b.rotation().matrix()))
        M = out.T_b_c.matrix()
        if self._T_b_c is None or not np.array_equal(M, self._T_b_c):
            rec.log("world/body/cam0", rr.Transform3D(translation=M[:3, 3], mat3x3=M[:3, :3]))
            self._T_b_c = M
        self._traj.append(p)
        err = self.aligner.add(int(out.t_ns), out.T_w_b) if self.aligner is not None else None
        if out.keyframe and out.landmarks_w is not None:
            rec.log("world/landmarks", rr.Points3D(np.asarray(out.landmarks_w).reshape(-1, 3),
                                                   radii=self.cfg.landmark_radius_m,
                                                   colors=BLUE))
        self._log_camera(out)
        self._log_direct(out)
        bg, ba = out.bias.gyroscope(), out.bias.accelerometer()
        self._rows.append((int(out.index), int(out.t_ns), out.seconds * 1e3, out.n_features,
                           out.n_landmarks, *bg, *ba, out.td_s * 1e3, bool(out.keyframe),
                           np.nan if err is None else err))
        self._n += 1
        if self._n % self.cfg.strip_every == 0:
            self._log_strips()
        if len(self._rows) >= self.cfg.metrics_every:
            self._send_metrics()

    def add_direct_source(self, getter) -> None:
        """Show photometric points: ``getter()`` returns a ``vio.direct.source.PointSnapshot``
        (``uv`` normalized cam0 coordinates, ``rmse``) or None; called on keyframes."""
        self._direct = getter

    def _log_direct(self, out: FrameOutput) -> None:
        snap = self._direct() if self._direct is not None and out.keyframe else None
        if snap is None or self._camera is None or len(snap.uv) == 0:
            return
        t = np.clip(np.nan_to_num(snap.rmse, nan=np.inf) / self.cfg.direct_rmse_full, 0.0, 1.0)
        colors = np.stack([255 * t, 255 * (1 - t), np.zeros_like(t)], 1).astype(np.uint8)
        self.rec.log("world/body/cam0/image/direct_points",
                     rr.Points2D(self._camera.project_normalized(snap.uv), colors=colors,
                                 radii=self.cfg.feature_radius_px))

    def _image(self, pkt: FramePacket | None) -> np.ndarray | None:
        if pkt is None or self._n % self.cfg.image_every:
            return None
        if pkt.images:
            return pkt.images[0]
        if pkt.image_files and not self._image_error:
            from vio.io.euroc import read_image
            try:
                return read_image(pkt.image_files[0])
            except DataError as exc:
                log.warning("rerun: not logging images any more: %s", exc)
                self._image_error = True
        return None

    def _log_camera(self, out: FrameOutput) -> None:
        img = self._image(out.packet)
        if img is not None:
            im = rr.Image(img, color_model="L" if img.ndim == 2 else "BGR")
            q = self.cfg.jpeg_quality
            self.rec.log("world/body/cam0/image", im.compress(q) if q and img.ndim == 2 else im)
        ff = out.features
        n = self._tracks.update(ff.ids if ff is not None else np.zeros(0, np.int64))
        if ff is None or self._camera is None or n.size == 0:
            return
        px = self._camera.project_normalized(ff.uv)
        colors = self._lut[np.minimum(n, self.cfg.track_len_full)]
        self.rec.log("world/body/cam0/image/features",
                     rr.Points2D(px, colors=colors, radii=self.cfg.feature_radius_px))

    # -------------------------------------------------------------- batched
    def _log_strips(self) -> None:
        self._strip_n = self._n
        if self._traj.n >= 2:
            self.rec.log("world/trajectory/estimate",
                         rr.LineStrips3D([self._traj.data], colors=ORANGE, radii=0.01))
        if self.aligner is not None and self.aligner.n_matched >= 1:
            self.aligner.refit()
            gt = self.aligner.strip()
            if len(gt) >= 2:
                self.rec.log("world/trajectory/groundtruth",
                             rr.LineStrips3D([gt], colors=GREEN, radii=0.008))

    def _send_metrics(self) -> None:
        rows, self._rows = self._rows, []
        if not rows:
            return
        frame = np.array([r[0] for r in rows], np.int64)
        t_ns = np.array([r[1] for r in rows], np.int64)
        vals = np.array([r[2:] for r in rows], float)
        self._send_series(frame, t_ns, vals)

    def _send_series(self, frame: np.ndarray, t_ns: np.ndarray, vals: np.ndarray) -> None:
        def send(name: str, sel: np.ndarray, col: np.ndarray) -> None:
            if not sel.any():
                return
            idx = [rr.TimeColumn("frame", sequence=frame[sel]),
                   rr.TimeColumn("time", timestamp=t_ns[sel].astype("datetime64[ns]"))]
            self.rec.send_columns(f"metrics/{name}", indexes=idx,
                                  columns=rr.Scalars.columns(scalars=col[sel]))

        every = np.ones(len(frame), bool)
        for k, name in enumerate(_SERIES):
            send(name, every, vals[:, k])
        kf = vals[:, len(_SERIES)] > 0.5
        send("keyframe", kf, np.ones(len(frame)))
        err = vals[:, len(_SERIES) + 1]
        send("gt_error_m", np.isfinite(err), err)

    # --------------------------------------------------------------- closing
    def close(self) -> None:
        """Send the buffered tail (strips, metrics) and flush; idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._n != self._strip_n:
            self._log_strips()
        self._send_metrics()
        self.rec.flush()
        if self._owned and self.memory is None:
            self.rec.disconnect()

    def __enter__(self) -> RerunSink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - never raise from a finalizer
            pass


# ------------------------------------------------------------------ A* plan
_AXIS = {"x": 0, "y": 1, "z": 2}


def _plane_to_world(uv: np.ndarray, height: float | np.ndarray,
                    plane_axes: tuple[str, str]) -> np.ndarray:
    """Plane points (K, 2) + height along ``e_u x e_v`` -> world points (K, 3)."""
    ea, eb = (np.eye(3)[_AXIS[a]] for a in plane_axes)
    n = np.cross(ea, eb)
    return uv[:, :1] * ea + uv[:, 1:2] * eb + np.reshape(height, (-1, 1)) * n


def log_plan(path: Path, grid: OccupancyGrid, res: PlanResult, m: MapData | None = None) -> None:
    """Record the grid (image: white free, grey inflation, black obstacle), path and map to ``path``.

    The image is in cell coordinates (x = column = u, y = row = v, so it shows
    v growing downward); ``plan/grid/path`` overlays it in pixel units.
    ``world/...`` holds the same path in 3D on the floor, with landmarks and
    trajectory. Writes to the file without a viewer.
    """
    rec = rr.RecordingStream("vio_plan", recording_id=uuid.uuid4())
    rec.save(str(path))
    img = np.full(grid.shape, 255, np.uint8)
    img[grid.blocked] = 160
    img[grid.occupied] = 0
    rec.log("plan/grid", rr.Image(img, color_model="L"))
    ends = np.array([res.start_cell, res.goal_cell], dtype=float)[:, ::-1] + 0.5
    rec.log("plan/grid/endpoints", rr.Points2D(ends, colors=[[0, 200, 0], [220, 0, 0]], radii=1.5,
                                               labels=["start", "goal"]))
    if res.found:
        rec.log("plan/grid/path", rr.LineStrips2D([res.path_cells[:, ::-1] + 0.5], colors=[[0, 90, 255]]))
        xyz = _plane_to_world(res.path_world, grid.floor_height, grid.plane_axes)
        rec.log("world/plan/path", rr.LineStrips3D([xyz], colors=[[0, 90, 255]], radii=0.02))
    if m is not None and len(m.points_w):
        rec.log("world/map/landmarks", rr.Points3D(m.points_w, radii=0.01, colors=[[120, 120, 120]]))
    if m is not None and len(m.trajectory_xyz) > 1:
        rec.log("world/map/trajectory", rr.LineStrips3D([m.trajectory_xyz], colors=[[255, 150, 0]]))
    rec.flush()
    rec.disconnect()
