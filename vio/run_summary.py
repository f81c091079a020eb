"""The summary lines of a run (``vio run`` prints them): frames, faults, initialization,
time per frame, biases, td, extrinsic and, with ground truth, the ATE (SE3, Sim3) and the
``--segments`` table."""

from __future__ import annotations

import gtsam
import numpy as np

from vio.io.euroc import EurocDataset
from vio.run import RunResult

# the summary's Sim3 line needs this much ground-truth path (m) for a meaningful scale
MIN_SCALE_PATH_M = 1.0


def summary(res: RunResult, data: EurocDataset, segments_s: float | None = None) -> list[str]:
    """Human-readable summary lines (ATE when ground truth is present; with ``segments_s``
    the ``vio eval --segments`` table of the online poses, or why there is none)."""
    lines = [f"frames          {res.frames_in} in, {len(res.outputs)} estimated, "
             f"{res.keyframes} keyframes, {res.recoveries} solver recoveries"
             + (f", {res.qr_resolves} QR re-solve(s)" if res.qr_resolves else "")
             + (f", {res.point_holds} refused update(s) re-solved holding a world point"
                if res.point_holds else ""),
             _faults_line(res)]
    lines.append(_init_line(res))
    if res.outputs:
        ms = res.frame_ms()
        ms = ms if ms.size else np.zeros(1)
        rtf = res.data_s / res.wall_s if res.wall_s > 0 else float("inf")
        last = res.outputs[-1]
        lines += [f"time per frame  mean {ms.mean():.2f} ms, p95 {np.percentile(ms, 95):.2f} ms, "
                  f"max {ms.max():.1f} ms after initialization; real-time factor {rtf:.1f}x",
                  f"gyro bias       {np.round(last.bias.gyroscope(), 4)} rad/s",
                  f"accel bias      {np.round(last.bias.accelerometer(), 4)} m/s^2",
                  f"td              {last.td_s * 1e3:.2f} ms"]
        cal = data.cam0.calib
        if cal.line_time_s > 0.0:
            lines.append(f"rolling shutter {cal.line_time_s * 1e6:.1f} us a row ({cal.readout_s * 1e3:.1f} ms "
                         "readout), each row at its own time"
                         + (" (its sensor row through the lens)" if cal.has_lens else ""))
        t = last.T_b_c.translation()
        d = data.cam0.calib.T_b_c.between(last.T_b_c)
        moved = np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation()))), np.linalg.norm(d.translation()) * 1e3
        lines.append(f"extrinsic t_b_c {np.round(t, 4)} m"
                     + (f" (moved {moved[0]:.3f} deg / {moved[1]:.1f} mm from the calibration)"
                        if max(moved) > 1e-3 else ""))
    if segments_s and (data.groundtruth is None or len(res.outputs) <= 3):
        lines.append("segments        not evaluated: "
                     + ("no ground truth" if data.groundtruth is None else f"{len(res.outputs)} pose(s)"))
    if data.groundtruth is not None and len(res.outputs) > 3:
        from vio.evaluation import evaluate, overlap_problem, segment_lines
        problem = overlap_problem(res.arrays()[0], data.groundtruth)
        if problem is not None:
            lines.append(f"ATE             not evaluated: {problem}")
        else:
            e = evaluate(*res.arrays(), data.groundtruth, segments_s=segments_s)
            lines.append(f"ATE RMSE        {e.ate_rmse:.4f} m (SE3-aligned, {e.n_matched} poses, "
                         f"path {e.path_length:.1f} m)")
            if e.path_length >= MIN_SCALE_PATH_M:    # a still run's scale is noise
                s = evaluate(*res.arrays(), data.groundtruth, sim3=True)
                lines.append(f"ATE RMSE Sim3   {s.ate_rmse:.4f} m (the estimate's scale "
                             f"{s.scale_error_pct:+.1f} % against the ground truth)")
            lines += segment_lines(e)
    return lines


def _faults_line(res: RunResult) -> str:
    """What the run met and did about it (``vio.faults``, ``vio.camera_gaps``, the backend's
    restarts and bridges); with ``--live`` those counts are the backend process's own."""
    pnp = (f", {res.frames_contradicted} frame(s) placed by PnP against their IMU prediction"
           if res.frames_contradicted else "")
    if res.live:   # the frame check runs on the frame path, in this process
        return "faults          in the live backend process (not reported here; its warnings name each)" + pnp
    return (f"faults          {res.imu_gaps} IMU gap(s) bridged ({res.imu_gap_s:.2f} s), "
             f"{res.imu_dropped} IMU sample(s) dropped, {res.restarts} divergence restart(s)"
             + (f", {res.frames_dropped} frame(s) dropped (image missing, unreadable or blank)"
                if res.frames_dropped else "")
             + (f", {res.camera_gaps} camera gap(s) ({res.camera_gap_s:.2f} s without frames)"
                if res.camera_gaps else "")
             + (f", {res.imu_contradicted} IMU interval(s) contradicted by vision, bridged"
                if res.imu_contradicted else "")
             + pnp
             + (f", {res.reinits} re-initialization(s)" if res.reinits else "")
             + (f", {res.realigns} gravity re-alignment(s)" if res.realigns else "")
             + (f", {res.reiterations} update(s) iterated again" if res.reiterations else ""))


def _init_line(res: RunResult) -> str:
    """How and when the run initialized (or why it did not)."""
    if res.init is None:
        return "initialization  " + (f"not reached ({res.init_wait or 'no attempt'})" if not res.outputs else
                                     "in the live backend process (not reported)")
    return (f"initialization  {res.init.method} after {res.init.decided_s:.2f} s of data "
            f"(first pose at {res.init.state_s:.2f} s)"
            + (f", aligned at a td remainder of {1e3 * res.init.td_s:+.1f} ms" if res.init.td_s else "")
            + (f", the window's metric scale +-{100 * res.init.scale_sigma:.1f} % (1 sigma)"
               if res.init.scale_sigma is not None else ""))
