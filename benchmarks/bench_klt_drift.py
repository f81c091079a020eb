"""How far a KLT track's position drifts from its point, by track age (stop 66, measured).

    python benchmarks/bench_klt_drift.py FOLDER [--mode stereo] [--config Y] [--frames 300]
                                         [--near-m 2] [--json OUT]
    python benchmarks/bench_klt_drift.py --flight V2_02_medium@5+40 [--distort] [--blur-ms 8]
                                         [--exposure none|smooth|step] [--seed 0] [--td-ms 0] ...

``FOLDER`` is a rendering with its ``sim_truth.yaml`` (``vio sim``, ``vio sim --flight``);
``--flight SEQ@START+SECONDS`` renders (or reuses from the cache, ``$VIO_BENCH_CACHE`` or
``~/.cache/vio-bench``) the flight as ``bench_flights.py`` does, with its options; a new
rendering takes a minute or two. ``vio.frontend.KltTracker`` runs over cam0's first
``--frames`` images with the ``FrontendConfig`` of ``--mode`` (``vio.modes``: stereo caps
tracks at 40 frames) and ``--config``'s ``frontend:`` section, loaded as ``vio run --config``
loads it (strict keys). The LK prediction gets the TRUE inter-frame camera rotation
(the pipeline gives it the raw-gyro rotation, ``vio.tracking``: nearly the same guess).

Truth: the scene is rebuilt from ``sim_truth.yaml``; camera poses are the written ground
truth (``T_w_b``, at image stamp + ``td_s``, plus the pixel row's rolling-shutter time)
times cam0's ``T_b_c``. Each track's first observation is undistorted and cast into the
scene (rays that miss are dropped): its point ``p_w`` and depth z. At every later
observation ``p_w`` is projected with that frame's true pose through the lens; the error
is |tracked - true| px (inliers and outliers alike). Observations whose point is behind
the camera or not the first hit from it (1 cm) are skipped. Age 0 is exact by
construction and not reported. Printed per age bin (frames since the first observation):
count, median and 90th percentile error, and the median split by depth at the first
observation (near < ``--near-m``). ``--json OUT`` writes the figures. Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads (vio.threads)

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from bench_flights import GT_DIR, add_render_options, parse_flight, rendered  # noqa: E402  (benchmarks/)
from vio.config import to_dict  # noqa: E402
from vio.frontend import Camera, FrontendConfig, KltTracker  # noqa: E402
from vio.io.euroc import load_euroc, read_image  # noqa: E402
from vio.io.types import GroundTruth  # noqa: E402
from vio.run import MODES, load_config  # noqa: E402
from vio.sim.optics import FlightOptics  # noqa: E402
from vio.sim.scene import Scene  # noqa: E402
from vio.trajectory import interpolate_poses  # noqa: E402

BINS = ((1, 1), (2, 3), (4, 7), (8, 15), (16, 31), (32, 63), (64, 1 << 30))
FIRST_HIT_M = 0.01


@dataclass
class Samples:
    """Observations after the first: age (frames), error (px), depth at birth (m)."""

    age: list[np.ndarray] = field(default_factory=list)
    err: list[np.ndarray] = field(default_factory=list)
    depth: list[np.ndarray] = field(default_factory=list)
    tracks: int = 0      # tracks started
    missed: int = 0      # of which the ray hit nothing
    hidden: int = 0      # later observations skipped: behind the camera or occluded


def bin_label(lo: int, hi: int) -> str:
    """An age bin's column head: "1", "8-15", "64+"."""
    return f"{lo}" if lo == hi else (f"{lo}-{hi}" if hi < 1 << 30 else f"{lo}+")


def camera_poses(gt: GroundTruth, T_b_c: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True ``T_w_c`` at times ``t_ns`` (K,): (R_w_c (K, 3, 3), p_w_c (K, 3))."""
    p_wb, R_wb = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, np.asarray(t_ns, np.int64))
    return R_wb @ T_b_c[:3, :3], p_wb + R_wb @ T_b_c[:3, 3]


def cast(scene: Scene, cam: Camera, R: np.ndarray, p: np.ndarray,
         px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) hit by the rays through distorted pixels ``px`` (M, 2) of cameras
    (R, p) (one per row) and their z in those cameras (M,); NaN rows where nothing is hit."""
    ray_c = np.column_stack([cam.undistort_px(px), np.ones(len(px))])   # z = 1: t is the depth
    z = scene.raycast(p, np.einsum("mij,mj->mi", R, ray_c))
    z[~np.isfinite(z)] = np.nan
    return p + z[:, None] * np.einsum("mij,mj->mi", R, ray_c), z


def reproject(scene: Scene, cam: Camera, R: np.ndarray, p: np.ndarray,
              p_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (M, 2) of ``p_w`` (M, 3) in cameras (R, p), and (M,) bool: in front
    and the first surface hit from the camera (within ``FIRST_HIT_M``)."""
    d = p_w - p
    p_c = np.einsum("mji,mj->mi", R, d)
    t = scene.raycast(p, d)
    seen = (p_c[:, 2] > 0) & (np.abs(t - 1.0) * np.linalg.norm(d, axis=1) < FIRST_HIT_M)
    return cam.project(np.where(seen[:, None], p_c, 1.0)), seen


def score(out: Samples, scene: Scene, cam: Camera, j: int, ids: np.ndarray, px: np.ndarray,
          R: np.ndarray, p: np.ndarray, births: dict[int, tuple[int, np.ndarray, float]]) -> None:
    """Add frame ``j``'s observations ``px`` of tracks ``ids`` born earlier (cameras R, p
    per row) to ``out``: the tracks whose first ray hit the scene, where their point is seen."""
    rec = [births[i] for i in ids.tolist()]
    hit = np.array([np.isfinite(r[2]) for r in rec], dtype=bool)
    rec = [r for r, h in zip(rec, hit) if h]
    if not rec:
        return
    true_px, seen = reproject(scene, cam, R[hit], p[hit], np.array([r[1] for r in rec]))
    out.hidden += int((~seen).sum())
    out.age.append(j - np.array([r[0] for r in rec])[seen])
    out.err.append(np.linalg.norm(px[hit] - true_px, axis=1)[seen])
    out.depth.append(np.array([r[2] for r in rec])[seen])


def measure(folder: Path, fcfg: FrontendConfig, n_frames: int) -> Samples:
    """Track cam0's first ``n_frames`` images and score each observation (module doc)."""
    data = load_euroc(folder)
    truth = yaml.safe_load((folder / "sim_truth.yaml").read_text())
    scene = Scene.from_description(truth["scene"])
    cam = Camera(data.cam0.calib)
    tracker = KltTracker(cam, fcfg)
    td_ns, line_ns = int(round(float(truth.get("td_s", 0.0)) * 1e9)), cam.calib.line_time_s * 1e9
    births: dict[int, tuple[int, np.ndarray, float]] = {}     # id -> (frame, p_w, depth)
    out, R_prev = Samples(), None
    for j in range(min(n_frames, len(data.cam0))):
        t = int(data.cam0.t_ns[j])
        R_frame = camera_poses(data.groundtruth, cam.T_b_c, np.array([t + td_ns]))[0][0]
        mono = tracker.track(t, read_image(data.cam0.files[j]),
                             None if R_prev is None else R_prev.T @ R_frame)
        R_prev = R_frame
        R, p = camera_poses(data.groundtruth, cam.T_b_c,
                            t + td_ns + np.round(mono.px[:, 1] * line_ns).astype(np.int64))
        new = np.array([i not in births for i in mono.ids.tolist()], dtype=bool)
        if new.any():
            p_w, z = cast(scene, cam, R[new], p[new], mono.px[new])
            births.update(zip(mono.ids[new].tolist(), ((j, pw, zz) for pw, zz in zip(p_w, z))))
            out.tracks += int(new.sum())
            out.missed += int(np.isnan(z).sum())
        score(out, scene, cam, j, mono.ids[~new], mono.px[~new], R[~new], p[~new], births)
    return out


def summarize(s: Samples, near_m: float) -> list[dict]:
    """Per age bin: count, median and p90 error (px); median and count near / far."""
    cat = (lambda x: np.concatenate(x) if x else np.zeros(0))
    age, err, depth = cat(s.age), cat(s.err), cat(s.depth)

    def med(e: np.ndarray) -> float | None:
        return float(np.median(e)) if e.size else None

    rows = []
    for lo, hi in BINS:
        e = err[(age >= lo) & (age <= hi)]
        near = depth[(age >= lo) & (age <= hi)] < near_m
        rows.append({"ages": bin_label(lo, hi),
                     "count": int(e.size), "median_px": med(e),
                     "p90_px": float(np.percentile(e, 90)) if e.size else None,
                     "near_count": int(near.sum()), "near_median_px": med(e[near]),
                     "far_count": int((~near).sum()), "far_median_px": med(e[~near])})
    return rows


def print_table(rows: list[dict], s: Samples, near_m: float) -> None:
    """The bins as columns (as benchmarks/README.md, stop 66)."""
    def cell(v: float | int | None) -> str:
        return "-" if v is None else (f"{v:d}" if isinstance(v, int) else f"{v:.2f}")

    lines = [("frames since the first observation", [r["ages"] for r in rows]),
             ("observations", [cell(r["count"]) for r in rows]),
             ("median px", [cell(r["median_px"]) for r in rows]),
             ("90th percentile px", [cell(r["p90_px"]) for r in rows]),
             (f"median px, near < {near_m:g} m", [cell(r["near_median_px"]) for r in rows]),
             ("  observations near", [cell(r["near_count"]) for r in rows]),
             (f"median px, far >= {near_m:g} m", [cell(r["far_median_px"]) for r in rows]),
             ("  observations far", [cell(r["far_count"]) for r in rows])]
    for name, vals in lines:
        print(f"{name:36s}" + "".join(f"{v:>8s}" for v in vals))
    print(f"tracks {s.tracks} (first ray missed the scene: {s.missed}); later observations "
          f"behind the camera or occluded, skipped: {s.hidden}; age 0 exact by construction")


def dataset(a: argparse.Namespace) -> Path:
    """The folder to measure: ``a.data`` or the (cached) rendering of ``a.flight``."""
    if (a.data is None) == (a.flight is None):
        raise SystemExit("give either a dataset FOLDER or --flight SEQ@START+SECONDS")
    if a.data is not None:
        return a.data
    if not GT_DIR.is_dir():
        raise SystemExit(f"{GT_DIR}: not found (../shared/data/euroc_imu_gt)")
    seq, start, seconds = parse_flight(a.flight)
    optics = FlightOptics(distortion=a.distort, blur_s=a.blur_ms * 1e-3)
    return rendered(seq, start, seconds, a.seed, a.td_ms, optics, a.exposure, a.line_time)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", type=Path, default=None, help="folder with sim_truth.yaml")
    ap.add_argument("--flight", default=None, help="SEQ@START+SECONDS, rendered as bench_flights.py")
    ap.add_argument("--mode", default="stereo", choices=MODES, help="whose FrontendConfig (vio.modes)")
    ap.add_argument("--config", type=Path, default=None, help="YAML overrides, as vio run --config")
    ap.add_argument("--frames", type=int, default=300, help="cam0 images tracked")
    ap.add_argument("--near-m", type=float, default=2.0, help="near / far split of the depth")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    add_render_options(ap, "--flight: ")
    a = ap.parse_args()
    logging.disable(logging.WARNING)
    folder = dataset(a)
    if not (folder / "sim_truth.yaml").is_file():
        raise SystemExit(f"{folder}: no sim_truth.yaml (not a vio sim rendering)")
    fcfg = load_config(a.config, mode=a.mode).frontend
    s = measure(folder, fcfg, a.frames)
    rows = summarize(s, a.near_m)
    print(f"{folder}: cam0, {a.frames} frames at most, mode {a.mode}, max_track_len {fcfg.max_track_len}")
    print_table(rows, s, a.near_m)
    if a.json is not None:
        a.json.write_text(json.dumps({"dataset": str(folder), "mode": a.mode, "frames": a.frames,
                                      "near_m": a.near_m, "frontend": to_dict(fcfg), "tracks": s.tracks,
                                      "missed": s.missed, "hidden": s.hidden, "bins": rows}, indent=1))


if __name__ == "__main__":
    main()
