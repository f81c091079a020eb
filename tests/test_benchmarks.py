"""Smoke tests of the benchmark suite (benchmarks/): the GTSAM-native baseline runs on
real data and the report renders. No timing assertions (numbers live in benchmarks/).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import report  # noqa: E402
from conftest import shared  # noqa: E402


@pytest.fixture(scope="module")
def v101_150():
    """Our run and the baseline on the first 150 frames of the real V1_01 tracks."""
    from baseline_gtsam import Schedule, record_schedule, run_baseline
    from vio.io.euroc import load_euroc
    from vio.pipeline import PipelineConfig
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    cfg = PipelineConfig()
    ours, sched = record_schedule(data, cfg, max_frames=150)
    sched = Schedule.from_json(json.loads(json.dumps(sched.to_json())))  # JSON round trip
    base = run_baseline(data, sched, cfg, max_frames=150)
    return data, ours, sched, base


def test_baseline_runs_on_our_keyframes_and_scores_finite_ate(v101_150):
    from vio.evaluation import evaluate
    data, ours, sched, base = v101_150
    # same keyframes: every keyframe the baseline inserted is one of ours, and all of ours are used
    kf_base = {o.t_ns for o in base.outputs if o.keyframe}
    assert kf_base == set(sched.keyframes), "baseline keyframes differ from the schedule"
    assert base.keyframes == ours.keyframes
    assert base.recoveries == 0
    # one online estimate per frame from the initial keyframe on
    assert base.outputs[0].t_ns == sched.init.t_ns
    assert len(base.outputs) == base.frames_in - sum(t < sched.init.t_ns for t in data.cam0.t_ns[:150])
    e = evaluate(*base.arrays(), data.groundtruth)
    assert math.isfinite(e.ate_rmse)
    # 150 frames (7.5 s, ~2.7 m path): a working VIO stays within 10 cm
    assert e.ate_rmse < 0.10, f"baseline ATE {e.ate_rmse:.3f} m"


def test_schedule_json_round_trip(v101_150):
    _, _, sched, _ = v101_150
    back = type(sched).from_json(json.loads(json.dumps(sched.to_json())))
    assert back.keyframes == sched.keyframes and back.td_s == sched.td_s
    assert back.init.T_w_b.equals(sched.init.T_w_b, 1e-12)
    np.testing.assert_allclose(back.init.bias.vector(), sched.init.bias.vector(), atol=1e-15)


TINY = {
    "machine": {"cpu": "Test CPU", "cores": 2, "python": "3.11", "gtsam": "4.3.0", "numpy": "2.0",
                "commit": "abc123"},
    "created": "2025-01-01 00:00:00", "quick": True,
    "accuracy": {
        "runs": [{"dataset": "SEQ@0+20s/td5ms", "mode": "features", "group": "SEQ@0+20s", "twin": "SEQ@0+20s/td0ms",
                  "td_true_ms": 5.0, "overrides": {},
                  "ours": {"ate_rmse": 0.05, "ate_pct": 0.5, "path_m": 10.0, "rpe_trans": 0.02, "rpe_rot_deg": 0.3,
                           "recoveries": 0, "keyframes": 100, "frame_ms": {"mean": 5.0, "p50": 1.0, "p95": 20.0,
                                                                           "max": 40.0},
                           "rtf": 10.0, "peak_rss_mb": 250.0, "td_ms": 3.0, "td_err_ms": -2.0},
                  "baseline": {"ate_rmse": 0.1, "ate_pct": 1.0, "path_m": 10.0, "recoveries": 1,
                               "frame_ms": {"mean": 2.5, "p50": 0.5, "p95": 9.0, "max": 12.0}, "rtf": 20.0,
                               "peak_rss_mb": 200.0},
                  "ratio": {"ate": 0.5, "time": 2.0}}],
        "td": [{"group": "SEQ@0+20s", "td_true_ms": 5.0, "td_est_ms": 3.0, "td0_est_ms": -1.0,
                "raw_err_ms": -2.0, "diff_ms": 4.0, "diff_err_ms": -1.0}],
        "skipped": {"stereo": "not wired"}},
}


def test_report_renders_tables_from_tiny_json():
    md = report.render(json.loads(json.dumps(TINY)))
    assert "Test CPU, 2 cores" in md and "gtsam 4.3.0" in md
    row = next(line for line in md.splitlines() if line.startswith("| SEQ@0+20s/td5ms | 10.0"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:5] == ["0.050", "0.100", "0.50"]       # ATE ours, baseline, ratio
    assert "| SEQ@0+20s | 5.0 | 3.00 | -1.00 | -2.00 | 4.00 | -1.00 |" in md
    assert "5.0 / 1.0 / 20.0 / 40.0" in md                 # ours ms/frame mean/p50/p95/max
    assert "`stereo` (not wired)" in md


def test_readme_section_only_between_markers(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{report.START}\nold\n{report.END}\noutro\n")
    assert report.update_readme(readme, report.readme_section(TINY))
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{report.END}\noutro\n")
    assert "old" not in text and "| SEQ@0+20s/td5ms | 0.050 | 0.100 | 5.0 | 2.5 |" in text
    plain = tmp_path / "PLAIN.md"
    plain.write_text("no markers here\n")
    assert not report.update_readme(plain, "new")
    assert plain.read_text() == "no markers here\n"
    assert "markers" in capsys.readouterr().out
