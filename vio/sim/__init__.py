"""Synthetic EuRoC/ASL datasets: a textured room rendered along a smooth 6-DoF path.

``simulate(out_dir, cfg)`` writes ``out_dir/mav0`` (cam0[, cam1] PNGs, imu0,
state_groundtruth_estimate0, body.yaml) plus ``out_dir/sim_truth.yaml`` and
``out_dir/exposure.csv``. Clocks: IMU and ground truth are stamped in the IMU clock;
a written image stamp ``s`` was exposed at ``s + td`` (row r at ``s + td + r * line_time``).
Everything is deterministic for ``cfg.seed``.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from vio.config import to_dict
from vio.conventions import quat_wxyz_from_rot
from vio.io.types import CameraCalib
from vio.sim.config import SimConfig
from vio.sim.imu import ImuSim, simulate_imu
from vio.sim.render import camera_row_poses, exposure_sequence, photometric, render, sim_camera
from vio.sim.scene import Scene, build_scene
from vio.sim.texture import TextureAtlas, build_textures
from vio.sim.trajectory import Trajectory, make_trajectory
from vio.sim.writer import (CameraWriter, write_body_yaml, write_exposure_csv, write_groundtruth,
                            write_imu, write_imu_yaml, write_truth_yaml)

__all__ = ["SimConfig", "SimResult", "SimWorld", "build_world", "simulate", "frame_stamps",
           "row_times", "render_frame"]


@dataclass(frozen=True)
class SimResult:
    """What ``simulate`` wrote: folder paths and counts."""

    out_dir: Path
    mav0: Path
    truth_path: Path
    exposure_path: Path
    cameras: tuple[str, ...]
    n_frames: int
    n_imu: int


@dataclass(frozen=True)
class SimWorld:
    """The deterministic world of a config: trajectory, scene, textures, cameras."""

    cfg: SimConfig
    trajectory: Trajectory
    scene: Scene
    atlas: TextureAtlas
    cameras: tuple[CameraCalib, ...]


def build_world(cfg: SimConfig) -> SimWorld:
    """Trajectory, scene (obstacles clear of the path), textures and cameras of ``cfg``."""
    traj = make_trajectory(cfg)
    scene = build_scene(cfg, traj)
    atlas = build_textures(scene, cfg.texels_per_m, cfg.seed)
    names = ("cam0", "cam1") if cfg.stereo else ("cam0",)
    cams = tuple(sim_camera(n, cfg.image_scale, cfg.cam_rate_hz, cfg.line_time_s) for n in names)
    return SimWorld(cfg, traj, scene, atlas, cams)


def imu_stamps(cfg: SimConfig) -> np.ndarray:
    """IMU (and ground-truth) stamps (N,) int64 ns covering ``cfg.seconds``."""
    n = int(np.floor(cfg.seconds * cfg.imu_rate_hz + 1e-9)) + 1
    return cfg.t0_ns + np.round(np.arange(n) * (1e9 / cfg.imu_rate_hz)).astype(np.int64)


def frame_stamps(cfg: SimConfig, t_imu_ns: np.ndarray) -> np.ndarray:
    """Written image stamps (M,) int64 ns on a ``cam_rate_hz`` grid from ``t0_ns``, keeping
    frames whose stamp and whole exposure (``stamp + td + [0, (H-1) line_time]``) lie
    inside the IMU span."""
    period = round(1e9 / cfg.cam_rate_hz)
    lo, hi = int(t_imu_ns[0]), int(t_imu_ns[-1])
    stamps = cfg.t0_ns + period * np.arange((hi - cfg.t0_ns) // period + 1, dtype=np.int64)
    readout = round(cfg.readout_s * 1e9)
    start = stamps + round(cfg.td_s * 1e9)
    keep = (stamps >= lo) & (stamps <= hi) & (start >= lo) & (start + readout <= hi)
    return stamps[keep]


def row_times(cfg: SimConfig, stamp_ns: int, height: int) -> np.ndarray:
    """Exposure time (seconds since ``t0_ns``, IMU clock) of each image row (H,)."""
    t = (int(stamp_ns) - cfg.t0_ns) * 1e-9 + cfg.td_s
    return t + np.arange(height) * cfg.line_time_s


def render_frame(world: SimWorld, cam: CameraCalib, t_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radiance and depth (H, W) float32 of ``cam`` with row r seen at ``t_rows[r]``."""
    if np.all(t_rows == t_rows[0]):
        s = world.trajectory.sample(t_rows[:1])
        R, p = s.R_w_b.repeat(len(t_rows), 0), s.p_w.repeat(len(t_rows), 0)
    else:
        s = world.trajectory.sample(t_rows)
        R, p = s.R_w_b, s.p_w
    return render(world.scene, world.atlas, cam, *camera_row_poses(R, p, cam.T_b_c))


def _quats_wxyz(R: np.ndarray) -> np.ndarray:
    """(N,4) unit quaternions (w, x, y, z), w >= 0, of rotation matrices (N,3,3)."""
    return np.array([quat_wxyz_from_rot(gtsam.Rot3(r)) for r in R]).reshape(-1, 4)


def _write_inertial(world: SimWorld, mav0: Path, t_ns: np.ndarray) -> ImuSim:
    cfg = world.cfg
    t_s = (t_ns - cfg.t0_ns) * 1e-9
    imu = simulate_imu(world.trajectory, t_s, cfg)
    write_imu(mav0 / "imu0", t_ns, imu.gyro, imu.accel)
    write_imu_yaml(mav0 / "imu0" / "sensor.yaml", cfg.imu_rate_hz,
                   (cfg.gyro_noise_density, cfg.gyro_random_walk,
                    cfg.accel_noise_density, cfg.accel_random_walk))
    s = world.trajectory.sample(t_s)
    write_groundtruth(mav0 / "state_groundtruth_estimate0", t_ns, s.p_w, _quats_wxyz(s.R_w_b),
                      s.v_w, imu.bg, imu.ba)
    return imu


def _prepare(out_dir: Path, overwrite: bool) -> Path:
    mav0 = out_dir / "mav0"
    if mav0.exists():
        if not overwrite:
            raise FileExistsError(f"{mav0} exists; pass overwrite=True (--force) to replace it")
        shutil.rmtree(mav0)
    mav0.mkdir(parents=True)
    return mav0


def simulate(out_dir: Path, cfg: SimConfig, progress: bool = False,
             overwrite: bool = False) -> SimResult:
    """Render and write one synthetic EuRoC sequence to ``out_dir`` (see module doc)."""
    out_dir = Path(out_dir)
    mav0 = _prepare(out_dir, overwrite)
    world = build_world(cfg)
    write_body_yaml(mav0)
    t_imu = imu_stamps(cfg)
    _write_inertial(world, mav0, t_imu)
    stamps = frame_stamps(cfg, t_imu)
    t_frames = (stamps - cfg.t0_ns) * 1e-9
    exposure = {}
    for k, cam in enumerate(world.cameras):
        rng = np.random.default_rng([cfg.seed, 5, k])
        exposure[cam.name] = exposure_sequence(cfg.exposure_changes, t_frames, cfg.exposure_log_gain_amp,
                                               cfg.exposure_bias_amp, cfg.exposure_period_s, rng)
    writers = [CameraWriter(mav0 / cam.name, cam) for cam in world.cameras]
    frames = range(len(stamps) if cfg.render_images else 0)
    if progress:
        from tqdm import tqdm
        frames = tqdm(frames, desc="vio sim", unit="frame")
    for j in frames:
        for k, (cam, wr) in enumerate(zip(world.cameras, writers)):
            radiance, _ = render_frame(world, cam, row_times(cfg, int(stamps[j]), cam.height))
            a, b = exposure[cam.name][0][j], exposure[cam.name][1][j]
            rng = np.random.default_rng([cfg.seed, 6, j, k])
            wr.add(int(stamps[j]), photometric(radiance, a, b, cfg.image_noise_sigma, rng))
    for wr in writers:
        wr.close(f"vio sim {wr.calib.name} (EuRoC MT9V034 intrinsics and T_BS, zero distortion)")
    exposure_path = out_dir / "exposure.csv"
    write_exposure_csv(exposure_path, stamps, exposure)
    truth_path = out_dir / "sim_truth.yaml"
    write_truth_yaml(truth_path, {
        "seed": cfg.seed, "td_s": cfg.td_s, "line_time_s": cfg.line_time_s, "t0_ns": cfg.t0_ns,
        "convention": "image stamp + td = exposure time of row 0 (IMU clock); "
                      "row r at stamp + td + r * line_time_s",
        "gravity_w": [0.0, 0.0, -cfg.gravity],
        "exposure_model": "image = clip(exp(a) * radiance + b + noise)",
        "exposure_file": exposure_path.name,
        "n_frames": int(len(stamps)), "n_imu": int(len(t_imu)),
        "scene": world.scene.describe(),
        "config": to_dict(cfg),
    })
    return SimResult(out_dir, mav0, truth_path, exposure_path,
                     tuple(c.name for c in world.cameras), int(len(stamps)), int(len(t_imu)))
