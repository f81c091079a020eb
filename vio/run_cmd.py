"""``vio run``: the command line's run (load the dataset, pick the mode and the configuration,
run it with ``vio.run.run_dataset``, write the trajectory files, print the summary)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from vio.run import PHOTOMETRIC_MODES, STEREO_MODES, RunResult, load_config, resolve_mode, run_dataset
from vio.run_summary import summary
from vio.trajectory import write_tum

# |td estimate - the run's starting offset| (s) from which a mono run suggests rerunning at
# the estimate. Real MH_05 mono from 17 start frames (benchmarks/README.md, stop 48): with its
# stamps 12 ms off 78.75 mm, rerun at the estimate (11.7 ms) 68.93 mm, unmoved 59.32 mm (64.14
# / 68.93 mm with the stamps 0.3 ms either way: the mean's own spread). Stereo's and feature
# mode's ATE do not follow the offset (real MH_01 stereo, real V1_01 tracks).
TD_HINT_S = 0.003


def td_hint(res: RunResult, td0_s: float, mode: str) -> str | None:
    """The summary's note when a monocular run's td estimate ends at least ``TD_HINT_S``
    from the offset its initialization aligned its first seconds at (``td0_s``, s, the
    sync layer's, plus the remainder a dynamic initialization found): the window keeps the
    scale it found there; None otherwise."""
    if mode != "mono" or res.init is None or not res.outputs:
        return None
    td, aligned = float(res.outputs[-1].td_s), td0_s + res.init.td_s
    if not abs(td - aligned) >= TD_HINT_S:
        return None
    return (f"td note         the estimate is {1e3 * (td - aligned):+.1f} ms from the offset this run's "
            f"initialization aligned its first seconds at; the window keeps the scale it found there: for the "
            f"best trajectory rerun with --td {td:.4f}")


def _note_cold_kernels(mode: str) -> None:
    """One line on stderr when the Numba kernels are not compiled yet (first run after an
    install or update): that run spends 20-40 s compiling before its first frame
    (hybrid on 2 cores: 49 s instead of 15 s for real MH_01); later runs load them."""
    from factors.jit import cache_is_warm
    from factors.track_kernel import track_eval
    kernels = [track_eval]
    if mode in PHOTOMETRIC_MODES:
        from factors.photometric_kernel import host_system
        kernels.append(host_system)
    if not all(cache_is_warm(k) for k in kernels):
        print("vio run: compiling the numerical kernels (first run after an install or update, "
              "20-40 s; cached for later runs)", file=sys.stderr)


def _check_outputs(args: argparse.Namespace) -> None:
    """Every output file's folder must exist, and ``--smooth`` have its ``--out``, before the
    run, not only when they are written at its end (a long run's result would be lost)."""
    for flag in ("out", "smoothed", "map", "smooth", "rrd"):
        path = getattr(args, flag, None)
        if path is not None and not Path(path).resolve().parent.is_dir():
            raise ValueError(f"--{flag} {path}: folder {Path(path).parent} does not exist")
    if getattr(args, "smooth", None) is not None and not args.out:
        raise ValueError("--smooth needs --out (the raw track it smooths)")


def cmd_run(args: argparse.Namespace) -> int:
    """Entry point of ``vio run``."""
    _check_outputs(args)
    if args.demo:
        from vio.io.eqvio import load_eqvio
        data = load_eqvio()
    elif args.dataset is None:
        raise ValueError("give a DATASET folder or --demo")
    else:
        from vio.io.load import load_dataset
        data = load_dataset(args.dataset, args.trim, getattr(args, "topics", None), getattr(args, "calib", None),
                            getattr(args, "imu_calib", None), getattr(args, "groundtruth", None))
    mode = resolve_mode(data, args.mode)
    cfg = load_config(args.config, args.td if args.td is not None else data.td_s, mode)
    _note_cold_kernels(mode)
    if getattr(args, "live", False):
        cfg = dataclasses.replace(cfg, live=True)
    sinks = []
    if args.rerun or args.rrd:
        from vio.viz import RerunConfig, RerunSink
        q = getattr(args, "viz_jpeg_quality", 60)
        vcfg = RerunConfig(image_every=getattr(args, "viz_image_every", 3), jpeg_quality=q or None)
        sinks.append(RerunSink(spawn=args.rerun, rrd=args.rrd, groundtruth=data.groundtruth,
                               cam=data.cam0.calib, cfg=vcfg,
                               cam1=data.cam1.calib if mode in STEREO_MODES else None))
    try:
        res = run_dataset(data, cfg, args.max_frames, sinks, progress=not args.no_progress,
                          mode=mode)
    finally:
        for sink in sinks:
            sink.close()
    if args.out:
        t, _, _ = res.arrays()
        write_tum(args.out, t, [o.T_w_b for o in res.outputs])
    if args.smoothed:
        items = sorted(res.smoothed.values(), key=lambda x: x[0])
        write_tum(args.smoothed, [t for t, _ in items], [T for _, T in items])
    if args.map is not None:
        from vio.nav.grid import save_map
        t, p, _ = res.arrays()
        save_map(args.map, res.map_points(), p)
    if args.smooth is not None:
        from vio.nav.cli import smooth_file
        smooth_file(args.out, args.smooth)
    for line in summary(res, data, getattr(args, "segments", None)):
        print(line)
    if mode in PHOTOMETRIC_MODES and not cfg.direct.points.exposure_td:
        where = (f"its stereo pre-pass's estimate over the first {cfg.td_prepass_s:g} s" if cfg.td_prepass_s > 0
                 else "--td")
        print(f"td note         the photometric term holds td at the sync layer's value ({where}); to "
              "estimate it in the photometric factors: --config examples/photometric_td.yaml")
    note = td_hint(res, cfg.td_s, mode)
    if note is not None:
        print(note)
    return 0
