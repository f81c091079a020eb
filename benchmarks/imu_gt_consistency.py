"""How far a dataset's IMU and its ground truth agree on motion, by time scale.

A monocular VIO takes its metric scale from the accelerometer alone: over its window
it matches the visual second differences of position against the preintegrated
accelerations. If the IMU and the ground truth disagree on how much the body
accelerated, the estimate's scale follows the IMU and is scored against the ground
truth: that disagreement is a floor under the mono ATE that no estimator removes.

For windows of length ``2T`` starting every ``T / 2`` along the ground truth, the
position second difference of the ground truth

    d2p_gt = p(t0 + 2T) - 2 p(t0 + T) + p(t0)

is compared with the same second difference predicted by the IMU,

    d2p_imu = int_{t0}^{t0+2T} h(t) (R_w_b(t) (a_m(t) - b_a(t)) + g) dt,
    h(t) = T - |t - t0 - T|          (the triangle kernel of a second difference),

with the ground truth's own orientation and accelerometer bias (a constant bias is
fitted when the file has none). Only positions enter on the ground-truth side, so the
figure does not depend on the ground truth's velocities. The least-squares ratio

    k(T) = <d2p_gt, d2p_imu> / <d2p_imu, d2p_imu>

is 1 for a consistent pair; k < 1 means the IMU reports more motion than the ground
truth (a VIO estimate driven by it comes out long by about 1 / k - 1). Windows where
the body is slower than ``--min-speed`` are skipped (the static start).

With ``--per-axis`` the same windows fit one ratio per body axis of the accelerometer
(and a constant bias), ``y = sum_k s_k int h R_w_b[:, k] (a_m,k - b_a,k) dt + g T^2``:
an accelerometer scale-factor error would show as the same ``s_k != 1`` on every
sequence of one IMU; an axis that carries gravity (EuRoC's x and z) is pinned near 1 by it.

    python benchmarks/imu_gt_consistency.py DATASET [DATASET ...] [--scales 0.25,0.5,1,2,4] [--per-axis]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vio.io.euroc import find_mav0, read_imu_csv  # noqa: E402
from vio.io.load import load_groundtruth  # noqa: E402
from vio.trajectory import interpolate_poses  # noqa: E402

GRAVITY_W = np.array([0.0, 0.0, -9.81])


def imu_world_accel(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """IMU times (s), the ground truth's position (m) at them, world accelerations
    R_w_b (a_m - b_a) + g (m/s^2) and the body-to-world rotations (N, 3, 3); the flag
    says whether the ground truth carried an accelerometer bias."""
    mav0 = find_mav0(path)
    imu = read_imu_csv(mav0 / "imu0" / "data.csv")
    gt = load_groundtruth(path)
    t_gt = gt.t_ns * 1e-9
    keep = (imu.t_ns >= gt.t_ns[0]) & (imu.t_ns <= gt.t_ns[-1])
    t, a_m = imu.t_ns[keep] * 1e-9, imu.accel[keep]
    p, R = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, imu.t_ns[keep])
    has_bias = gt.ba is not None and bool(np.all(np.isfinite(gt.ba)))
    b = (np.stack([np.interp(t, t_gt, gt.ba[:, k]) for k in range(3)], 1) if has_bias
         else np.zeros_like(a_m))
    acc = np.einsum("nij,nj->ni", R, a_m - b) + GRAVITY_W
    return t, p, acc, R, has_bias


def windows(t: np.ndarray, p: np.ndarray, T: float, min_speed: float):
    """The windows of the module docstring, every ``T / 2``: ``(i0, i2, h, d2p_gt)`` with
    ``i0:i2`` the 2T of samples, ``h`` (i2 - i0,) the triangle kernel times each sample's
    time step and ``d2p_gt`` (3,) the ground truth's second difference; windows where the
    body is slower than ``min_speed`` (m/s) are skipped."""
    n = int(round(T / float(np.median(np.diff(t)))))
    for i0 in range(0, len(t) - 2 * n, max(1, n // 2)):
        i1, i2 = i0 + n, i0 + 2 * n
        if np.linalg.norm(p[i2] - p[i0]) / (t[i2] - t[i0]) < min_speed:
            continue
        yield i0, i2, (T - np.abs(t[i0:i2] - t[i1])) * np.gradient(t[i0:i2]), p[i2] - 2 * p[i1] + p[i0]


def consistency(t: np.ndarray, p: np.ndarray, acc: np.ndarray, R: np.ndarray, T: float,
                fit_bias: bool, min_speed: float = 0.2) -> tuple[float, int]:
    """k(T) (see the module docstring) and the number of windows used."""
    gt_rows, imu_rows, bias_rows = [], [], []
    for i0, i2, h, d2p in windows(t, p, T, min_speed):
        gt_rows.append(d2p)
        imu_rows.append(h @ acc[i0:i2])
        bias_rows.append(-np.einsum("n,nij->ij", h, R[i0:i2]))  # d(d2p_imu)/d(b_a)
    if not gt_rows:
        return float("nan"), 0
    y, x = np.concatenate(gt_rows), np.concatenate(imu_rows)
    if not fit_bias:
        return float(x @ y / (x @ x)), len(gt_rows)
    A = np.column_stack([x, np.concatenate(bias_rows)])   # y = k x + k J db
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(sol[0]), len(gt_rows)


def per_axis(t: np.ndarray, p: np.ndarray, acc: np.ndarray, R: np.ndarray, T: float,
             min_speed: float = 0.2) -> tuple[np.ndarray, int]:
    """Per body axis k the ratio s_k (3,) of the module docstring's per-axis fit (a
    constant accelerometer bias fitted with them) and the number of windows used;
    ``acc`` are world accelerations as :func:`imu_world_accel` returns them."""
    a_b = np.einsum("nji,nj->ni", R, acc - GRAVITY_W)     # body-frame specific force, bias removed
    ys, xs = [], []
    for i0, i2, h, d2p in windows(t, p, T, min_speed):
        ys.append(d2p - h.sum() * GRAVITY_W)
        hR = h[:, None, None] * R[i0:i2]
        # column k: axis k's reading through the attitude; then d/d(b_a)
        xs.append(np.column_stack([np.einsum("nik,nk->ik", hR, a_b[i0:i2]), -hR.sum(0)]))
    if not ys:
        return np.full(3, np.nan), 0
    sol, *_ = np.linalg.lstsq(np.concatenate(xs), np.concatenate(ys), rcond=None)
    return sol[:3], len(ys)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("datasets", nargs="+", type=Path)
    ap.add_argument("--scales", default="0.25,0.5,1,2,4",
                    help="half-window lengths T in seconds (comma-separated)")
    ap.add_argument("--min-speed", type=float, default=0.2, help="m/s; slower windows skipped")
    ap.add_argument("--per-axis", action="store_true", help="one ratio per body axis (module doc)")
    args = ap.parse_args(argv)
    scales = [float(s) for s in args.scales.split(",")]
    if args.per_axis:
        print("s_k(T): ground truth / IMU per accelerometer axis x / y / z (1 = consistent)")
        print("| dataset | " + " | ".join(f"T = {s:g} s" for s in scales) + " |")
        print("|---|" + "---|" * len(scales))
        for d in args.datasets:
            t, p, acc, R, _ = imu_world_accel(d)
            cells = [" / ".join(f"{v:.3f}" for v in per_axis(t, p, acc, R, s, args.min_speed)[0])
                     for s in scales]
            print(f"| {d.name} | " + " | ".join(cells) + " |")
        return 0
    print("k(T) = ground-truth / IMU position second differences over windows of 2T "
          "(1 = consistent; < 1: the IMU reports more motion)")
    print("| dataset | " + " | ".join(f"T = {s:g} s" for s in scales) + " |")
    print("|---|" + "---|" * len(scales))
    for d in args.datasets:
        t, p, acc, R, has_bias = imu_world_accel(d)
        cells = []
        for s in scales:
            k, n = consistency(t, p, acc, R, s, fit_bias=not has_bias, min_speed=args.min_speed)
            cells.append(f"{k:.4f} ({n})")
        print(f"| {d.name}{'' if has_bias else ' (bias fitted)'} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
