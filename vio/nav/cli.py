"""Command-line glue for the navigation extras: ``vio plan`` and ``smooth_file``.

``vio plan MAP START GOAL`` builds an occupancy grid from a map file written by
``vio.nav.grid.save_map`` (``vio run`` saves one), runs A* between two plane
points given as ``"u,v"`` metres (``x,y`` for the default z-up world) and prints
a summary; ``--out`` writes the path as CSV, ``--rrd`` records grid and path to a
Rerun file (no viewer needed). Negative coordinates need ``--`` first, as in
``vio plan map.npz -- -1.5,2 3,0.5``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from vio.config import load
from vio.errors import ConfigError, DataError
from vio.nav.astar import AStarConfig, PlanResult, astar_grid, plan
from vio.nav.grid import GridConfig, OccupancyGrid, load_map, plane_split
from vio.nav.kalman import KalmanConfig, SmoothedTrack, apply_planar, read_tum, smooth_track, write_tum


def _parse_xy(text: str) -> tuple[float, float]:
    try:
        u, v = (float(s) for s in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'x,y' in metres, got {text!r}") from None
    if not (np.isfinite(u) and np.isfinite(v)):
        raise argparse.ArgumentTypeError(f"non-finite coordinate {text!r}")
    return u, v


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``plan`` sub-command (``func=run_plan``) on a ``vio`` sub-parser set."""
    p = subparsers.add_parser("plan", help="A* path on a saved landmark map",
                              description=__doc__.split("\n\n")[1].replace("``", ""))
    p.add_argument("map", type=Path, help="map .npz written by vio run (save_map)")
    p.add_argument("start", type=_parse_xy, help="start 'x,y' on the ground plane [m]")
    p.add_argument("goal", type=_parse_xy, help="goal 'x,y' on the ground plane [m]")
    p.add_argument("--grid-config", type=Path, help="YAML with GridConfig keys (flags override it)")
    p.add_argument("--resolution", type=float, help="cell size [m]")
    p.add_argument("--z-min", type=float, help="obstacle band bottom above the floor [m]")
    p.add_argument("--z-max", type=float, help="obstacle band top above the floor [m]")
    p.add_argument("--floor", type=float, help="floor height [m] (default: estimated from the points)")
    p.add_argument("--inflate", type=float, help="robot radius for obstacle inflation [m]")
    p.add_argument("--engine", choices=("auto", "numba", "python"), default="auto")
    p.add_argument("--out", type=Path, help="write the path to this CSV (columns u,v in metres)")
    p.add_argument("--rrd", type=Path, help="record grid and path to this Rerun .rrd file")
    p.set_defaults(func=run_plan)


def _grid_config(args: argparse.Namespace) -> GridConfig:
    base = load(GridConfig, args.grid_config) if args.grid_config else GridConfig()
    over = {"resolution": args.resolution, "z_min": args.z_min, "z_max": args.z_max,
            "floor_height": args.floor, "robot_radius": args.inflate}
    kw = {k: v for k, v in over.items() if v is not None}
    return dataclasses.replace(base, **kw)


def run_plan(args: argparse.Namespace) -> int:
    """Run ``vio plan``; 0 when a path is found, 1 when not, 2 on bad input."""
    try:
        cfg = _grid_config(args)
        m = load_map(args.map)
        traj_uv, _ = plane_split(m.trajectory_xyz, cfg.plane_axes)
        extra = np.vstack([traj_uv, np.array([args.start, args.goal])])
        grid = OccupancyGrid.from_points(m.points_w, cfg, extra_uv=extra)
    except (DataError, ConfigError, ValueError) as exc:
        print(f"vio plan: error: {exc}", file=sys.stderr)
        return 2
    acfg = AStarConfig(engine=args.engine)
    astar_grid(np.zeros((2, 2), bool), (0, 0), (1, 1), acfg)  # load the JIT cache outside the timing
    t0 = time.perf_counter()
    res = plan(grid, args.start, args.goal, acfg)
    dt = time.perf_counter() - t0
    H, W = grid.shape
    print(f"map      {args.map}: {len(m.points_w)} landmarks, {len(m.trajectory_xyz)} trajectory poses")
    print(f"grid     {H}x{W} cells @ {grid.resolution:.3f} m, floor {grid.floor_height:+.3f} m, band "
          f"[{cfg.z_min:.2f}, {cfg.z_max:.2f}] m, occupied {grid.occupied.mean():.1%}, "
          f"blocked after {cfg.robot_radius:.2f} m inflation {grid.blocked.mean():.1%}")
    print(f"plan     {args.start} -> {args.goal}: {res.reason}; expanded {res.expanded} in {dt * 1e3:.1f} ms")
    if res.found:
        print(f"path     {len(res.path_cells)} cells, length {res.cost:.3f} m")
        if args.out:
            write_path_csv(args.out, res, cfg.plane_axes)
            print(f"wrote    {args.out}")
    elif args.out:
        print(f"not writing {args.out}: no path")
    if args.rrd:
        from vio.viz import log_plan
        log_plan(args.rrd, grid, res, m)
        print(f"wrote    {args.rrd}")
    return 0 if res.found else 1


def write_path_csv(path: Path, res: PlanResult, plane_axes: tuple[str, str] = ("x", "y")) -> None:
    """CSV with a header naming the plane axes, one row per path cell centre [m]."""
    header = f"{plane_axes[0]},{plane_axes[1]}"
    np.savetxt(path, res.path_world, delimiter=",", header=header, comments="", fmt="%.6f")


def smooth_file(traj_in: Path, traj_out: Path, cfg: KalmanConfig = KalmanConfig()) -> SmoothedTrack:
    """Smooth a TUM trajectory's planar pose (``vio run --smooth``) and write it as TUM.

    The ground-plane position and the heading come from the RTS smoother; the
    off-plane coordinate and roll/pitch are kept from ``traj_in`` (see
    ``vio.nav.kalman.apply_planar``). Returns the smoothed planar track.
    """
    raw = read_tum(traj_in)
    track = smooth_track(raw.t_s, raw.T_w_b, cfg)
    write_tum(traj_out, apply_planar(raw, track, cfg))
    return track
