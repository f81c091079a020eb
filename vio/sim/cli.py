"""``vio sim OUT``: write a synthetic EuRoC/ASL dataset (see ``vio.sim``).

Options given on the command line override the ``--config`` YAML (a ``SimConfig``
mapping, optionally under a top-level ``sim:`` section), which overrides the defaults.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from vio.config import from_dict, read_yaml
from vio.errors import ConfigError
from vio.sim.config import SimConfig

# CLI flag destination -> SimConfig field
_FIELDS = {"seconds": "seconds", "seed": "seed", "td": "td_s", "line_time": "line_time_s",
           "stereo": "stereo", "exposure": "exposure_changes", "scale": "image_scale",
           "image_noise": "image_noise_sigma", "speed": "speed_mps", "motion": "motion"}


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``sim`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser(
        "sim", help="render a synthetic EuRoC-format dataset (textured room, IMU, ground truth)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="output folder (mav0/ and sim_truth.yaml go here)")
    p.add_argument("--config", type=Path, help="YAML with SimConfig keys (optionally under 'sim:')")
    p.add_argument("--seconds", type=float, help="duration in seconds (default 10)")
    p.add_argument("--seed", type=int, help="random seed: scene, path, textures, noise (default 0)")
    p.add_argument("--td", type=float, help="camera-IMU offset td in s: stamp + td = exposure (default 0)")
    p.add_argument("--line-time", type=float, dest="line_time",
                   help="rolling-shutter line time in s (default 0 = global shutter)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--stereo", dest="stereo", action="store_const", const=True, help="cam0 + cam1 (default)")
    g.add_argument("--mono", dest="stereo", action="store_const", const=False, help="cam0 only")
    p.add_argument("--exposure", choices=("none", "smooth", "step"),
                   help="per-frame affine brightness changes (default none)")
    p.add_argument("--scale", type=float, help="image scale of the 752x480 EuRoC resolution (default 1)")
    p.add_argument("--image-noise", type=float, dest="image_noise", help="pixel noise sigma, gray levels")
    p.add_argument("--speed", type=float, help="mean speed in m/s (default 0.7)")
    p.add_argument("--motion", choices=("loop", "constant_velocity"),
                   help="loop (default: perturbed ellipse, IMU excitation) or constant_velocity "
                        "(a straight pass, acceleration ~0.03 m/s^2 RMS; the room is lengthened to fit)")
    p.add_argument("--noise-free", action="store_true",
                   help="no IMU white noise, no bias random walk, no pixel noise")
    p.add_argument("--no-images", action="store_true",
                   help="write IMU, ground truth and calibration only (e.g. for `vio tracks`)")
    p.add_argument("--tumvi", action="store_true",
                   help="TUM-VI layout: equidistant fisheye 512x512, mocap0, dso/ Kalibr files")
    p.add_argument("--flight", type=Path, metavar="SRC",
                   help="render along a real flight instead: SRC's real IMU and ground truth "
                        "(an EuRoC folder with imu0 and state_groundtruth_estimate0, e.g. "
                        "euroc_imu_gt/MH_05_difficult), the room sized to it (vio.sim.flight)")
    p.add_argument("--start", type=float, default=0.0,
                   help="with --flight: seconds after the first ground-truth row (default 0)")
    p.add_argument("--distort", action="store_true",
                   help="with --flight: SRC's own camera calibrations, rendered through their distortion")
    p.add_argument("--blur-ms", type=float, default=0.0, dest="blur_ms",
                   help="with --flight: exposure duration rendered as motion blur (ms, default 0)")
    p.add_argument("--force", action="store_true", help="replace an existing OUT/mav0")
    p.add_argument("--progress", action="store_true", help="show a progress bar")
    p.set_defaults(func=run)
    return p


def config_from_args(args: argparse.Namespace) -> SimConfig:
    """Defaults <- ``--config`` file <- explicit flags."""
    data: dict = {}
    if getattr(args, "config", None) is not None:
        loaded = read_yaml(args.config) or {}
        if not isinstance(loaded, dict):
            raise ConfigError(f"{args.config}: expected a mapping of SimConfig keys")
        data = dict(loaded.get("sim", loaded) or {})
    for flag, key in _FIELDS.items():
        value = getattr(args, flag, None)
        if value is not None:
            data[key] = value
    if getattr(args, "noise_free", False):
        data.update(imu_noise=False, image_noise_sigma=0.0)
    if getattr(args, "no_images", False):
        data["render_images"] = False
    if data.get("motion") == "constant_velocity" and "room_size" not in data:
        data["room_size"] = _pass_room(data)
    return from_dict(SimConfig, data, str(args.config) if getattr(args, "config", None) else "command line")


def _pass_room(data: dict) -> list[float]:
    """The default room lengthened along x for a straight pass of ``data``'s duration
    and speed (``SimConfig.motion == "constant_velocity"``)."""
    d = SimConfig()
    need = (data.get("speed_mps", d.speed_mps) * data.get("seconds", d.seconds)
            + 2 * data.get("wall_margin_m", d.wall_margin_m) + 0.5)
    return [max(d.room_size[0], need), d.room_size[1], d.room_size[2]]


def run(args: argparse.Namespace) -> int:
    """Execute ``vio sim``; returns the process exit code."""
    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        print(f"vio sim: {exc}", file=sys.stderr)
        return 2
    from vio.sim import simulate

    t0 = time.perf_counter()
    if getattr(args, "flight", None) is not None:
        return _run_flight(args, cfg, t0)
    if getattr(args, "tumvi", False):
        from vio.sim.fisheye import simulate_tumvi
        try:
            simulate_tumvi(args.out, cfg, overwrite=getattr(args, "force", False))
        except (FileExistsError, OSError) as exc:
            print(f"vio sim: {exc}", file=sys.stderr)
            return 1
        print(f"vio sim: wrote a TUM-VI-like fisheye sequence to {args.out} in {time.perf_counter() - t0:.1f} s")
        return 0
    try:
        res = simulate(args.out, cfg, progress=getattr(args, "progress", False),
                       overwrite=getattr(args, "force", False))
    except (FileExistsError, OSError) as exc:
        print(f"vio sim: {exc}", file=sys.stderr)
        return 1
    dt = time.perf_counter() - t0
    print(f"vio sim: wrote {res.mav0} ({'+'.join(res.cameras)}, {res.n_frames} frames, "
          f"{res.n_imu} IMU samples) and {res.truth_path.name} in {dt:.1f} s")
    return 0


def _run_flight(args: argparse.Namespace, cfg: SimConfig, t0: float) -> int:
    """``vio sim OUT --flight SRC``: images along SRC's real flight (``vio.sim.flight``).
    ``--seconds`` (None: to the end of the flight), ``--td``, ``--seed``, ``--mono`` /
    ``--stereo``, ``--scale`` (undistorted cameras), ``--exposure``, ``--image-noise``,
    ``--distort``, ``--blur-ms`` and ``--line-time`` apply; the motion options do not."""
    from vio.errors import DataError
    from vio.sim.flight import render_flight
    from vio.sim.optics import FlightOptics
    from vio.sim.tracks_config import TrackGenConfig

    seconds = getattr(args, "seconds", None)
    try:
        tcfg = TrackGenConfig(start_s=args.start, duration_s=seconds, td_s=cfg.td_s, seed=cfg.seed,
                              rate_hz=cfg.cam_rate_hz)
        optics = FlightOptics(distortion=getattr(args, "distort", False),
                              blur_s=getattr(args, "blur_ms", 0.0) * 1e-3)
        res = render_flight(args.flight, args.out, tcfg, cfg, optics, progress=getattr(args, "progress", False),
                            overwrite=getattr(args, "force", False))
    except (FileExistsError, OSError, ValueError, DataError) as exc:
        print(f"vio sim: {exc}", file=sys.stderr)
        return 1
    print(f"vio sim: wrote {res.mav0} ({'+'.join(res.cameras)}, {res.n_frames} frames along "
          f"{args.flight}'s flight, {res.n_imu} real IMU samples) and {res.truth_path.name} in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point (``python -m vio.sim.cli OUT ...``)."""
    parser = argparse.ArgumentParser(prog="vio")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["sim", *(argv if argv is not None else sys.argv[1:])])
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
