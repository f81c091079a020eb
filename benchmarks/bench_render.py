"""Render speed of ``vio sim``: seconds per image and the projected time for 10 s of stereo.

    python benchmarks/bench_render.py [--frames 40] [--scale 1.0] [--line-time 3e-5] [--full]

Prints the one-off costs (world build = scene + textures, numba first call) and the
per-image costs (ray casting/texturing, exposure + noise, PNG write). ``--full`` also
times ``simulate`` end to end for 10 s of stereo in a temporary folder.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vio.sim import SimConfig, build_world, render_frame, row_times, simulate  # noqa: E402
from vio.sim.render import photometric  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--line-time", type=float, default=3e-5)
    ap.add_argument("--full", action="store_true", help="also time simulate() for 10 s stereo")
    args = ap.parse_args()
    cfg = SimConfig(seconds=10.0, image_scale=args.scale, line_time_s=args.line_time)

    t = time.perf_counter()
    world = build_world(cfg)
    t_world = time.perf_counter() - t
    cam = world.cameras[0]
    t = time.perf_counter()
    render_frame(world, cam, row_times(cfg, cfg.t0_ns, cam.height))
    t_first = time.perf_counter() - t

    rng = np.random.default_rng(0)
    t_render = t_photo = t_png = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for j in range(args.frames):
            stamp = cfg.t0_ns + int(j * 10e9 / max(args.frames, 1))
            t0 = time.perf_counter()
            rad, _ = render_frame(world, cam, row_times(cfg, stamp, cam.height))
            t1 = time.perf_counter()
            img = photometric(rad, 0.1, 2.0, cfg.image_noise_sigma, rng)
            t2 = time.perf_counter()
            cv2.imwrite(str(Path(tmp) / f"{j}.png"), img)
            t3 = time.perf_counter()
            t_render, t_photo, t_png = t_render + t1 - t0, t_photo + t2 - t1, t_png + t3 - t2
    n = max(args.frames, 1)
    per_image = (t_render + t_photo + t_png) / n
    print(f"resolution {cam.width}x{cam.height}, line time {cfg.line_time_s:g} s, "
          f"{world.atlas.data.size / 1e6:.1f} M texels")
    print(f"world build (scene + textures): {t_world:.2f} s; first render (numba load/compile): {t_first:.2f} s")
    print(f"per image: render {t_render / n * 1e3:.1f} ms, exposure+noise {t_photo / n * 1e3:.1f} ms, "
          f"PNG {t_png / n * 1e3:.1f} ms, total {per_image * 1e3:.1f} ms")
    projected = t_world + 400 * per_image
    print(f"projected 10 s stereo (200 frames x 2 images): {projected:.1f} s (goal < 60 s)")
    if args.full:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            res = simulate(Path(tmp), cfg)
            print(f"measured simulate() 10 s stereo: {time.perf_counter() - t:.1f} s "
                  f"({res.n_frames} frames, {res.n_imu} IMU samples)")


if __name__ == "__main__":
    main()
