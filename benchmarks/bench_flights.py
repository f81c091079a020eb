"""Whole flights with the real IMU and rendered images (issue 16): ``vio.sim.flight``.

    python benchmarks/bench_flights.py [--flights MH_05_difficult@19.05+29.3,V2_01_easy@5+40]
                                       [--modes mono,stereo] [--config Y] [--workers 2]
                                       [--seed 0] [--td-ms 0] [--distort] [--blur-ms 8]
                                       [--exposure none|smooth|step] [--line-time 3e-5]

Each flight ``SEQ@START+SECONDS`` of ``../shared/data/euroc_imu_gt/SEQ`` is rendered once
(cached under ``$VIO_BENCH_CACHE`` or ``~/.cache/vio-bench``: the room sized to the flight,
cam0 and cam1 at EuRoC's intrinsics, 20 Hz, ``--td-ms`` between stamp and exposure) and
each mode runs on it from its first frame with the mode's defaults. The real IMU, with
its noise, biases and vibration, drives the estimator for as long as the flight lasts,
where the shared real-image sets stop after 15-16 s. The default list is issue 16's 29-s
MH_05 flight (the frames ORB-SLAM3's 0.087 m covers: cam0 from 19.05 s after the first
ground-truth row) and 40-s flights of the seven other sequences, none of which any
setting was tuned on. ``--distort``, ``--blur-ms`` and ``--exposure`` add what a real
camera adds (``vio.sim.optics``: the sequence's own radial-tangential lenses, motion blur
over the exposure; affine brightness changes), ``--line-time`` a rolling shutter (each
sensor row at its own time, through the lens with ``--distort``). Printed per flight and mode: ATE (m, SE3 and Sim3 aligned), path,
ATE as % of the path, the Sim3 scale error (%), the initialization (decision / first
pose, s), divergence restarts, IMU intervals vision contradicted (bridged), frames estimated and time per frame p95 / max (ms).
Asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads: bit-reproducible runs (vio.threads)

import numpy as np  # noqa: E402

from datasets import cache_dir, settings_key  # noqa: E402  (benchmarks/)
from vio.config import to_dict  # noqa: E402
from bench_stretches import run  # noqa: E402  (benchmarks/)
from vio.sim.config import SimConfig  # noqa: E402
from vio.sim.optics import FlightOptics  # noqa: E402
from vio.sim.tracks_config import TrackGenConfig  # noqa: E402

GT_DIR = ROOT.parent / "shared" / "data" / "euroc_imu_gt"
FLIGHTS = ("MH_05_difficult@19.05+29.3,MH_03_medium@20+40,MH_04_difficult@15+40,V1_02_medium@5+40,"
           "V1_03_difficult@6+40,V2_01_easy@5+40,V2_02_medium@5+40,V2_03_difficult@5+40")


def parse_flight(text: str) -> tuple[str, float, float]:
    """``SEQ@START+SECONDS`` -> (SEQ, START, SECONDS)."""
    try:
        seq, rest = text.split("@")
        start, seconds = rest.split("+")
        return seq, float(start), float(seconds)
    except ValueError:
        raise SystemExit(f"--flights: {text!r} is not SEQ@START+SECONDS") from None


def rendered(seq: str, start: float, seconds: float, seed: int, td_ms: float,
             optics: FlightOptics = FlightOptics(), exposure: str = "none", line_time_s: float = 0.0) -> Path:
    """The cached rendering of one flight (cam0 and cam1; ``line_time_s``: a rolling shutter)."""
    from vio.sim.flight import render_flight
    tcfg = TrackGenConfig(start_s=start, duration_s=seconds, td_s=td_ms * 1e-3, seed=seed)
    scfg = SimConfig(stereo=True, seed=seed, exposure_changes=exposure, line_time_s=line_time_s)
    parts = [str(GT_DIR / seq), to_dict(tcfg), to_dict(scfg), "vio.sim.flight"]
    if optics != FlightOptics():
        parts.append(to_dict(optics))
    out = cache_dir() / f"flight-{seq}-{start:g}-{settings_key(parts)}"
    if not (out / "sim_truth.yaml").exists():     # written last: a finished rendering
        render_flight(GT_DIR / seq, out, tcfg, scfg, optics, overwrite=True)
    return out


def run_flight(job: tuple) -> list[tuple[str, float, str]]:
    """Render (or reuse) one flight and run each mode on it: (mode, ATE % of the path, the
    printed row) per mode."""
    text, modes, config, seed, td_ms, optics, exposure, line_time = job
    logging.disable(logging.WARNING)
    seq, start, seconds = parse_flight(text)
    folder = rendered(seq, start, seconds, seed, td_ms, optics, exposure, line_time)
    rows = []
    for mode in modes:
        r = run(folder, mode, config)
        pct = r["ate_mm"] / 10 / max(r["path_m"], 1e-9)
        rows.append((mode, pct, f"{text:30s} {mode:7s} {r['ate_mm'] / 1e3:7.4f} {r['sim3_mm'] / 1e3:7.4f} "
                     f"{r['path_m']:6.1f} {pct:6.3f} {r['scale_pct']:+7.2f} {r['init_s']:>11s} "
                     f"{r['restarts']:3d} {r['bridged']:3d} {r['poses']:5d}/{r['frames']:<5d} "
                     f"{r['p95']:6.1f} {r['max']:6.1f}"))
    return rows


def add_render_options(ap: argparse.ArgumentParser, what: str = "") -> None:
    """The rendering's options (seed, td, lens, blur, exposure); ``what`` prefixes the help."""
    ap.add_argument("--seed", type=int, default=0, help=f"{what}scene, texture and image-noise seed")
    ap.add_argument("--td-ms", type=float, default=0.0, help=f"{what}camera stamp to exposure offset (ms)")
    ap.add_argument("--distort", action="store_true", help=f"{what}the sequences' own distorted cameras")
    ap.add_argument("--blur-ms", type=float, default=0.0, help=f"{what}motion blur: exposure duration (ms)")
    ap.add_argument("--exposure", default="none", choices=("none", "smooth", "step"),
                    help=f"{what}brightness changes (vio.sim.render.exposure_sequence)")
    ap.add_argument("--line-time", type=float, default=0.0, help=f"{what}rolling shutter: seconds per row")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", default=FLIGHTS, help="comma list of SEQ@START+SECONDS")
    ap.add_argument("--modes", default="mono", help="comma list of vio run modes (image modes)")
    ap.add_argument("--config", type=Path, default=None, help="YAML overrides, as vio run --config")
    ap.add_argument("--workers", type=int, default=1, help="flights rendered and run in parallel")
    add_render_options(ap)
    a = ap.parse_args()
    optics = FlightOptics(distortion=a.distort, blur_s=a.blur_ms * 1e-3)
    if not GT_DIR.is_dir():
        raise SystemExit(f"{GT_DIR}: not found (../shared/data/euroc_imu_gt)")
    jobs = [(f, a.modes.split(","), a.config, a.seed, a.td_ms, optics, a.exposure, a.line_time)
            for f in a.flights.split(",")]
    print(f"{'flight':30s} {'mode':7s} {'ATE m':>7s} {'Sim3 m':>7s} {'path':>6s} {'ATE %':>6s} "
          f"{'scale%':>7s} {'init s':>11s} {'rst':>3s} {'brg':>3s} {'poses/frames':>11s} {'p95':>6s} "
          f"{'max':>6s}", flush=True)
    pcts: dict[str, list[float]] = {}
    with ProcessPoolExecutor(max_workers=max(1, a.workers)) as pool:
        for rows in pool.map(run_flight, jobs):
            for mode, pct, row in rows:
                print(row, flush=True)
                pcts.setdefault(mode, []).append(pct)
    for mode, v in pcts.items():
        print(f"{mode}: ATE % of path mean {np.mean(v):.3f}, max {np.max(v):.3f}, under 0.2 %: "
              f"{sum(x < 0.2 for x in v)} of {len(v)}")


if __name__ == "__main__":
    main()
