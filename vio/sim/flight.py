"""Images rendered along a real flight: the real IMU, a rendered camera.

``render_flight(src, out, tracks_cfg, sim_cfg)`` takes an EuRoC sequence's real IMU and
ground truth (a folder with ``imu0/``, ``state_groundtruth_estimate0/`` and
``cam0/sensor.yaml``, e.g. ``../shared/data/euroc_imu_gt/<SEQ>``), smooths the ground truth
against the IMU as the feature-track generator does (:func:`vio.sim.tracks.fused_truth`:
the IMU-consistent trajectory at every frame's stamp and exposure), and renders
``vio.sim``'s textured room, sized to the flight, along it. The output is an EuRoC folder
whose IMU rows are the source's verbatim: image-mode runs (mono, stereo, direct, hybrid)
on real IMU noise, biases and motion, for as long as the flight lasts, where the shared
real-image sets stop after 15-16 s.

Frames: the room spans ``[0, L]`` (z up, gravity -z as in the EuRoC ground-truth world);
the written ground truth is the fused trajectory shifted by ``offset_w`` into it (a
translation, so SE3-aligned errors are unchanged). Clocks: a frame stamped ``s`` shows the
pose at ``s + td`` (``tracks_cfg.td_s``; with motion blur the mean over an exposure centred
there); with a rolling shutter (``sim_cfg.line_time_s``) sensor row r shows the pose at
``s + td + r * line_time``, through the lens where there is one (``DistortedView.sensor_row``). The cameras are ``vio.sim.render.sim_camera``'s (EuRoC
intrinsics and extrinsics, no distortion) or, with ``FlightOptics.distortion``, the
source's own calibrations rendered through their distortion (``vio.sim.optics``).
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from vio.config import to_dict
from vio.io.calib import load_camera
from vio.io.euroc import find_mav0
from vio.io.types import CameraCalib
from vio.sim import SimResult
from vio.sim.config import SimConfig
from vio.sim.optics import DistortedView, FlightOptics, blur_offsets
from vio.sim.render import camera_row_poses, exposure_sequence, photometric, render, sim_camera
from vio.sim.scene import scene_around
from vio.sim.texture import build_textures
from vio.sim.tracks import frame_grid, fused_truth
from vio.sim.tracks_config import TrackGenConfig
from vio.sim.tracks_io import GT_DIR, read_groundtruth, read_table
from vio.sim.writer import (CameraWriter, write_body_yaml, write_exposure_csv, write_groundtruth,
                            write_truth_yaml)
from vio.trajectory import interpolate_poses

__all__ = ["render_flight", "flight_room"]


WALL_MARGIN_M = 3.0          # walls beyond the flight (EuRoC's halls: most points 3-12 m away)
MAX_TEXELS = 16e6            # level-0 texels of the whole room (~85 MB with the mip levels)


def flight_room(p_w: np.ndarray, margin_m: float = WALL_MARGIN_M) -> tuple[np.ndarray, np.ndarray]:
    """(room size (3,) m, offset (3,) m added to world positions) of a room whose walls
    stand ``margin_m`` beyond the flight positions ``p_w`` (N, 3) horizontally, the floor
    1 m below the lowest and the ceiling 1.5 m above the highest."""
    lo = p_w.min(axis=0) - np.array([margin_m, margin_m, 1.0])
    hi = p_w.max(axis=0) + np.array([margin_m, margin_m, 1.5])
    return np.maximum(hi - lo, 1.0), -lo


def _room_config(cfg: SimConfig, size: np.ndarray) -> SimConfig:
    """``cfg`` with the room ``size``; obstacles at ``cfg``'s counts per the default room's
    floor area (at least ``cfg``'s counts); texture density lowered where the room's
    surfaces would need more than ``MAX_TEXELS`` texels at ``cfg.texels_per_m``."""
    d = SimConfig()
    scale = size[0] * size[1] / (d.room_size[0] * d.room_size[1])
    area = 2 * (size[0] * size[1] + size[0] * size[2] + size[1] * size[2])
    return replace(cfg, room_size=tuple(float(x) for x in size),
                   n_boxes=int(max(cfg.n_boxes, round(cfg.n_boxes * scale))),
                   n_pillars=int(max(cfg.n_pillars, round(cfg.n_pillars * scale))),
                   texels_per_m=float(min(cfg.texels_per_m, np.sqrt(MAX_TEXELS / area))))


def render_flight(src: Path, out: Path, tracks_cfg: TrackGenConfig, sim_cfg: SimConfig,
                  optics: FlightOptics = FlightOptics(), progress: bool = False,
                  overwrite: bool = False) -> SimResult:
    """Render ``src``'s flight from ``tracks_cfg.start_s`` for ``tracks_cfg.duration_s``
    (camera rate ``tracks_cfg.rate_hz``, offset ``td_s``; the ground-truth smoothing's
    settings) into ``out/mav0`` with ``sim_cfg``'s cameras (``stereo``, ``image_scale``),
    textures, obstacles, brightness changes (``exposure_changes``) and image noise, and
    ``optics``' lens distortion and motion blur (see module docstring)."""
    src, out = find_mav0(src), Path(out)
    mav0 = out / "mav0"
    if mav0.exists():
        if not overwrite:
            raise FileExistsError(f"{mav0} exists; pass overwrite=True (--force) to replace it")
        shutil.rmtree(mav0)
    imu = read_table(src / "imu0" / "data.csv", 6)
    gt, gt_p, gt_q, _ = read_groundtruth(src)
    td = int(round(tracks_cfg.td_s * 1e9))
    t_ns = frame_grid(tracks_cfg, gt.t_ns, imu.t_ns, td)
    if len(t_ns) < 2:
        raise ValueError(f"{src}: fewer than 2 camera frames fit the ground truth and IMU from "
                         f"{tracks_cfg.start_s} s for {tracks_cfg.duration_s} s")
    fused = fused_truth(src, tracks_cfg, imu, gt, gt_p, gt_q, t_ns, td, _readout_nodes(t_ns + td, sim_cfg))
    size, offset = flight_room(fused.p_w)
    cfg = _room_config(sim_cfg, size)
    scene = scene_around(cfg, (fused.p_w + offset)[:, :2])
    atlas = build_textures(scene, cfg.texels_per_m, cfg.seed)
    names = ("cam0", "cam1") if cfg.stereo else ("cam0",)
    if optics.distortion:
        cams = [replace(load_camera(src / n / "sensor.yaml", n), rate_hz=tracks_cfg.rate_hz,
                        line_time_s=cfg.line_time_s) for n in names]
    else:
        cams = [sim_camera(n, cfg.image_scale, tracks_cfg.rate_hz, cfg.line_time_s) for n in names]
    mav0.mkdir(parents=True)
    exposure = _render_frames(mav0, cams, scene, atlas, cfg, optics, fused, offset, t_ns, td, progress)
    n_imu = _write_inertial(src, mav0, imu, fused, offset, t_ns, td, tracks_cfg.imu_margin_s)
    exposure_path = out / "exposure.csv"
    write_exposure_csv(exposure_path, t_ns, exposure)
    truth_path = out / "sim_truth.yaml"
    write_truth_yaml(truth_path, {
        "generator": "vio.sim.flight", "source": str(src), "start_s": tracks_cfg.start_s,
        "duration_s": tracks_cfg.duration_s, "td_s": tracks_cfg.td_s, "line_time_s": cfg.line_time_s,
        "convention": "image stamp + td = exposure time (IMU clock); the IMU rows are the source's",
        "offset_w": [float(x) for x in offset], "gravity_w": [0.0, 0.0, -9.81],
        "exposure_model": "image = clip(exp(a) * radiance + b + noise)", "exposure_file": exposure_path.name,
        "optics": to_dict(optics), "scene": scene.describe(), "config": to_dict(cfg),
        "tracks_config": to_dict(tracks_cfg),
        "imu_consistent_gt": {"pos_shift_rms_m": fused.shift_pos_rms_m,
                              "rot_shift_rms_deg": float(np.degrees(fused.shift_rot_rms_rad))},
    })
    return SimResult(out, mav0, truth_path, exposure_path, tuple(names), int(len(t_ns)), n_imu)


def _render_frames(mav0: Path, cams: list[CameraCalib], scene, atlas, cfg: SimConfig, optics: FlightOptics,
                   fused, offset: np.ndarray, t_ns: np.ndarray, td: int,
                   progress: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every frame of every camera written as PNG (camera ``sensor.yaml`` too); returns
    the brightness ``(a, b)`` per camera (``vio.sim.render.exposure_sequence``)."""
    views = [DistortedView(c) if optics.distortion else None for c in cams]
    writers = [CameraWriter(mav0 / c.name, c) for c in cams]
    t_s = (t_ns - t_ns[0]) * 1e-9
    exposure = {c.name: exposure_sequence(cfg.exposure_changes, t_s, cfg.exposure_log_gain_amp,
                                          cfg.exposure_bias_amp, cfg.exposure_period_s,
                                          np.random.default_rng([cfg.seed, 5, k]))
                for k, c in enumerate(cams)}
    dt = np.round(blur_offsets(optics) * 1e9).astype(np.int64)
    frames = range(len(t_ns))
    if progress:
        from tqdm import tqdm
        frames = tqdm(frames, desc="vio sim", unit="frame")
    for j in frames:
        body = [_body_rows(fused, offset, cams[0], t + td) for t in t_ns[j] + dt]
        for k, (cam, view, wr) in enumerate(zip(cams, views, writers)):
            rcam = cam if view is None else view.virtual
            pose_of = None if view is None or cam.line_time_s == 0.0 else view.sensor_row
            radiance = np.mean([render(scene, atlas, rcam, *_camera_rows(sample, cam, rcam.height), pose_of)[0]
                                for sample in body], axis=0)
            if view is not None:
                radiance = view(radiance)
            a, b = exposure[cam.name][0][j], exposure[cam.name][1][j]
            rng = np.random.default_rng([cfg.seed, 6, j, k])
            wr.add(int(t_ns[j]), photometric(radiance, a, b, cfg.image_noise_sigma, rng))
    lens = "its own calibration, rendered through the distortion" if optics.distortion else "zero distortion"
    for wr in writers:
        wr.close(f"vio sim along a real flight (EuRoC intrinsics and T_BS, {lens})")
    return exposure


def _readout_nodes(exposure_ns: np.ndarray, cfg: SimConfig, n: int = 4) -> np.ndarray | None:
    """Trajectory nodes ``n`` evenly spaced over each frame's rolling-shutter readout after
    its exposure time ``exposure_ns`` (None for a global shutter): rows between them
    interpolate over ~3.6 ms at a 14-ms readout (a slerp over a 50-ms frame period is up to
    ~1 mrad off the IMU's motion at 5 rad/s^2)."""
    if cfg.line_time_s == 0.0:
        return None
    readout = cfg.readout_s * 1e9
    return (exposure_ns[:, None] + np.round(np.arange(1, n + 1) * readout / n).astype(np.int64)).ravel()


def _body_rows(fused, offset: np.ndarray, cam: CameraCalib, t0_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Body poses ``(p_w, R_w_b)`` ((n,3), (n,3,3)) of the sensor rows of the rig's cameras
    (they share ``cam``'s height and line time), row r at ``t0_ns + r * line_time``; n = 1
    for a global shutter."""
    if cam.line_time_s == 0.0:
        return interpolate_poses(fused.t_ns, fused.p_w + offset, fused.q_wxyz, np.array([t0_ns]))
    t = t0_ns + np.round(np.arange(cam.resolution[1]) * cam.line_time_s * 1e9).astype(np.int64)
    return interpolate_poses(fused.t_ns, fused.p_w + offset, fused.q_wxyz, t)


def _camera_rows(body: tuple[np.ndarray, np.ndarray], cam: CameraCalib,
                 rows: int) -> tuple[np.ndarray, np.ndarray]:
    """``cam``'s row poses from ``_body_rows``' ``body``: (H,3,3), (H,3); a global
    shutter's one pose repeated ``rows`` times (the rendered image's height)."""
    p_w, R_w = body
    if len(p_w) == 1:
        return camera_row_poses(R_w.repeat(rows, 0), p_w.repeat(rows, 0), cam.T_b_c)
    return camera_row_poses(R_w, p_w, cam.T_b_c)


def _write_inertial(src: Path, mav0: Path, imu, fused, offset: np.ndarray, t_ns: np.ndarray,
                    td: int, margin_s: float) -> int:
    """The source's IMU rows (and sensor.yaml) around the frames, the fused trajectory
    (shifted into the room) as ground truth, body.yaml; returns the IMU rows written."""
    (mav0 / "imu0").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "imu0" / "sensor.yaml", mav0 / "imu0" / "sensor.yaml")
    margin = int(round(margin_s * 1e9))
    lo, hi = min(t_ns[0], t_ns[0] + td) - margin, max(t_ns[-1], t_ns[-1] + td) + margin
    imu.write_slice(mav0 / "imu0" / "data.csv", lo, hi)
    write_groundtruth(mav0 / GT_DIR, fused.t_ns, fused.p_w + offset, fused.q_wxyz, fused.v_w,
                      fused.bg, fused.ba)
    write_body_yaml(mav0)
    return int(np.count_nonzero((imu.t_ns >= lo) & (imu.t_ns <= hi)))
