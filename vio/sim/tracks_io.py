"""File side of the feature-track generator: verbatim excerpts of the source
files (IMU, ground truth) and the output folder writer."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from vio.errors import DataError
from vio.io.csvio import NumericTable, check_increasing, read_numeric, read_text_lines
from vio.sim.tracks_config import TrackGenResult

GT_DIR = "state_groundtruth_estimate0"


@dataclass(frozen=True)
class Table:
    """A parsed timestamped file plus its raw text, so excerpts copy rows verbatim."""

    table: NumericTable
    raw: list[str]

    @property
    def t_ns(self) -> np.ndarray:
        return self.table.t_ns

    def write_slice(self, dst: Path, t0_ns: int, t1_ns: int, pad: int = 0) -> None:
        """Header lines plus the data rows with ``t0_ns <= t <= t1_ns`` (and ``pad`` more each side)."""
        nos = self.table.lines
        i0 = max(int(np.searchsorted(self.t_ns, t0_ns, "left")) - pad, 0)
        i1 = min(int(np.searchsorted(self.t_ns, t1_ns, "right")) + pad, len(nos))
        rows = self.raw[: nos[0] - 1] + [self.raw[n - 1] for n in nos[i0:i1]]
        dst.write_text("".join(r + "\n" for r in rows))


def read_table(path: Path, n_values: int | tuple[int, ...], tum: bool = False) -> Table:
    table = read_numeric(path, n_values, delimiter=None if tum else ",", time_in_seconds=tum)
    check_increasing(table)
    if len(table.t_ns) < 2:
        raise DataError(path, "fewer than 2 data rows")
    return Table(table, read_text_lines(path))


def read_groundtruth(mav0: Path) -> tuple[Table, np.ndarray, np.ndarray, bool]:
    """Body poses in the world: (table, p_w (N, 3) m, q_wxyz (N, 4) unit, is_tum)."""
    csv, tum = mav0 / GT_DIR / "data.csv", mav0 / GT_DIR / "groundtruth_tum.txt"
    if csv.is_file():
        tab = read_table(csv, (7, 16))
        p, q = tab.table.values[:, 0:3], tab.table.values[:, 3:7]
    elif tum.is_file():
        tab = read_table(tum, 7, tum=True)
        p, q = tab.table.values[:, 0:3], tab.table.values[:, [6, 3, 4, 5]]  # TUM xyzw -> wxyz
    else:
        raise DataError(mav0 / GT_DIR, "no data.csv or groundtruth_tum.txt")
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    bad = np.flatnonzero(np.abs(norm[:, 0] - 1.0) > 1e-2)
    if bad.size:
        raise DataError(tab.table.path, f"quaternion norm {norm[bad[0], 0]:.4f} is not 1",
                        int(tab.table.lines[bad[0]]))
    return tab, p, q / norm, not csv.is_file()


def write_outputs(src: Path, out: Path, res: TrackGenResult, gt: Table, gt_tum: bool, imu: Table,
                  truth: dict, gt_rows: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """The output folder. Ground truth: ``gt_rows`` = (t_ns (K,) int64, (K, 16) EuRoC
    values p, q_wxyz, v, bg, ba) when given (the IMU-consistent trajectory), else the
    source rows verbatim."""
    m = out / "mav0"
    for d in ("cam0", "imu0", GT_DIR):
        (m / d).mkdir(parents=True, exist_ok=True)
    for rel in ("cam0/sensor.yaml", "imu0/sensor.yaml", f"{GT_DIR}/sensor.yaml", "body.yaml"):
        if (src / rel).exists():
            shutil.copyfile(src / rel, m / rel)
    t = res.t_ns
    (m / "cam0/data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{s},{s}.png\n" for s in t))
    rows = "".join(f"{t[f]},{f},{i},{u:.12f},{v:.12f}\n" for f, i, (u, v) in
                   zip(res.frame_idx.tolist(), res.landmark_id.tolist(), res.uv.tolist()))
    (m / "cam0/features.csv").write_text("timestamp_ns,frame_idx,landmark_id,u_norm,v_norm\n" + rows)
    margin = int(round(truth["config"]["imu_margin_s"] * 1e9))
    t_lo, t_hi = min(t[0], t[0] + res.td_ns) - margin, max(t[-1], t[-1] + res.td_ns) + margin
    imu.write_slice(m / "imu0/data.csv", t_lo, t_hi)
    if gt_rows is None:
        gt.write_slice(m / GT_DIR / ("groundtruth_tum.txt" if gt_tum else "data.csv"), t_lo, t_hi, pad=1)
    else:
        head = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
                "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
                "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
                "b_a_RS_S_z [m s^-2]\n")
        (m / GT_DIR / "data.csv").write_text(head + "".join(
            f"{int(t)}," + ",".join(repr(float(x)) for x in r) + "\n" for t, r in zip(*gt_rows)))
    lm = zip(res.landmark_ids.tolist(), res.landmark_p_w.tolist())
    (out / "landmarks.csv").write_text("landmark_id,p_w_x,p_w_y,p_w_z\n" + "".join(
        f"{i},{x!r},{y!r},{z!r}\n" for i, (x, y, z) in lm))  # repr: exact float round trip
    (out / "sim_truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False, default_flow_style=None))


