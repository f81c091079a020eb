"""Command line: ``vio run | sim | tracks | eval | plan | convert | batch``.

Bad input is reported as one line naming the file (and line) with exit code 2;
the CLI never shows a traceback for a user error.
"""

from __future__ import annotations

import argparse
import gc
import logging
import sys
from pathlib import Path

from vio.threads import one_blas_thread

one_blas_thread()   # before numpy loads: one BLAS thread per process (vio.threads)

from vio.config import positive_float, positive_int  # noqa: E402
from vio.errors import ConfigError, DataError  # noqa: E402


def _add_run(sub) -> None:
    p = sub.add_parser("run", help="run the VIO on an EuRoC/ASL/TUM-VI folder, a ROS 1/2 bag (or --demo)")
    p.add_argument("dataset", nargs="?", type=Path,
                   help="EuRoC/ASL folder (contains mav0/), ROS 1 .bag file or ROS 2 bag folder")
    p.add_argument("--demo", action="store_true",
                   help="run on the real EuRoC V1_01 tracks shipped inside the gtsam wheel")
    p.add_argument("--config", type=Path, help="YAML file overriding the defaults")
    p.add_argument("--out", type=Path, help="TUM trajectory output (online estimates)")
    p.add_argument("--smoothed", type=Path, help="also write the window-smoothed trajectory")
    p.add_argument("--max-frames", type=positive_int, default=None, help="only the first N frames")
    p.add_argument("--mode", choices=["auto", "features", "stereo", "mono", "direct", "hybrid"],
                   default="auto")
    p.add_argument("--td", type=float, default=None, help="initial camera-IMU offset td [s]")
    p.add_argument("--trim", action="store_true", help="drop camera frames outside the IMU span")
    p.add_argument("--calib", type=Path, help="Kalibr camchain.yaml (cameras, T_cam_imu, timeshift as td)")
    p.add_argument("--imu-calib", type=Path, help="Kalibr imu.yaml (noise densities, random walks)")
    p.add_argument("--topics", type=lambda s: [t for t in s.split(",") if t],
                   help="bag topics, comma-separated: the IMU and 1-2 cameras (cam0 first)")
    p.add_argument("--groundtruth", type=Path, help="ground truth to evaluate against (TUM file, "
                   "ASL data.csv or a dataset folder); default: the dataset's own")
    p.add_argument("--segments", type=positive_float, metavar="SECONDS",
                   help="with ground truth: the error and scale per stretch of SECONDS (as vio eval)")
    p.add_argument("--map", type=Path, help="save the landmark map (.npz) for `vio plan`")
    p.add_argument("--smooth", type=Path, help="write a Kalman-smoothed planar track (TUM)")
    p.add_argument("--rerun", action="store_true", help="stream to a Rerun viewer")
    p.add_argument("--rrd", type=Path, help="record a Rerun .rrd file")
    p.add_argument("--viz-image-every", type=positive_int, default=3, metavar="N",
                   help="Rerun: log the camera images every N frames (default 3)")
    p.add_argument("--viz-jpeg-quality", type=int, default=60, metavar="Q",
                   help="Rerun: JPEG quality 1-100 of the logged images, 0 for raw (default 60)")
    p.add_argument("--live", action="store_true",
                   help="backend in its own process, frames from IMU propagation (not deterministic)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("-v", "--verbose", action="store_true")


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="ATE/RPE of a TUM trajectory against ground truth (evo)")
    p.add_argument("estimate", type=Path, help="TUM file")
    p.add_argument("groundtruth", type=Path, help="TUM file, EuRoC data.csv or dataset folder")
    p.add_argument("--sim3", action="store_true", help="Sim3 alignment (monocular scale)")
    p.add_argument("--plot", type=Path, help="save a top-view plot (PNG)")
    p.add_argument("--segments", type=positive_float, metavar="SECONDS",
                   help="also per stretch of SECONDS: path, mean error, the estimate's length vs the truth")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The CLI's parser; ``command`` "run" or "eval": only that subcommand (the other
    subcommands' modules, e.g. ``vio batch`` with Ray, took 0.5 s to import before every
    ``vio run``)."""
    parser = argparse.ArgumentParser(prog="vio", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    _add_run(sub)
    _add_eval(sub)
    if command in ("run", "eval"):
        return parser
    from vio.sim import cli as sim_cli
    from vio.sim import tracks_cli
    sim_cli.add_parser(sub)
    tracks_cli.add_parser(sub)
    from vio.nav import cli as nav_cli
    nav_cli.add_parsers(sub)
    from vio import batch
    from vio.io import bag_write
    bag_write.add_parser(sub)
    batch.add_parser(sub)
    return parser


def cmd_eval(args: argparse.Namespace) -> int:
    from vio.evaluation import evaluate_files, segment_lines
    r = evaluate_files(args.estimate, args.groundtruth, args.sim3, args.plot, args.segments)
    print(f"matched poses   {r.n_matched}")
    print(f"path length     {r.path_length:.2f} m")
    print(f"ATE RMSE        {r.ate_rmse:.4f} m ({r.alignment}; mean {r.ate_mean:.4f}, max {r.ate_max:.4f})")
    print(f"RPE trans RMSE  {r.rpe_trans_rmse:.4f} m, rot {r.rpe_rot_rmse_deg:.3f} deg")
    for line in segment_lines(r):
        print(line)
    if args.plot:
        print(f"plot            {args.plot}")
    return 0


def _handlers() -> dict:
    from vio.nav import cli as nav_cli
    from vio.sim import cli as sim_cli
    from vio.sim import tracks_cli
    from vio import batch
    from vio.io import bag_write
    return {"sim": sim_cli.run, "tracks": tracks_cli.run, "plan": nav_cli.run_plan, "convert": bag_write.run,
            "batch": batch.run}


def _prestart_worker(args: argparse.Namespace) -> None:
    """Start the KLT front end's worker process (``vio.overlap.prestart``) before this
    process imports ``vio.run`` and loads the dataset, when the run will use one: a mode
    with the KLT in the worker named, or ``auto`` on a folder with cam0 images and no
    feature tracks. Its start-up (interpreter, OpenCV, Numba: ~0.6 s) then overlaps this
    process's instead of delaying the first frame; unused (a config turning the worker
    off), it is stopped at exit."""
    from vio import overlap
    from vio.modes import KLT_WORKER_MODES
    if not overlap.SUPPORTED or args.demo or getattr(args, "live", False) or args.dataset is None:
        return
    mode = args.mode
    if mode == "auto":
        cam0 = Path(args.dataset) / "mav0" / "cam0"
        mode = "mono" if (cam0 / "data").is_dir() and not (cam0 / "features.csv").exists() else "features"
    if mode in KLT_WORKER_MODES:
        overlap.prestart()


def _run(args: argparse.Namespace) -> int:
    """``vio run``. Its start-up (imports, kernel loads, the dataset) makes long-lived
    objects only: no cyclic collection until the run loop, and the modules' objects frozen
    at once, so the full collection before the loop (``vio.run.run_dataset``) skips them:
    0.12 -> 0.04 s on real MH_05 mono. The collector's state is restored on return."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        _prestart_worker(args)
        from vio.run_cmd import cmd_run
        gc.freeze()
        return cmd_run(args)
    finally:
        gc.unfreeze()
        if enabled:
            gc.enable()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    level = logging.INFO if getattr(args, "verbose", False) else logging.WARNING
    if not logging.getLogger().handlers:   # (else the embedding application configured it)
        logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
        # the console keeps `level` when the Rerun sink lets the vio logger pass INFO
        logging.getLogger().handlers[0].setLevel(level)
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "eval":
            return cmd_eval(args)
        return int(_handlers()[args.command](args))
    except (DataError, ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"vio {args.command}: error: {exc}", file=sys.stderr)
        return 2


def console() -> None:
    """The ``vio`` console script: :func:`main`, then the process ends without Python's last
    cyclic collection over everything the run left behind (imports, kernels, the run's
    objects: ~0.4 s after real MH_05 mono's summary line, now ~0.05 s). Nothing of ours waits
    for that collection: files are closed, sinks and the KLT worker stopped by the time
    ``main`` returns or by the ``atexit`` handlers, which still run. ``main`` itself, called
    in-process by an application or a test, leaves the collector as it found it."""
    rc = main()
    gc.freeze()
    sys.exit(rc)


if __name__ == "__main__":
    console()
