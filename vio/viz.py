"""Rerun live view of a VIO run (``vio/viz*.py`` are the only modules importing rerun).

``RerunSink`` is a pipeline sink (``Pipeline.sinks``): it observes each
``FrameOutput`` and never feeds anything back to the estimator. Ground truth,
when given, is drawn for comparison only. Layout: ``vio.viz_blueprint``.

Timelines: ``frame`` (sequence, ``FrameOutput.index``) and ``time`` (timestamp,
``FrameOutput.t_ns`` as nanoseconds since the Unix epoch).

Entity paths (stable; tests read them back). Sizes given as "pt" are UI points
(constant on screen whatever the zoom):

- ``world``: ``ViewCoordinates`` right-handed z-up (static).
- ``world/trajectory/estimate/<k>``: ``LineStrips3D``, the online positions cut into
  segments of ``segment_len`` frames; the current segment is re-logged every frame.
  Both trajectories are logged as separate 2-point strips (see ``_pieces``).
- ``world/trajectory/groundtruth``: ``LineStrips3D`` of the ground-truth positions at
  the estimate's times, mapped into the estimate's world by a 4-DoF (yaw +
  translation) fit (``GroundTruthAligner``); re-logged every ``strip_every`` frames
  (less often on long runs, see ``_gt_due``). Wider and translucent, so the estimate
  drawn over it leaves it visible.
- ``world/map/window``: ``Points3D`` of the landmarks in the window, on keyframes.
- ``world/map/marginalized/<k>``: ``Points3D`` of the landmarks that left the window
  (their last estimate), in chunks; at most ``map_max_points`` (oldest chunks cleared).
- ``world/body``: ``Transform3D`` of ``T_w_b`` every frame.
- ``world/body/cam0``: ``Transform3D`` of ``T_b_c`` (when it changes) and a static ``Pinhole``.
- ``world/body/cam0/image``: the left image every ``image_every`` frames (JPEG at
  ``jpeg_quality``; raw when None); absent for feature-only data.
- ``world/body/cam0/image/features``: ``Points2D``, the tracked features (distorted
  pixels) coloured by track length (red: new, green: ``track_len_full`` frames or more).
- ``world/body/cam0/image/tracks``: ``LineStrips2D``, the last ``trail_len`` positions
  of each track (logged with the image; every frame for feature-only data).
- ``world/body/cam0/image/direct_points``: on keyframes of the direct / hybrid modes,
  the photometric points of the keyframe (``add_direct_source``), coloured by inverse
  depth (magenta: ``direct_inv_depth_full`` 1/m or nearer, cyan: far); the keyframes'
  images are always logged in these modes, and the points cleared with the next image.
- ``cam1/image`` (stereo): the right image; ``cam1/image/matches`` (``Points2D``) the
  stereo matches in cam1 pixels; ``cam1/image/disparity`` (``LineStrips2D``) from each
  match to the feature's cam0 pixel.
- ``metrics/<plot>/<series>`` (``Scalars``; see ``vio.viz_blueprint.PLOTS``): timing
  (``frame_ms``, ``keyframe_ms`` as points at keyframes), counts, velocity, gyro bias,
  accel bias, td, and ``gt_error/error_m`` with ground truth; buffered and sent as
  columns every ``metrics_every`` frames.
- ``events``: ``TextLog`` of the ``vio`` package's log records of level INFO and above
  (initialization, restarts, IMU gaps, ...), forwarded by a ``logging.Handler`` while
  the sink is open and stamped with the next frame the sink logs.
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr

from vio.errors import DataError
from vio.io.types import CameraCalib, GroundTruth
from vio.viz_align import (BLUE, GREEN, ORANGE, GroundTruthAligner, Rows, TrackLengths,  # noqa: F401
                           fit_yaw_translation, track_colors)
from vio.viz_blueprint import FOLLOW, OVERVIEW, default_blueprint, plots
from vio.viz_config import RerunConfig
from vio.viz_io import EventLog, jpeg, optimize_rrd, ramp
from vio.viz_plan import log_plan  # noqa: F401 - re-exported
from vio.viz_state import LandmarkMap, Segments, TrackTrails

if TYPE_CHECKING:
    from vio.pipeline import FrameOutput
    from vio.sync import FramePacket

log = logging.getLogger(__name__)

ENTITIES = ("world/trajectory/estimate/0", "world/trajectory/groundtruth", "world/map/window",
            "world/map/marginalized/0", "world/body", "world/body/cam0", "world/body/cam0/image",
            "world/body/cam0/image/features", "world/body/cam0/image/tracks",
            "metrics/timing/frame_ms", "metrics/timing/keyframe_ms", "metrics/counts/features",
            "metrics/counts/landmarks", "metrics/velocity/x", "metrics/velocity/norm",
            "metrics/gyro_bias/x", "metrics/gyro_bias/z", "metrics/accel_bias/y", "metrics/td/td_ms",
            "metrics/gt_error/error_m")

# the columns buffered per frame, in order (see _row)
_COLUMNS = ("timing/frame_ms", "counts/features", "counts/landmarks", "velocity/x", "velocity/y",
            "velocity/z", "velocity/norm", "gyro_bias/x", "gyro_bias/y", "gyro_bias/z",
            "accel_bias/x", "accel_bias/y", "accel_bias/z", "td/td_ms", "keyframe", "gt_error/error_m")
WINDOW_COLOR, MAP_COLOR, GT_COLOR = 0x10D8F0FF, 0x8C96AAFF, 0x30C03080


def _frame(center: np.ndarray, distance_m: float) -> rr.Points3D:
    """Two invisible points around ``center`` for a 3D eye to track. When the viewer starts
    tracking an entity with its data loaded, it orbits at 1.5 x the diagonal of its bounding
    box (measured in the 0.41 web viewer), else at the blueprint's eye distance; sized so,
    both are ``distance_m``."""
    d = distance_m / (1.5 * 2.0 * np.sqrt(3.0))
    return rr.Points3D(center + np.array([[-d, -d, -d], [d, d, d]]), colors=0x00000000, radii=0.0)


def _pieces(p: np.ndarray) -> np.ndarray:
    """(N, 3) polyline -> (N - 1, 2, 3) separate segments: the viewer draws a strip's joins
    as mitres, which turn each sharp reversal of a hand-held path into a long spike."""
    return np.stack([p[:-1], p[1:]], 1)


class RerunSink:
    """Pipeline sink logging each ``FrameOutput`` to Rerun (entities: module docstring).

    ``spawn``: spawn (or connect to) a viewer on ``cfg.port``; ``rrd``: record to
    this file; both may be set. ``recording``: log into this stream instead of a
    new one (spawn/rrd still attach to it); with none of the three, the sink
    records into memory (``self.memory``). ``cam``: cam0 calibration (frustum, feature
    pixels); ``cam1``: the second camera of stereo modes (right image, matches).
    Call ``close()`` (or use ``with``) to send the buffered tail and detach the event
    log handler; it also runs when the sink is garbage-collected.
    """

    def __init__(self, spawn: bool = False, rrd: Path | None = None,
                 groundtruth: GroundTruth | None = None, cam: CameraCalib | None = None,
                 app_id: str = "vio", recording: rr.RecordingStream | None = None,
                 cfg: RerunConfig = RerunConfig(), cam1: CameraCalib | None = None) -> None:
        self._closed = True          # until fully constructed (see __del__)
        self.cfg, self.cam, self.cam1 = cfg, cam, cam1
        from vio.frontend.camera import Camera
        self._camera = Camera(cam) if cam is not None else None
        self._camera1 = Camera(cam1) if cam1 is not None else None
        self.aligner = None
        if groundtruth is not None and len(groundtruth) >= 2:
            self.aligner = GroundTruthAligner(groundtruth, cfg.gt_max_gap_s, cfg.gt_min_spread_m)
        self.blueprint = default_blueprint(stereo=cam1 is not None, groundtruth=self.aligner is not None,
                                           follow_m=cfg.follow_m, overview_m=cfg.overview_m)
        self._owned = recording is None
        self.rec = recording if recording is not None else rr.RecordingStream(
            app_id, recording_id=uuid.uuid4())
        self.memory: rr.MemoryRecording | None = None
        self._rrd = None if rrd is None else Path(rrd)
        self._connect(spawn, self._rrd)
        self._tracks, self._trails = TrackLengths(), TrackTrails(cfg.trail_len)
        self._lut = track_colors(cfg.track_len_full)
        self._map = LandmarkMap(cfg.map_max_points, cfg.map_chunk)
        self._traj = Segments(cfg.segment_len)
        self._rows: list[tuple] = []
        self._n = self._gt_n = 0
        self._lo, self._hi = np.full(3, np.inf), np.full(3, -np.inf)      # trajectory bounds
        self._T_b_c: np.ndarray | None = None
        self._image_error = False
        self._direct = None
        self._log_static()
        self.events = EventLog()
        self.events.attach()
        self._closed = False

    # ----------------------------------------------------------------- setup
    def _connect(self, spawn: bool, rrd: Path | None) -> None:
        if rrd is not None and not rrd.parent.is_dir():
            raise ValueError(f"{rrd}: directory {rrd.parent} does not exist")
        bp, port = self.blueprint, self.cfg.port
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
        for p in plots(self.aligner is not None):
            for leaf, name, color, points in p.series:
                style = (rr.SeriesPoints(colors=color, names=name, markers="diamond", marker_sizes=3.0)
                         if points else rr.SeriesLines(colors=color, names=name, widths=1.5))
                rec.log(f"metrics/{p.name}/{leaf}", style, static=True)
        rec.log(FOLLOW, _frame(np.zeros(3), self.cfg.follow_m), static=True)
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
        self._log_events()
        p = np.asarray(out.T_w_b.translation(), float)
        rec.log("world/body", rr.Transform3D(translation=p, mat3x3=out.T_w_b.rotation().matrix()))
        M = out.T_b_c.matrix()
        if self._T_b_c is None or not np.array_equal(M, self._T_b_c):
            rec.log("world/body/cam0", rr.Transform3D(translation=M[:3, 3], mat3x3=M[:3, :3]))
            self._T_b_c = M
        self._lo, self._hi = np.minimum(self._lo, p), np.maximum(self._hi, p)
        if out.keyframe or self._n == 0:
            rec.log(OVERVIEW, _frame((self._lo + self._hi) / 2, self.cfg.overview_m))
        k, seg = self._traj.append(p)
        if len(seg) >= 2:
            rec.log(f"world/trajectory/estimate/{k}",
                    rr.LineStrips3D(_pieces(seg), colors=ORANGE, radii=-self.cfg.estimate_pt))
        err = self.aligner.add(int(out.t_ns), out.T_w_b) if self.aligner is not None else None
        if out.keyframe and out.landmarks_w is not None:
            self._log_map(out)
        self._log_direct(out, self._log_camera(out))
        row = self._row(out, err)
        if self._n == 0:     # alignment (and first-call compilation): an event, not a plot spike
            rec.log("events", rr.TextLog(f"first estimate at frame {out.index}: took {row[2]:.0f} ms "
                                         "(initialization)", level="INFO"))
            row = (*row[:2], np.nan, *row[3:])
        self._rows.append(row)
        self._n += 1
        if self._gt_due():
            self._log_groundtruth()
        if len(self._rows) >= self.cfg.metrics_every:
            self._send_metrics()

    @staticmethod
    def _row(out: FrameOutput, err: float | None) -> tuple:
        v = np.asarray(out.v_w, float).reshape(3)
        return (int(out.index), int(out.t_ns), out.seconds * 1e3, out.n_features, out.n_landmarks,
                *v, float(np.linalg.norm(v)), *out.bias.gyroscope(), *out.bias.accelerometer(),
                out.td_s * 1e3, float(bool(out.keyframe)), np.nan if err is None else err)

    def _log_events(self) -> None:
        recs = self.events.records
        while recs:
            level, text = recs.popleft()
            self.rec.log("events", rr.TextLog(text, level=level))

    def _log_map(self, out: FrameOutput) -> None:
        ids = out.landmark_ids if out.landmark_ids is not None else np.arange(len(out.landmarks_w))
        up = self._map.update(ids, out.landmarks_w)
        self.rec.log("world/map/window", rr.Points3D(up.window, colors=WINDOW_COLOR,
                                                     radii=-self.cfg.window_pt))
        for k in up.dropped:
            self.rec.log(f"world/map/marginalized/{k}", rr.Clear(recursive=False))
        if up.chunk is not None:
            self.rec.log(f"world/map/marginalized/{up.chunk[0]}",
                         rr.Points3D(up.chunk[1], colors=MAP_COLOR, radii=-self.cfg.map_pt))

    def add_direct_source(self, getter) -> None:
        """Show photometric points: ``getter()`` returns a ``vio.direct.records.PointSnapshot``
        (``uv`` normalized cam0 coordinates, ``inv_depth``) or None; called on keyframes."""
        self._direct = getter

    def _log_direct(self, out: FrameOutput, image_logged: bool = False) -> None:
        """On keyframes (whose image is always logged in these modes) the points of the
        snapshot; they are cleared with the next image."""
        path = "world/body/cam0/image/direct_points"
        if self._direct is not None and image_logged and not out.keyframe:
            self.rec.log(path, rr.Clear(recursive=False))
        snap = self._direct() if self._direct is not None and out.keyframe else None
        if snap is None or self._camera is None or len(snap.uv) == 0:
            return
        rho = getattr(snap, "inv_depth", None)
        rho = np.zeros(len(snap.uv)) if rho is None else np.asarray(rho, float)
        self.rec.log(path, rr.Points2D(self._camera.project_normalized(snap.uv),
                                 colors=ramp(rho / self.cfg.direct_inv_depth_full),
                                 radii=-self.cfg.feature_pt))

    # ----------------------------------------------------------------- images
    def _images(self, pkt: FramePacket | None, force: bool) -> list[np.ndarray | None]:
        """[cam0, cam1] images of this frame (None where absent or not due)."""
        if pkt is None or (self._n % self.cfg.image_every and not force):
            return [None, None]
        if pkt.images:
            return [pkt.images[0], pkt.images[1] if len(pkt.images) > 1 else None]
        out: list[np.ndarray | None] = [None, None]
        if pkt.image_files and not self._image_error:
            from vio.io.euroc import read_image
            try:
                for i, f in enumerate(pkt.image_files[:2]):
                    out[i] = read_image(f)
            except DataError as exc:
                log.warning("rerun: not logging images any more: %s", exc)
                self._image_error = True
        return out

    def _log_camera(self, out: FrameOutput) -> bool:
        """Images and feature overlays of this frame; True if the cam0 image was logged."""
        pkt = out.packet
        has_images = pkt is not None and bool(pkt.images or pkt.image_files) and not self._image_error
        img0, img1 = self._images(pkt, force=self._direct is not None and out.keyframe)
        q = self.cfg.jpeg_quality
        if img0 is not None:
            self.rec.log("world/body/cam0/image", jpeg(img0, q))
        if img1 is not None and self.cam1 is not None:
            self.rec.log("cam1/image", jpeg(img1, q))
        ff = out.features
        n = self._tracks.update(ff.ids if ff is not None else np.zeros(0, np.int64))
        if ff is None or self._camera is None:
            return img0 is not None
        px = self._camera.project_normalized(ff.uv) if n.size else np.zeros((0, 2))
        trails = self._trails.update(ff.ids, px)
        if has_images and img0 is None:
            return False                   # overlays only on frames with an image
        colors = self._lut[np.minimum(n, self.cfg.track_len_full)]
        self.rec.log("world/body/cam0/image/features",
                     rr.Points2D(px, colors=colors, radii=-self.cfg.feature_pt))
        self.rec.log("world/body/cam0/image/tracks", rr.LineStrips2D(trails, colors=0xFFD040C0,
                                                                     radii=-0.6))
        if img1 is not None:
            self._log_matches(ff, px)
        return img0 is not None

    def _log_matches(self, ff, px0: np.ndarray) -> None:
        if ff.right_uv is None or self._camera1 is None:
            return
        ok = np.all(np.isfinite(ff.right_uv), axis=1)
        px1 = self._camera1.project_normalized(ff.right_uv[ok]) if ok.any() else np.zeros((0, 2))
        self.rec.log("cam1/image/matches", rr.Points2D(px1, colors=0x40E0FFFF, radii=-self.cfg.feature_pt))
        self.rec.log("cam1/image/disparity", rr.LineStrips2D(np.stack([px1, px0[ok]], 1),
                                                             colors=0x40E0FF90, radii=-0.6))

    # -------------------------------------------------------------- batched
    def _gt_due(self) -> bool:
        """Ground truth is re-logged every ``strip_every`` frames, and every 2% of the
        run once that is longer, so its total size grows linearly with the run."""
        return self.aligner is not None and self._n - self._gt_n >= max(self.cfg.strip_every, self._n // 50)

    def _log_groundtruth(self) -> None:
        self._gt_n = self._n
        if self.aligner is None or self.aligner.n_matched < 2:
            return
        self.aligner.refit()
        self.rec.log("world/trajectory/groundtruth",
                     rr.LineStrips3D(_pieces(self.aligner.matched_strip()), colors=GT_COLOR,
                                     radii=-self.cfg.groundtruth_pt))

    def _send_metrics(self) -> None:
        rows, self._rows = self._rows, []
        if not rows:
            return
        frame = np.array([r[0] for r in rows], np.int64)
        t_ns = np.array([r[1] for r in rows], np.int64)
        vals = np.array([r[2:] for r in rows], float)
        cols = dict(zip(_COLUMNS, vals.T))
        kf = cols.pop("keyframe") > 0.5
        cols["timing/keyframe_ms"] = np.where(kf, cols["timing/frame_ms"], np.nan)
        if self.aligner is None:
            cols.pop("gt_error/error_m")
        for name, col in cols.items():
            sel = np.isfinite(col)
            if not sel.any():
                continue
            idx = [rr.TimeColumn("frame", sequence=frame[sel]),
                   rr.TimeColumn("time", timestamp=t_ns[sel].astype("datetime64[ns]"))]
            self.rec.send_columns(f"metrics/{name}", indexes=idx,
                                  columns=rr.Scalars.columns(scalars=col[sel]))

    # --------------------------------------------------------------- closing
    def close(self, optimize: bool = True) -> None:
        """Send the buffered tail (ground truth, metrics, events), flush, detach, and
        compact the .rrd file (``optimize`` and ``cfg.optimize_rrd``); idempotent."""
        if self._closed:
            return
        self._closed = True
        self.events.detach()
        self._log_events()
        if self.aligner is not None and self._n != self._gt_n:
            self._log_groundtruth()
        self._send_metrics()
        self.rec.flush()
        if self._owned and self.memory is None:
            self.rec.disconnect()
            if optimize and self.cfg.optimize_rrd and self._rrd is not None:
                optimize_rrd(self._rrd)

    def __enter__(self) -> RerunSink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close(optimize=False)
        except Exception:  # noqa: BLE001 - never raise from a finalizer
            pass
