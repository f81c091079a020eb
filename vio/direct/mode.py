"""``vio run --mode direct`` and ``--mode hybrid``: wiring of the photometric points
(``vio.direct.source.PhotometricSource``) into a ``Pipeline``.

``attach(pipe, data, cfg, hybrid)`` registers the source in ``pipe.est.sources`` and
returns the per-packet stage (``DirectStage``) that ``run_dataset`` applies before
``pipe.process``: it supplies the ``FeatureFrame`` the pipeline needs; the source's
``observe`` reads a keyframe's stereo pair from the packet's files.

* hybrid: the usual stereo KLT stage (``vio.tracking.ImageStage``) tracks every frame
  and matches cam1 at its keyframes (``FrontendConfig.stereo_at``), in the front-end
  worker process as in stereo mode; its features give the backend's projection/stereo
  landmark factors, and the photometric point factors are added to the same graph.
* direct: photometric + IMU only. The backend's landmark manager is replaced by
  ``FeaturelessLandmarks``, which ignores every feature observation, so the graph holds
  no projection factor at all. KLT still runs *until the estimator is initialized*:
  the dynamic (visual-inertial) initialization aligns feature tracks, and the
  keyframe decisions of its buffered window use them. After that KLT is not run; the
  keyframe / stillness decisions of ``Pipeline`` (mean flow since the last keyframe,
  number of common features) see ``FeatureFrame``s made of the live points of every
  host in the window (their refined inverse depths, ``PhotometricSource.live_points``)
  projected into the frame with the IMU-propagated pose
  since the newest keyframe (ids = keyframe * 1e6 + point index; points that leave the
  image drop out, so a view change also triggers a keyframe). These frames carry no
  measurement: nothing in them reaches the graph.

The photometric modes' solver defaults (``vio.modes.MODE_DEFAULTS``; a YAML file
overrides them): relinearization threshold 0.005, checked every 10th update as in the
other modes. With per-point factors, every 10th update left the photometric factors at
stale linearization points and the window diverged within 1 s on a render; the per-host
factor refines its points' depths at each linearization, and checking at every update
now gives the same ATE (real MH_01, renders seed 3/14/21) for 10-18% more CPU.
Direct mode's default keyframe parallax
is 40 px instead of 20: the projected points follow rotation, so at 20 px a turn made
almost every frame a keyframe (279 keyframes in 20 s, 1.1 s per frame); at 40 px the
seed-3 sequence has 150 keyframes, 0.3 s per frame and the same ATE (2.5 cm); 60 px
lost it.

After a divergence restart (the source's ``lost``: points lost, or residuals that stay
high), ``vio.reinit`` re-initializes the window: ``DirectStage`` runs KLT again while it
buffers (direct mode) and ``DirectStage.rebuild`` gives the new estimator a fresh source
(``Pipeline.sources_factory``).

TrackFrame runs once per keyframe inside the source (initial guess of the keyframe
pose, tracking-failure signal in ``source.tracks``), not per frame. A Rerun sink
that has ``add_direct_source(getter)`` receives ``source.snapshot`` (points of the
newest keyframe and their residuals) at ``attach``.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import gtsam
import numpy as np

from factors.photometric import make_host_patch
from factors.photometric_host import HostPoints, StereoHost, host_residual_fn
from vio.backend.bridge import within_hold
from vio.backend.tracks import LandmarkManager
from vio.direct.keyframe import StereoRig, build_keyframe
from vio.direct.photocal import PhotoCalConfig, load_calibration
from vio.direct.source import PhotometricSource
from vio.direct.trackframe import MotionPrior, track_frame
from vio.imu import integrate
from vio.io.types import FeatureFrame
from vio.sync import FramePacket
from vio.errors import DataError
from vio.io.euroc import read_image
from vio.tracking import ImageStage, drop_blank

X = gtsam.symbol_shorthand.X
log = logging.getLogger(__name__)


class FeaturelessLandmarks(LandmarkManager):
    """A landmark manager that ignores feature observations (direct mode): no tracks,
    hence no projection factors; everything else is the inherited no-op bookkeeping."""

    def observe(self, k: int, fr: FeatureFrame) -> None:
        return None


class DirectStage:
    """Per-packet stage of the direct / hybrid modes (module docstring). ``klt`` None:
    the KLT features come with the packets (the front-end worker process, hybrid)."""

    def __init__(self, pipe, data, cfg, hybrid: bool, source: PhotometricSource,
                 klt: bool = True) -> None:
        self.pipe, self.hybrid, self.source = pipe, hybrid, source
        self._klt_args = (data.cam0.calib, data.cam1.calib, cfg.frontend)
        self._min_std = cfg.frontend.min_image_std
        self.klt = ImageStage(*self._klt_args) if klt else None
        self.cam0 = data.cam0.calib
        self._cfg = cfg.direct
        self._k = None
        self._pim = None
        self._tracking = True          # the KLT stage saw the previous packet

    def rebuild(self, est) -> None:
        """Attach a fresh photometric source (and, in direct mode, the featureless landmark
        manager) to ``est``, a re-initialization's new estimator (``vio.reinit``), before
        its first keyframe; the flow features follow the new source."""
        self.source = PhotometricSource(est, self.source.rig, self._cfg)
        est.sources.append(self.source)
        if not self.hybrid:
            est.lm = FeaturelessLandmarks(est)

    def __call__(self, pkt: FramePacket) -> FramePacket:
        if max(len(pkt.images), len(pkt.image_files)) < 2:
            raise ValueError(f"frame {pkt.stamp_ns}: direct/hybrid mode needs cam0 and cam1 images")
        est = self.pipe.est
        # KLT while initializing, and in direct mode also while a re-initialization buffers
        # (its stereo alignment needs tracks, vio.reinit), restarted after a pause
        if self.hybrid or not est.initialized or self.pipe.reinit.active:
            if self.klt is not None and not self._tracking:
                self.klt = ImageStage(*self._klt_args)
            self._tracking = True
            return pkt if self.klt is None else self.klt(pkt)
        self._tracking = False
        # direct after initialization: no image is read here; the source reads a
        # keyframe's pair when it observes it (two PNG decodes per frame were ~20% of
        # direct mode's time on real MH_01, where 3 frames in 10 are keyframes)
        if pkt.imu_gaps or within_hold(est, pkt.t_ns):
            # across an IMU gap the predicted flow measures nothing (the packet's IMU is
            # interpolated over the gap): no flow points, so every frame past the minimum
            # interval is a keyframe and TrackFrame extrapolates over short intervals only
            # (real MH_01, 3-s gap 6 s in: keyframes every 0.3 s, TrackFrame failed at
            # four of them and the estimate slid 0.49 m). Likewise while the IMU is held
            # out after vision contradicted it (BridgeConfig.imu_check_hold_s)
            pkt = dataclasses.replace(pkt, features=FeatureFrame.empty(pkt.t_ns))
        else:
            pkt = dataclasses.replace(pkt, features=self._flow_features(pkt))
        return self._left_image(pkt) if self.pipe.takes_keyframe(pkt) else pkt

    def _left_image(self, pkt: FramePacket) -> FramePacket:
        """A keyframe-to-be with its cam0 image decoded (``images``: left only; the source
        reads the right one), or ``dropped`` as the KLT stage drops a frame
        (``vio.tracking.ImageStage.load``) when that image does not decode or shows
        nothing: a blank image made a keyframe gives TrackFrame and every host a black
        target (real MH_01 direct, both cameras black for 1 s from frame 150: 11.0 mm and
        a restart against 4.7 mm clean)."""
        if pkt.images or not pkt.image_files:
            return pkt
        try:
            left = read_image(pkt.image_files[0], self.cam0)
        except DataError as exc:
            return dataclasses.replace(pkt, dropped=str(exc))
        return drop_blank(dataclasses.replace(pkt, images=(left,)), self._min_std)

    def _predict(self, pkt: FramePacket) -> gtsam.Pose3:
        """T_w_b at this packet: newest keyframe estimate + IMU since (own preintegration,
        since the pipeline integrates the packet only after this stage)."""
        est = self.pipe.est
        T, v, b = est.latest()
        if self._k != (id(est), est.k):       # a new keyframe, or a re-initialization's estimator
            self._k = (id(est), est.k)
            self._pim = gtsam.PreintegratedCombinedMeasurements(est.params, b)
        integrate(self._pim, pkt.imu)
        return self._pim.predict(gtsam.NavState(T, v), b).pose()

    def _flow_features(self, pkt: FramePacket) -> FeatureFrame:
        """The source's points (all hosts in the window) projected into this frame
        (normalized cam0), with their point ids: the ids persist over keyframes, so the
        pipeline's flow (stillness, parallax) compares the same points across frames."""
        src, est = self.source, self.pipe.est
        T_c_w = self._predict(pkt).compose(src.rig.T_b_c).inverse()
        ids, uvs = [], []
        w, h = self.cam0.resolution
        for f, uv_h, rho, idx in src.live_points():
            T = T_c_w.compose(est.values.atPose3(X(f)).compose(src.rig.T_b_c))
            q = src.rig.K0.unproject(uv_h) / np.maximum(rho, 1e-6)[:, None]
            q = q @ T.rotation().matrix().T + T.translation()
            z = q[:, 2]
            px = src.rig.K0.project(np.where(z[:, None] > 0.05, q, 1.0))
            ok = (z > 0.05) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
            ids.append((f * 1_000_000 + idx)[ok])
            uvs.append(q[ok, :2] / z[ok, None])
        ids_a = np.concatenate(ids).astype(np.int64) if ids else np.zeros(0, np.int64)
        uv = np.concatenate(uvs) if uvs else np.zeros((0, 2))
        return FeatureFrame(pkt.t_ns, ids_a, uv, np.zeros_like(uv), np.full(len(ids_a), np.nan))


def _cam_dir(cam) -> Path | None:
    """The folder holding a camera's ``data.csv`` (where a photometric calibration
    would be), None for sources without one (bags)."""
    files = getattr(cam, "files", None)
    if not files:
        return None
    d = Path(files[0]).parent.parent
    return d if (d / "data.csv").exists() else None


def _rig(data, pc: PhotoCalConfig) -> StereoRig:
    """The stereo rig with each camera's photometric calibration (logged when one is used)."""
    cals = []
    for i, cam in enumerate((data.cam0, data.cam1)):
        w, h = cam.calib.resolution
        cal = load_calibration(_cam_dir(cam), (h, w), pc, cam0=i == 0)
        if not cal.identity:
            log.info("cam%d photometric calibration: %s", i, cal.source)
        cals.append(cal)
    return StereoRig(data.cam0.calib, data.cam1.calib, *cals)


def attach(pipe, data, cfg, hybrid: bool, klt: bool = True) -> DirectStage:
    """Register the photometric source of ``cfg.direct`` in ``pipe`` (before its first
    keyframe) and return the packet stage; direct mode (``hybrid=False``) also replaces
    the landmark manager by ``FeaturelessLandmarks``. ``klt`` False: the packets arrive
    with their KLT features (hybrid with the front end in its worker process)."""
    if pipe.est.initialized:
        raise RuntimeError("attach the direct source before the pipeline is initialized")
    if data.cam1 is None:
        raise ValueError(f"{data.root}: direct/hybrid mode needs a cam1 calibration")
    source = PhotometricSource(pipe.est, _rig(data, cfg.direct.photometric), cfg.direct)
    _warm_up(source)
    pipe.est.sources.append(source)
    if not hybrid:
        pipe.est.lm = FeaturelessLandmarks(pipe.est)
    stage = DirectStage(pipe, data, cfg, hybrid, source, klt)
    pipe.sources_factory = stage.rebuild
    for sink in pipe.sinks:
        register = getattr(sink, "add_direct_source", None)
        if register is not None:
            register(lambda: stage.source.snapshot())
    return stage


def _warm_up(source: PhotometricSource) -> None:
    """Load (or compile) the Numba kernels of keyframe building, TrackFrame and the
    host factor now, on a noise image pair of the cameras' size: their first calls
    otherwise stall the first keyframes after initialization (~1.5 s to compile on
    a fresh install, ~0.3 s to load from Numba's cache)."""
    import cv2

    w, h = source.rig.cam0.resolution
    img = cv2.blur(np.random.default_rng(0).uniform(20, 230, (h, w)), (5, 5))   # smooth texture
    kd = build_keyframe(-1, 0, img, img, source.rig, source.cfg)
    if len(kd.uv) == 0:
        return
    track_frame(kd.reference(np.zeros(2), source.cfg), kd.image, gtsam.Pose3(), np.zeros(2),
                source.cfg.track, MotionPrior(gtsam.Pose3(), 1e-3, 1e-3))
    n = min(len(kd.uv), 8)
    pts = HostPoints.create(make_host_patch(kd.left, kd.uv[:n], source.rig.K0), kd.idepth[:n],
                            source.cfg.points.grad_c, source.cfg.points.max_targets)
    stereo = StereoHost(kd.right._stack, source.rig.K1, source.rig.T_c1_c0, kd.ab_right)
    # one signature serves every target count (the kernel gets the whole mask)
    fn = host_residual_fn(pts, [kd.left._stack], source.rig.K0, source.rig.T_b_c, source.params, stereo)
    fn([gtsam.Pose3(), np.zeros(2)] * 2)
