"""``vio tracks SRC OUT``: synthetic feature tracks from a real IMU + ground-truth sequence.

Settings come from ``TrackGenConfig`` defaults, then ``--variant NAME`` (a named other
generator, ``vio.sim.variants.VARIANTS``), then ``--config FILE`` (YAML with TrackGenConfig
keys, strict), then the individual options below.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from vio.config import from_dict, read_yaml
from vio.errors import ConfigError, DataError
from vio.sim.tracks import TrackGenConfig, generate_tracks
from vio.sim.variants import VARIANTS

# option dest -> TrackGenConfig field
_OVERRIDES = {"start": "start_s", "seconds": "duration_s", "td": "td_s", "seed": "seed",
              "noise_px": "noise_px", "outliers": "outlier_rate", "max_features": "max_features",
              "track_len": "mean_track_len", "persistent": "persistent_fraction"}


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``tracks`` subcommand; sets ``func=run`` as the handler."""
    p = subparsers.add_parser(
        "tracks", help="generate feature tracks from real IMU + ground truth",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path,
                   help="EuRoC folder (mav0/ with imu0, ground truth, cam0/sensor.yaml)")
    p.add_argument("out", type=Path, help="output folder (writes OUT/mav0, OUT/sim_truth.yaml)")
    p.add_argument("--variant", choices=sorted(VARIANTS),
                   help="a named generator variant (default: ours); --config and options override it")
    p.add_argument("--config", type=Path, help="YAML file with TrackGenConfig keys")
    p.add_argument("--start", type=float, help="excerpt start, s after the first GT row")
    p.add_argument("--seconds", type=float, help="excerpt duration, s (default: to the end)")
    p.add_argument("--td", type=float, help="camera-IMU offset td, s (exposure = stamp + td)")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--noise-px", type=float, help="isotropic pixel noise sigma, px")
    p.add_argument("--outliers", type=float, help="outlier fraction of observations, e.g. 0.015")
    p.add_argument("--max-features", type=int, help="cap on features per frame")
    p.add_argument("--track-len", type=float, help="mean lifetime of the tracks lost early, frames")
    p.add_argument("--persistent", type=float,
                   help="fraction of tracks kept until their point leaves the view (default 0.5)")
    p.set_defaults(func=run)
    return p


def config_from_args(args: argparse.Namespace) -> TrackGenConfig:
    """Defaults <- ``--variant`` <- ``--config`` file <- explicit options (strict: bad values
    raise ConfigError)."""
    variant = dict(VARIANTS[args.variant]) if getattr(args, "variant", None) else {}
    if args.config:
        data = read_yaml(args.config) or {}
        cfg = from_dict(TrackGenConfig, {**variant, **data} if isinstance(data, dict) else data,
                        str(args.config))
    else:
        cfg = from_dict(TrackGenConfig, variant, f"variant {args.variant}")
    over = {f: getattr(args, a) for a, f in _OVERRIDES.items() if getattr(args, a, None) is not None}
    if not over:
        return cfg
    base = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}
    return from_dict(TrackGenConfig, {**base, **over}, "command line")


def run(args: argparse.Namespace) -> int:
    """Generate the dataset and print a summary; 0 on success, 2 on bad input."""
    try:
        cfg = config_from_args(args)
        t0 = time.perf_counter()
        res = generate_tracks(args.src, args.out, cfg)
    except (ConfigError, DataError) as exc:
        print(f"vio tracks: error: {exc}", file=sys.stderr)
        return 2
    fpf, tl = res.features_per_frame, res.track_lengths
    print(f"wrote {res.out / 'mav0'}: {len(res.t_ns)} frames "
          f"({(res.t_ns[-1] - res.t_ns[0]) * 1e-9:.1f} s), {len(res.frame_idx)} observations, "
          f"{len(res.landmark_ids)} track ids on {res.n_points} room points")
    print(f"features/frame mean {fpf.mean():.1f} min {fpf.min()} max {fpf.max()}; track length "
          f"mean {tl.mean():.1f} median {np.median(tl):.0f} max {tl.max()}; outliers "
          f"{np.count_nonzero(res.outlier_kind)}; td {res.td_ns * 1e-9:+.4f} s; "
          f"{time.perf_counter() - t0:.2f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Standalone entry: ``python -m vio.sim.tracks_cli tracks SRC OUT ...``."""
    parser = argparse.ArgumentParser(prog="vio")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
