"""TUM-VI-like synthetic sequences: equidistant (Kannala-Brandt) fisheye cameras at
512x512 in the TUM-VI folder layout.

Layout written to ``out_dir``::

    mav0/cam0/{data.csv, data/*.png}, mav0/cam1/...   (no sensor.yaml, as in TUM-VI)
    mav0/imu0/data.csv
    mav0/mocap0/data.csv          ground truth: t, p_w (m), q_wxyz of the IMU
    dso/camchain.yaml             Kalibr: pinhole + equidistant, T_cam_imu, T_cn_cnm1
    dso/imu_config.yaml           Kalibr IMU noise
    sim_truth.yaml

Each fisheye image is the world's pinhole render (same pose, ``HALF_FOV_DEG`` half
field of view) resampled through the equidistant model; rays beyond that field of
view are black, like the dark border of TUM-VI's lenses. Same world, IMU and clocks
as ``vio.sim.simulate`` (global shutter).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np

from vio.io.kalibr import write_camchain, write_kalibr_imu
from vio.io.types import CameraCalib, ImuCalib
from vio.sim import (SimConfig, _prepare, _quats_wxyz, build_world, frame_stamps, imu_stamps,
                     render_frame, row_times)
from vio.sim.imu import simulate_imu
from vio.sim.render import exposure_sequence, photometric
from vio.sim.writer import CAM_HEADER, GT_HEADER, write_imu, write_truth_yaml

HALF_FOV_DEG = 65.0
# TUM-VI-like 512x512 equidistant intrinsics (fx, fy, cx, cy) and k1..k4
FISHEYE = {"cam0": ((190.98, 190.97, 254.93, 256.90), (0.0034, 0.0007, -0.0021, 0.0002)),
           "cam1": ((190.44, 190.43, 252.60, 254.92), (0.0034, 0.0017, -0.0027, 0.0003))}


def fisheye_camera(pin: CameraCalib) -> CameraCalib:
    """The TUM-VI-like fisheye camera at the pose of a simulator camera."""
    k, d = FISHEYE[pin.name]
    return CameraCalib(pin.T_b_c, k, "equidistant", d, (512, 512), pin.rate_hz, 0.0, pin.name)


def _theta(theta_d: np.ndarray, D: tuple[float, ...]) -> np.ndarray:
    """Invert ``theta_d = theta (1 + k1 th^2 + k2 th^4 + k3 th^6 + k4 th^8)`` (Newton)."""
    k1, k2, k3, k4 = D
    th = theta_d.copy()
    for _ in range(20):
        t2 = th * th
        f = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        th -= f / df
    return th


def pinhole_for(fish: CameraCalib, half_fov_deg: float = HALF_FOV_DEG) -> tuple[CameraCalib, np.ndarray, np.ndarray]:
    """The pinhole camera to render (same pose and centre resolution) and the remap
    tables (H, W) float32 from fisheye pixels to its pixels (-1 beyond the FOV)."""
    fx, fy, cx, cy = fish.intrinsics
    w, h = fish.resolution
    th_max = math.radians(half_fov_deg)
    f = 0.5 * (fx + fy) * 0.8
    half = int(math.ceil(f * math.tan(th_max))) + 2
    pin = CameraCalib(fish.T_b_c, (f, f, half, half), "none", (), (2 * half + 1, 2 * half + 1),
                      fish.rate_hz, 0.0, fish.name)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    mx, my = (u - cx) / fx, (v - cy) / fy
    th_d = np.hypot(mx, my)
    th = _theta(th_d, fish.distortion)
    scale = np.where(th_d > 1e-12, np.tan(np.minimum(th, 1.5)) / np.maximum(th_d, 1e-12), 1.0)
    map_x, map_y = f * mx * scale + half, f * my * scale + half
    outside = th > th_max
    map_x[outside] = map_y[outside] = -1.0
    return pin, map_x.astype(np.float32), map_y.astype(np.float32)


def _write_csv(path: Path, header: str, t_ns: np.ndarray, values: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [header] + [f"{int(t)}," + ",".join(f"{x:.12g}" for x in row) for t, row in zip(t_ns, values)]
    path.write_text("\n".join(rows) + "\n")


def simulate_tumvi(out_dir: str | Path, cfg: SimConfig = SimConfig(), overwrite: bool = False) -> Path:
    """Render a TUM-VI-like fisheye sequence into ``out_dir`` (see module docstring)."""
    cfg = dataclasses.replace(cfg, line_time_s=0.0)
    out_dir = Path(out_dir)
    mav0 = _prepare(out_dir, overwrite)
    world = build_world(cfg)
    t_imu = imu_stamps(cfg)
    imu = simulate_imu(world.trajectory, (t_imu - cfg.t0_ns) * 1e-9, cfg)
    write_imu(mav0 / "imu0", t_imu, imu.gyro, imu.accel)
    s = world.trajectory.sample((t_imu - cfg.t0_ns) * 1e-9)
    gt_header = ",".join(GT_HEADER.split(",")[:8])
    _write_csv(mav0 / "mocap0" / "data.csv", gt_header, t_imu, np.hstack([s.p_w, _quats_wxyz(s.R_w_b)]))
    stamps = frame_stamps(cfg, t_imu)
    fishes = [fisheye_camera(c) for c in world.cameras]
    for k, fish in enumerate(fishes):
        pin, mx, my = pinhole_for(fish)
        rng_e = np.random.default_rng([cfg.seed, 5, k])
        a, b = exposure_sequence(cfg.exposure_changes, (stamps - cfg.t0_ns) * 1e-9, cfg.exposure_log_gain_amp,
                                 cfg.exposure_bias_amp, cfg.exposure_period_s, rng_e)
        cam_dir = mav0 / fish.name
        (cam_dir / "data").mkdir(parents=True)
        for j, st in enumerate(stamps):
            radiance, _ = render_frame(world, pin, row_times(cfg, int(st), pin.height))
            img = cv2.remap(radiance, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            img = photometric(img, a[j], b[j], cfg.image_noise_sigma, np.random.default_rng([cfg.seed, 6, j, k]))
            img[mx < 0] = 0
            cv2.imwrite(str(cam_dir / "data" / f"{int(st)}.png"), img)
        (cam_dir / "data.csv").write_text("\n".join([CAM_HEADER] + [f"{int(t)},{int(t)}.png" for t in stamps]) + "\n")
    dso = out_dir / "dso"
    dso.mkdir(exist_ok=True)
    write_camchain(dso / "camchain.yaml", fishes, td_s=0.0)
    write_kalibr_imu(dso / "imu_config.yaml", ImuCalib(cfg.gyro_noise_density, cfg.gyro_random_walk,
                                                       cfg.accel_noise_density, cfg.accel_random_walk,
                                                       cfg.imu_rate_hz))
    write_truth_yaml(out_dir / "sim_truth.yaml", {"seed": cfg.seed, "td_s": cfg.td_s, "t0_ns": cfg.t0_ns,
                                                  "layout": "TUM-VI (equidistant fisheye 512x512, mocap0)",
                                                  "half_fov_deg": HALF_FOV_DEG, "n_frames": int(len(stamps))})
    return out_dir
