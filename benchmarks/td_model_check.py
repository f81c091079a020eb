"""Check the td observation model against the true image motion of a generated dataset.

The td factor moves an observation taken at ``t_k + td`` back to the state time ``t_k``
along a predicted image velocity: ``uv(t_k) ~ uv_obs - td * vel``, with ``vel`` from
:func:`vio.backend.graph.image_velocity` at the observed ``uv``, the depth at ``t_k``,
the camera's velocity at ``t_k`` and its angular rate = the mean gyro over
``[t_k, t_k + td]`` minus the gyro bias (:class:`vio.imu.KeyframeRates`). Here every
input is true (the dataset's ground truth, landmarks and noise-free projections), so
whatever differs is the model's own error:

* ``td_fit``: the least-squares td of the true displacements ``uv(t_k + td) - uv(t_k)``
  on the predicted velocities (``sum d.v / sum v.v``): equal to the true td for an
  unbiased model; ``rel``: relative error of the predicted velocity against the true
  one (at the exposure) and ``resid_px``: RMS pixel error left after the shift.
* rows for the same with the gyro replaced by the ground truth's own rotation rate
  (``gt-rate``), which separates the raw ground truth's disagreement with the gyro from
  the model.

Usage: ``python -m benchmarks.td_model_check DATASET [DATASET ...]`` (folders written by
``vio tracks``). Frames: ``T_w_b`` body = IMU, ``T_b_c`` from cam0's sensor.yaml; times
int64 ns in the IMU clock; image coordinates on the normalized plane.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

from vio.backend.graph import image_velocity
from vio.imu import mean_gyro
from vio.io.calib import load_camera
from vio.io.euroc import read_groundtruth, read_imu_csv
from vio.io.features import read_features
from vio.trajectory import interpolate_poses

H_NS = 1_000_000     # finite-difference half step of the true velocity (1 ms)


def _project(p_w: np.ndarray, R_w_c: np.ndarray, t_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p_c = np.einsum("nji,nj->ni", R_w_c, p_w - t_w_c)
    return p_c[:, :2] / p_c[:, 2:3], p_c[:, 2]


def _camera(gt, T_b_c, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, R = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, t_ns)
    Rbc, tbc = T_b_c.rotation().matrix(), T_b_c.translation()
    return R @ Rbc, p + R @ tbc


def _gt_rates(gt, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Body rotation rate (n, 3) rad/s of the ground truth over [t0, t1] (Log(R0^T R1) / dt)."""
    _, R0 = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, t0)
    _, R1 = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, t1)
    import gtsam
    dt = (t1 - t0) * 1e-9
    return np.array([gtsam.Rot3.Logmap(gtsam.Rot3(a.T @ b)) / d for a, b, d in zip(R0, R1, dt)])


def check(folder: Path) -> list[dict]:
    """Rows (dicts) of the check on one dataset folder (see the module docstring)."""
    m = folder / "mav0"
    truth = yaml.safe_load((folder / "sim_truth.yaml").read_text())
    td = int(truth["td_ns"])
    cam = load_camera(m / "cam0" / "sensor.yaml")
    imu = read_imu_csv(m / "imu0" / "data.csv")
    gt = read_groundtruth(m / "state_groundtruth_estimate0")
    lm = np.loadtxt(folder / "landmarks.csv", delimiter=",", skiprows=1, ndmin=2)
    p_of = dict(zip(lm[:, 0].astype(np.int64).tolist(), lm[:, 1:4]))
    frames = read_features(m / "cam0" / "features.csv")
    t = np.concatenate([np.full(len(f.ids), f.t_ns, np.int64) for f in frames])
    ids = np.concatenate([f.ids for f in frames])
    p_w = np.array([p_of[int(i)] for i in ids])
    te = t + td
    lo, hi = gt.t_ns[0] + 2 * H_NS, gt.t_ns[-1] - 2 * H_NS
    ok = (t > lo) & (t < hi) & (te > lo) & (te < hi)
    t, te, p_w = t[ok], te[ok], p_w[ok]
    uv_e, _ = _project(p_w, *_camera(gt, cam.T_b_c, te))          # at the exposure
    uv_k, z_k = _project(p_w, *_camera(gt, cam.T_b_c, t))          # at the state time
    up, _ = _project(p_w, *_camera(gt, cam.T_b_c, te + H_NS))
    um, _ = _project(p_w, *_camera(gt, cam.T_b_c, te - H_NS))
    v_true = (up - um) / (2 * H_NS * 1e-9)
    # the state at t_k: velocity (finite difference), bias from the data when given
    pk, Rk = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, t)
    pp, _ = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, t + H_NS)
    pm, _ = interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, t - H_NS)
    v_w = (pp - pm) / (2 * H_NS * 1e-9)
    uniq, inv = np.unique(t, return_inverse=True)
    gyro = np.array([mean_gyro(imu, *sorted((int(a), int(a + td)))) for a in uniq])[inv]
    w_gt = _gt_rates(gt, np.minimum(t, te) - (td == 0) * H_NS, np.maximum(t, te) + (td == 0) * H_NS)
    if gt.bg is not None:
        bg = np.array([np.interp(t, gt.t_ns, gt.bg[:, a]) for a in range(3)]).T
        bias_src = "ground truth"
    else:   # the raw ground truth carries none: the excerpt's mean gyro-minus-rate
        bg = np.broadcast_to(np.median(gyro - w_gt, axis=0), gyro.shape)
        bias_src = "median(gyro - gt rate)"
    Rbc, tbc = cam.T_b_c.rotation().matrix(), cam.T_b_c.translation()
    v_b = np.einsum("nji,nj->ni", Rk, v_w)
    fx = cam.intrinsics[0]
    rows = []
    for name, w_b in (("gyro", gyro - bg), ("gt-rate", w_gt)):
        v_cb = v_b + np.cross(w_b, tbc)
        vel = image_velocity(uv_e, z_k, w_b @ Rbc, v_cb @ Rbc)
        d = uv_e - uv_k
        s = float(np.sum(vel * vel))
        fit = float(np.sum(d * vel) / s) if s > 0 else float("nan")
        rel = np.linalg.norm(vel - v_true, axis=1) / np.maximum(np.linalg.norm(v_true, axis=1), 1e-9)
        resid = (d - td * 1e-9 * vel) * fx
        rows.append({"data": folder.name, "rates": name, "bias": bias_src, "td_ms": td * 1e-6,
                     "td_fit_ms": fit * 1e3, "rel_med": float(np.median(rel)),
                     "rel_mean_signed": float(np.sum((vel - v_true) * v_true) / np.sum(v_true * v_true)),
                     "resid_px": float(np.sqrt(np.mean(resid ** 2))), "n": int(len(t))})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", type=Path, nargs="+")
    args = ap.parse_args(argv)
    print(f"{'data':28s} {'rates':8s} {'td':>7s} {'td_fit':>8s} {'rel_med':>8s} {'gain-1':>8s} "
          f"{'resid_px':>8s}  bias")
    for f in args.folders:
        for r in check(f):
            print(f"{r['data'][:28]:28s} {r['rates']:8s} {r['td_ms']:7.2f} {r['td_fit_ms']:8.3f} "
                  f"{r['rel_med']:8.4f} {r['rel_mean_signed']:+8.4f} {r['resid_px']:8.3f}  {r['bias']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
