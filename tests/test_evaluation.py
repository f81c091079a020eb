"""Trajectory evaluation (``vio.evaluation``): the Sim3 alignment reports the estimate's scale."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from vio.evaluation import evaluate
from vio.io.types import GroundTruth


def _helix(n: int = 200) -> GroundTruth:
    t = np.linspace(0.0, 10.0, n)
    p = np.stack([2.0 * np.cos(t), 2.0 * np.sin(t), 0.3 * t], axis=1)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return GroundTruth((t * 1e9).astype(np.int64), p, q)


@pytest.mark.parametrize("shrink", [0.97, 1.0, 1.05])
def test_sim3_scale_is_the_estimate_shortfall(shrink):
    """An estimate that is the ground truth shrunk by ``shrink``, rotated and shifted:
    Sim3 finds scale 1 / shrink with no residual error, SE3 reports scale 1 and the error."""
    gt = _helix()
    R = gtsam.Rot3.Ypr(0.4, -0.1, 0.2).matrix()
    p_est = shrink * gt.p_w @ R.T + np.array([1.0, -2.0, 0.5])
    sim = evaluate(gt.t_ns, p_est, gt.q_wxyz, gt, sim3=True)
    se3 = evaluate(gt.t_ns, p_est, gt.q_wxyz, gt)
    assert sim.scale == pytest.approx(1.0 / shrink, rel=1e-6)
    assert sim.scale_error_pct == pytest.approx(100.0 * (shrink - 1.0), abs=1e-4)
    assert sim.ate_rmse < 1e-6 and sim.alignment == "sim3"
    assert se3.scale == 1.0
    assert (se3.ate_rmse > 0.01) == (shrink != 1.0)


def test_segments_find_the_stretch_whose_motion_is_too_long(tmp_path, capsys):
    """The helix's seconds 4-6 stretched by 20 % (later positions carried along): the
    stretch reports +20 %, the others 0 %, and the error grows from there; a still stretch
    has no length; the CLI prints the table; a non-positive length is refused."""
    gt = _helix(201)                        # 20 poses a second over 10 s
    t = gt.t_ns * 1e-9
    p = gt.p_w.copy()
    a, b = np.searchsorted(t, 4.0), np.searchsorted(t, 6.0)
    p[a:b] = p[a] + 1.2 * (gt.p_w[a:b] - gt.p_w[a])
    p[b:] += p[b - 1] + (gt.p_w[b] - gt.p_w[b - 1]) - gt.p_w[b]
    res = evaluate(gt.t_ns, p, gt.q_wxyz, gt, segments_s=2.0)
    pct = [s.length_pct for s in res.segments]
    assert [s.t0_s for s in res.segments] == [0.0, 2.0, 4.0, 6.0, 8.0]
    assert pct[2] == pytest.approx(20.0, abs=0.5)
    assert all(abs(x) < 0.5 for i, x in enumerate(pct) if i != 2)
    assert sum(s.n for s in res.segments) == res.n_matched
    still = GroundTruth(gt.t_ns, np.where((t < 2.0)[:, None], gt.p_w[0], gt.p_w), gt.q_wxyz)
    first = evaluate(still.t_ns, still.p_w, still.q_wxyz, still, segments_s=2.0).segments[0]
    assert first.path_m == 0.0 and np.isnan(first.length_pct)
    with pytest.raises(ValueError, match="positive"):
        evaluate(gt.t_ns, p, gt.q_wxyz, gt, segments_s=0.0)
    from vio.cli import main
    from vio.trajectory import write_tum
    est_file, gt_file = tmp_path / "est.txt", tmp_path / "gt.txt"
    write_tum(est_file, gt.t_ns, [gtsam.Pose3(gtsam.Rot3(), x) for x in p])
    write_tum(gt_file, gt.t_ns, [gtsam.Pose3(gtsam.Rot3(), x) for x in gt.p_w])
    assert main(["eval", str(est_file), str(gt_file), "--segments", "2"]) == 0
    out = capsys.readouterr().out
    assert "length vs truth [%]" in out and "+20.0" in out


def test_vio_run_prints_the_stretches_of_its_online_poses(capsys):
    """``vio run --segments 2`` on the real V1_01 tracks (6 s of them): the table follows the
    ATE lines, one row per 2 s; without ground truth (the shipped demo) a line says so; a
    non-positive length is a usage error."""
    from conftest import shared
    from vio.cli import main
    root = shared("euroc_V1_01_30s_features")
    assert main(["run", str(root), "--max-frames", "120", "--no-progress", "--segments", "2"]) == 0
    out = capsys.readouterr().out
    table = out[out.index("ATE RMSE"):].splitlines()
    head = next(i for i, line in enumerate(table) if line.startswith("stretch [s]"))
    assert [row.split()[0] for row in table[head + 1:head + 4]] == ["0.0-2.0", "2.0-4.0", "4.0-6.0"]
    assert main(["run", "--demo", "--max-frames", "30", "--no-progress", "--segments", "2"]) == 0
    assert "segments        not evaluated: no ground truth" in capsys.readouterr().out
    with pytest.raises(SystemExit) as err:
        main(["run", "--demo", "--segments", "0"])
    assert err.value.code == 2 and "argument --segments" in capsys.readouterr().err
