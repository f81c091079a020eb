"""Trajectory evaluation with evo: ATE and RPE after SE3 (or Sim3) alignment.

Ground truth appears only here (and in benchmarks), never in the estimator.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vio.io.types import GroundTruth


# a stretch's own scale needs its ground truth to spread this much (RMS about its mean, m):
# over a still stretch the ratio is the ground truth's millimetre noise against the estimate's
MIN_SEGMENT_SPREAD_M = 0.02


@dataclass(frozen=True)
class SegmentErrors:
    """One stretch of a run, ``[t0_s, t1_s)`` seconds after the first matched pose (the
    last one to the end: a tail shorter than half a stretch joins it):
    ``n`` poses, the ground truth's path ``path_m`` (m), the mean position error after the
    whole run's alignment ``ate_mean`` (m: where the run's error is) and the estimate's
    length over the stretch against the ground truth, ``length_pct`` (%, from the stretch's
    own Sim3 alignment; negative: short; NaN where the stretch has fewer than 3 poses or its
    ground truth spreads less than ``MIN_SEGMENT_SPREAD_M``): a monocular run's scale as it goes."""

    t0_s: float
    t1_s: float
    n: int
    path_m: float
    ate_mean: float
    length_pct: float


@dataclass(frozen=True)
class TrajectoryErrors:
    """ATE (absolute translation error, m) and RPE (relative pose error over
    ``rpe_delta_m`` metres of path: translation m, rotation deg) statistics. ``scale``:
    the Sim3 alignment's scale s (ground truth ~ s R estimate + t; s > 1: the estimated
    trajectory is short), 1 with SE3."""

    n_matched: int
    ate_rmse: float
    ate_mean: float
    ate_max: float
    rpe_trans_rmse: float
    rpe_rot_rmse_deg: float
    path_length: float
    alignment: str
    scale: float = 1.0
    segments: tuple[SegmentErrors, ...] = ()

    @property
    def scale_error_pct(self) -> float:
        """The estimate's length against the ground truth's, in % (negative: short)."""
        return 100.0 * (1.0 / self.scale - 1.0)


def _evo_traj(t_ns: np.ndarray, p: np.ndarray, q_wxyz: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D
    return PoseTrajectory3D(positions_xyz=np.asarray(p, float),
                            orientations_quat_wxyz=np.asarray(q_wxyz, float),
                            timestamps=np.asarray(t_ns, np.float64) * 1e-9)


def overlap_problem(est_t_ns: np.ndarray, gt: GroundTruth, max_diff_s: float = 0.01) -> str | None:
    """None when at least 3 estimate stamps have a ground-truth pose within ``max_diff_s``;
    otherwise a one-line reason naming both time spans (seconds)."""
    est_t_ns = np.asarray(est_t_ns, np.int64)
    if len(gt) == 0 or est_t_ns.size == 0:
        return f"ground truth has {len(gt)} poses, the estimate {est_t_ns.size}"
    j = np.clip(np.searchsorted(gt.t_ns, est_t_ns), 1, max(len(gt) - 1, 1))
    near = np.minimum(np.abs(gt.t_ns[j - 1] - est_t_ns), np.abs(gt.t_ns[np.minimum(j, len(gt) - 1)] - est_t_ns))
    n = int((near <= max_diff_s * 1e9).sum())
    if n >= 3:
        return None
    return (f"ground truth [{gt.t_ns[0] * 1e-9:.3f}, {gt.t_ns[-1] * 1e-9:.3f}] s does not overlap the estimate "
            f"[{est_t_ns[0] * 1e-9:.3f}, {est_t_ns[-1] * 1e-9:.3f}] s ({n} poses within {max_diff_s * 1e3:.0f} ms)")


def _segments(ref, est, seconds: float) -> tuple[SegmentErrors, ...]:
    """:class:`SegmentErrors` of consecutive ``seconds``-long stretches of the associated
    trajectories ``ref`` and ``est`` (evo, ``est`` already aligned to ``ref``)."""
    from evo.core.geometry import GeometryException, umeyama_alignment
    t = np.asarray(est.timestamps, float) - float(est.timestamps[0])
    pe, pr = np.asarray(est.positions_xyz, float), np.asarray(ref.positions_xyz, float)
    err = np.linalg.norm(pe - pr, axis=1)
    starts = list(np.arange(0.0, t[-1] + 1e-9, seconds))
    if len(starts) > 1 and t[-1] - starts[-1] < 0.5 * seconds:
        starts.pop()                   # a short tail joins the last stretch
    out = []
    for i, a in enumerate(starts):
        sel = (t >= a) & (t < (starts[i + 1] if i + 1 < len(starts) else np.inf))
        if not sel.any():
            continue
        path = float(np.linalg.norm(np.diff(pr[sel], axis=0), axis=1).sum()) if sel.sum() > 1 else 0.0
        length = float("nan")
        spread = float(np.sqrt(((pr[sel] - pr[sel].mean(axis=0)) ** 2).sum(axis=1).mean()))
        if sel.sum() >= 3 and spread >= MIN_SEGMENT_SPREAD_M:
            try:
                c = umeyama_alignment(pe[sel].T, pr[sel].T, with_scale=True)[2]
                length = 100.0 * (1.0 / c - 1.0) if c > 0 else float("nan")
            except GeometryException:   # degenerate (collinear or still) stretch
                pass
        end = starts[i + 1] if i + 1 < len(starts) else max(a + seconds, float(t[-1]))
        out.append(SegmentErrors(float(a), float(end), int(sel.sum()), path, float(err[sel].mean()), length))
    return tuple(out)


def evaluate(est_t_ns: np.ndarray, est_p: np.ndarray, est_q_wxyz: np.ndarray, gt: GroundTruth,
             sim3: bool = False, max_diff_s: float = 0.01, rpe_delta_m: float = 1.0,
             segments_s: float | None = None) -> TrajectoryErrors:
    """Associate by time, align (SE3, or Sim3 for mono), and compute ATE/RPE; with
    ``segments_s``, also the errors of each ``segments_s``-second stretch
    (:class:`SegmentErrors`)."""
    if segments_s is not None and not segments_s > 0:
        raise ValueError(f"segments must be a positive number of seconds, got {segments_s}")
    from evo.core import metrics, sync
    problem = overlap_problem(est_t_ns, gt, max_diff_s)
    if problem is not None:
        raise ValueError(problem)
    est = _evo_traj(est_t_ns, est_p, est_q_wxyz)
    ref = _evo_traj(gt.t_ns, gt.p_w, gt.q_wxyz)
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff_s)
    if est.num_poses < 3:
        raise ValueError(f"only {est.num_poses} poses match the ground truth in time")
    est = copy.deepcopy(est)
    _, _, scale = est.align(ref, correct_scale=sim3)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    s = ape.get_all_statistics()
    path = float(ref.path_length)
    delta = min(rpe_delta_m, max(path / 4, 1e-3))
    rt = metrics.RPE(metrics.PoseRelation.translation_part, delta, metrics.Unit.meters, all_pairs=False)
    rr = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta, metrics.Unit.meters, all_pairs=False)
    try:
        rt.process_data((ref, est))
        rr.process_data((ref, est))
        rpe_t, rpe_r = rt.get_statistic(metrics.StatisticsType.rmse), rr.get_statistic(metrics.StatisticsType.rmse)
    except Exception:  # noqa: BLE001 - too short for the RPE delta
        rpe_t = rpe_r = float("nan")
    segs = _segments(ref, est, segments_s) if segments_s else ()
    return TrajectoryErrors(int(est.num_poses), float(s["rmse"]), float(s["mean"]), float(s["max"]),
                            float(rpe_t), float(rpe_r), path, "sim3" if sim3 else "se3", float(scale), segs)


def segment_lines(res: TrajectoryErrors) -> list[str]:
    """The table of ``res.segments`` (empty without), as ``vio eval`` and ``vio run`` print it."""
    if not res.segments:
        return []
    return ["stretch [s]      poses  path [m]  mean error [m]  length vs truth [%]"] + [
        f"{g.t0_s:6.1f}-{g.t1_s:<6.1f}  {g.n:7d}  {g.path_m:8.2f}  {g.ate_mean:14.4f}  "
        + (f"{g.length_pct:+19.1f}" if np.isfinite(g.length_pct) else f"{'n/a':>19}")
        for g in res.segments]


def evaluate_files(est_path: str | Path, gt_path: str | Path, sim3: bool = False,
                   plot: str | Path | None = None, segments_s: float | None = None) -> TrajectoryErrors:
    """ATE/RPE of a TUM estimate against a TUM file, an ASL data.csv (EuRoC estimate or
    TUM-VI mocap0) or a dataset folder holding one (``segments_s``: see :func:`evaluate`)."""
    from vio.io.euroc import read_tum
    from vio.io.load import load_groundtruth
    est = read_tum(Path(est_path))
    gt = load_groundtruth(gt_path)
    problem = overlap_problem(est.t_ns, gt)
    if problem is not None:
        raise ValueError(f"{est_path} vs {gt_path}: {problem}")
    res = evaluate(est.t_ns, est.p_w, est.q_wxyz, gt, sim3, segments_s=segments_s)
    if plot is not None:
        save_plot(est, gt, res, Path(plot), sim3)
    return res


def save_plot(est: GroundTruth, gt: GroundTruth, res: TrajectoryErrors, path: Path, sim3: bool) -> None:
    """Top view of the aligned estimate over the ground truth."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from evo.core import sync
    ref, e = sync.associate_trajectories(_evo_traj(gt.t_ns, gt.p_w, gt.q_wxyz),
                                         _evo_traj(est.t_ns, est.p_w, est.q_wxyz), max_diff=0.01)
    e.align(ref, correct_scale=sim3)
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(ref.positions_xyz[:, 0], ref.positions_xyz[:, 1], "k-", label="ground truth")
    ax.plot(e.positions_xyz[:, 0], e.positions_xyz[:, 1], "r-", label="estimate")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"ATE RMSE {res.ate_rmse:.3f} m ({res.alignment})")
    ax.legend()
    fig.savefig(path, dpi=100)
    plt.close(fig)
