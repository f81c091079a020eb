"""Where a monocular estimate's scale error comes from: the Umeyama (Sim3) scale of the
whole run and of sliding windows, and the ratio of 1-s chords per second (ground truth over
estimate: above 1 the estimate is short). Ground truth only here.

    python benchmarks/scale_windows.py EST.txt GROUNDTRUTH [--window 3]

``EST.txt``: a TUM trajectory (``vio run --out``); ``GROUNDTRUTH``: a dataset folder, ASL
data.csv or TUM file. Measured (issue 16): real MH_05 mono 15 s, 1-s chords 0.92 in the
first second (the initialization's window: its batch is 7% long), 1.01-1.08 afterwards,
whole-run scale 1.031; generated MH_04@40 tracks 1.5-3.4% short for 30 s after a start at
scale 1.004.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]


def umeyama_scale(src: np.ndarray, dst: np.ndarray) -> float:
    """Scale ``s`` of the least-squares similarity ``dst ~ s R src + t`` (N,3 each)."""
    S, D = src - src.mean(0), dst - dst.mean(0)
    U, d, Vt = np.linalg.svd(D.T @ S / len(src))
    e = np.ones(3)
    e[2] = np.sign(np.linalg.det(U @ Vt))
    return float((d * e).sum() / (S ** 2).sum(1).mean())


def matched(t_ns: np.ndarray, p: np.ndarray, gt_t: np.ndarray, gt_p: np.ndarray, tol_ns: int = 5_000_000):
    """Estimate stamps (s from the first), positions and ground-truth positions matched in time."""
    j = np.clip(np.searchsorted(gt_t, t_ns), 1, len(gt_t) - 1)
    j -= np.abs(gt_t[j - 1] - t_ns) < np.abs(gt_t[j] - t_ns)    # the nearest row, either side
    ok = np.abs(gt_t[j] - t_ns) < tol_ns
    return (t_ns[ok] - t_ns[ok][0]) * 1e-9, p[ok], gt_p[j[ok]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("estimate", type=Path)
    ap.add_argument("groundtruth")
    ap.add_argument("--window", type=float, default=3.0)
    a = ap.parse_args()
    from vio.io.euroc import read_tum
    from vio.io.load import load_groundtruth
    est, gt = read_tum(a.estimate), load_groundtruth(a.groundtruth)
    ts, pe, pg = matched(est.t_ns, est.p_w, gt.t_ns, gt.p_w)
    print(f"whole run: scale gt/est {umeyama_scale(pe, pg):.4f} over {ts[-1]:.1f} s")
    for s0 in np.arange(0.0, ts[-1] - a.window + 1e-6, a.window / 2):
        m = (ts >= s0) & (ts < s0 + a.window)
        lg = np.linalg.norm(np.diff(pg[m], axis=0), axis=1).sum()
        print(f"[{s0:5.1f}, {s0 + a.window:5.1f}] s: scale {umeyama_scale(pe[m], pg[m]):.4f}, "
              f"ground-truth path {lg:.2f} m")
    d = max(1, int(round(1.0 / np.median(np.diff(ts)))))
    ce = np.linalg.norm(pe[d:] - pe[:-d], axis=1)
    cg = np.linalg.norm(pg[d:] - pg[:-d], axis=1)
    bins = [f"{k}:{cg[m].sum() / ce[m].sum():.3f}" for k in range(int(ts[-1] - 1))
            if (m := (ts[:-d] >= k) & (ts[:-d] < k + 1)).any()]
    print("1-s chord ratio gt/est per second:", " ".join(bins))


if __name__ == "__main__":
    main()
