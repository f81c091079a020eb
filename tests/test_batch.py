"""``vio batch`` on a local Ray with 2 workers: small real runs, a failing run recorded
with its error, the three result files, one trajectory and one plot per run."""

from __future__ import annotations

import csv
import json
import os

import pytest

from tests.conftest import shared
from vio.cli import main
from vio.errors import ConfigError

pytest.importorskip("ray")


@pytest.fixture(scope="module")
def ray_local():
    import ray
    yield
    ray.shutdown()


def _crash(x: int) -> int:
    if x == 1:
        os._exit(3)       # a worker that dies (e.g. a segfault): recorded, not fatal
    return x * 10


def test_batch_matrix_on_local_ray(tmp_path, ray_local, capsys):
    feats = shared("euroc_V1_01_30s_features")
    (tmp_path / "short_lag.yaml").write_text("backend:\n  solver:\n    lag_s: 2.0\n")
    (tmp_path / "spec.yaml").write_text(
        f"datasets:\n  - {feats}\n  - missing_folder\nconfigs: [null, short_lag.yaml]\nmax_frames: 50\n")
    out = tmp_path / "out"
    rc = main(["batch", str(tmp_path / "spec.yaml"), "--out", str(out), "--workers", "2", "--no-progress"])
    assert rc == 0
    assert "runs            4 (2 ok, 2 failed)" in capsys.readouterr().out
    recs = json.loads((out / "results.json").read_text())
    assert [r["status"] for r in recs] == ["ok", "ok", "failed", "failed"]
    for key in ("dataset", "mode", "config", "status", "ate_rmse_m", "rpe_trans_rmse_m", "td_ms",
                "ms_per_frame", "realtime_factor", "init_time_s", "restarts"):
        assert all(key in r for r in recs)
    ok = recs[:2]
    assert all(r["mode"] == "features" and 0 < r["ate_rmse_m"] < 0.05 and r["ms_per_frame"] > 0 for r in ok)
    assert all(0 <= r["init_time_s"] < 2.5 and r["restarts"] == 0 for r in ok)
    assert ok[0]["config"] == "default" and ok[1]["config"].endswith("short_lag.yaml")
    assert all(os.path.isfile(r["trajectory"]) and os.path.isfile(r["plot"]) for r in ok)
    assert "missing_folder: dataset folder not found" in recs[2]["error"]
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert len(rows) == 4 and rows[2]["status"] == "failed"
    md = (out / "results.md").read_text()
    assert "4 runs, 2 ok" in md and md.count("\n| 00") == 4


def test_map_jobs_records_a_dead_worker(ray_local):
    import sys

    from ray import cloudpickle
    from vio.batch import map_jobs
    cloudpickle.register_pickle_by_value(sys.modules[__name__])   # pytest's module name is not importable
    res = map_jobs(_crash, [0, 1, 2], workers=2, progress=False)
    assert res[0] == 0 and res[2] == 20
    assert "error" in res[1]


def test_spec_errors(tmp_path):
    from vio.batch import read_spec
    (tmp_path / "s.yaml").write_text("datasets: [a]\nmode: [stereo]\n")
    with pytest.raises(ConfigError, match=r"s.yaml: unknown key\(s\) \['mode'\]"):
        read_spec(tmp_path / "s.yaml", tmp_path)
    (tmp_path / "s.yaml").write_text("datasets:\n  - {path: a.bag, calib: c.yaml, imu: i.yaml}\n")
    with pytest.raises(ConfigError, match=r"datasets\[0\] must be"):
        read_spec(tmp_path / "s.yaml", tmp_path)
    (tmp_path / "s.yaml").write_text("datasets:\n  - {path: a.bag, calib: c.yaml}\nmodes: [mono, stereo]\n")
    jobs = read_spec(tmp_path / "s.yaml", tmp_path)
    assert [j.mode for j in jobs] == ["mono", "stereo"]
    assert jobs[0].dataset["calib"] == str(tmp_path / "c.yaml")


def test_unreachable_cluster_is_one_line(tmp_path, capsys):
    (tmp_path / "s.yaml").write_text("datasets: [a]\n")
    rc = main(["batch", str(tmp_path / "s.yaml"), "--out", str(tmp_path / "o"), "--address", "127.0.0.1:9"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--address 127.0.0.1:9: no Ray cluster answers" in err and err.count("\n") == 1
