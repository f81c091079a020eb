"""KLT tracks on REAL images against the ground truth's epipolar geometry, two front-end
settings side by side (stop 67: LK against tracks anchored to their first patch).

    python benchmarks/bench_klt_epipolar.py [DATA] [--mode mono] [--frames 300]
                                            [--a Y_A.yaml] [--b Y_B.yaml]

Real images have no scene to cast a track's first ray into (``bench_klt_drift.py`` does
that on renders). Here each observation of a track is checked against its first one: the
distance (px, at fx) of the later pixel from the epipolar line of the first, under the
ground-truth relative camera pose (``T_w_b`` interpolated at the image stamps, times
cam0's ``T_b_c``); pairs less than 5 cm apart are skipped (no line to speak of). The
distance measures the error across the line only (a depth error moves a point along it),
and the ground truth's own pose error sets a floor, the same for both settings. Both
settings run ``KltTracker`` over the same images with ``--mode``'s FrontendConfig and
their YAML's ``frontend:`` section; tracks are paired by birth (same frame, same pixel),
so the two are scored on the same points and observations. DATA defaults to real MH_05.
Asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads (vio.threads)

import numpy as np  # noqa: E402

from bench_klt_drift import BINS, bin_label, camera_poses  # noqa: E402  (benchmarks/)
from vio.frontend import Camera, KltTracker  # noqa: E402
from vio.io.euroc import load_euroc, read_image  # noqa: E402
from vio.run import MODES, load_config  # noqa: E402

MIN_BASELINE_M = 0.05
Track = dict[int, np.ndarray]          # frame -> pixel (2,)


def tracks_by_birth(data, cam: Camera, fcfg, n: int) -> dict[tuple, Track]:
    """Each track of cam0's first ``n`` frames keyed by (birth frame, birth pixel)."""
    tracker, birth, out = KltTracker(cam, fcfg), {}, {}
    for j in range(n):
        m = tracker.track(int(data.cam0.t_ns[j]), read_image(data.cam0.files[j]))
        for i, p in zip(m.ids.tolist(), m.px):
            key = birth.setdefault(i, (j, round(float(p[0]), 2), round(float(p[1]), 2)))
            out.setdefault(key, {})[j] = p
    return out


def epipolar_px(cam: Camera, R_wc: np.ndarray, p_wc: np.ndarray, f0: int, j: int,
                px0: np.ndarray, pxj: np.ndarray) -> float | None:
    """Distance (px) of ``pxj`` in frame j from the epipolar line of ``px0`` in frame f0."""
    R = R_wc[f0].T @ R_wc[j]
    t = R_wc[f0].T @ (p_wc[j] - p_wc[f0])
    if np.linalg.norm(t) < MIN_BASELINE_M:
        return None
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    xa, xb = (np.r_[cam.undistort_px(q[None])[0], 1.0] for q in (px0, pxj))
    line = E.T @ xa
    return float(abs(xb @ line) / np.hypot(line[0], line[1]) * cam.fx)


def score(cam: Camera, R_wc: np.ndarray, p_wc: np.ndarray, runs: list[dict[tuple, Track]]
          ) -> list[np.ndarray]:
    """(K, 2) rows (age, distance px) per run, on the tracks and frames all runs share."""
    rows: list[list[tuple[int, float]]] = [[] for _ in runs]
    for key in set.intersection(*(set(r) for r in runs)):
        f0 = key[0]
        for j in sorted(set.intersection(*(set(r[key]) for r in runs)) - {f0}):
            d = [epipolar_px(cam, R_wc, p_wc, f0, j, r[key][f0], r[key][j]) for r in runs]
            if d[0] is not None:
                for k, dk in enumerate(d):
                    rows[k].append((j - f0, dk))
    return [np.array(r).reshape(-1, 2) for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", type=Path,
                    default=ROOT.parent / "shared" / "data" / "euroc_MH_05_mono_15s")
    ap.add_argument("--mode", default="mono", choices=MODES, help="whose FrontendConfig (vio.modes)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--a", type=Path, default=None, help="YAML of setting A (default: the mode's)")
    ap.add_argument("--b", type=Path, default=None, help="YAML of setting B")
    a = ap.parse_args()
    logging.disable(logging.WARNING)
    data = load_euroc(a.data)
    if data.groundtruth is None:
        raise SystemExit(f"{a.data}: no ground truth")
    cam, n = Camera(data.cam0.calib), min(a.frames, len(data.cam0))
    R_wc, p_wc = camera_poses(data.groundtruth, cam.T_b_c, data.cam0.t_ns[:n])
    names = [str(y or f"{a.mode} defaults") for y in (a.a, a.b)]
    runs = [tracks_by_birth(data, cam, load_config(y, mode=a.mode).frontend, n) for y in (a.a, a.b)]
    scores = score(cam, R_wc, p_wc, runs)
    print(f"{a.data}: {n} frames, {len(scores[0])} shared observations; epipolar distance from "
          "the first observation, median px by frames since it")
    print(f"{'':40s}" + "".join(f"{bin_label(lo, hi):>8s}" for lo, hi in BINS))
    for name, s in zip(names, scores):
        cells = [s[(s[:, 0] >= lo) & (s[:, 0] <= hi), 1] for lo, hi in BINS]
        print(f"{name[-40:]:40s}" + "".join(f"{np.median(c):8.2f}" if c.size else f"{'-':>8s}" for c in cells))


if __name__ == "__main__":
    main()
