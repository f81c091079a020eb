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
