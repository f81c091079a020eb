"""The photometric modes' td from a stereo pre-pass (``vio.td_prepass``,
``PipelineConfig.td_prepass_s``): its configuration, its frame range and refusal, and
end to end on a rendered stereo sequence whose camera runs 8 ms behind its stamps."""

from __future__ import annotations

import dataclasses
import logging
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from vio.imu import ImuNoiseConfig
from vio.io.euroc import load_euroc
from vio.run import RunResult, default_config, load_config, run_dataset
from vio.td_prepass import prepass_config, prepass_td


def _cfg(**kw):
    cfg = default_config("hybrid")
    return dataclasses.replace(cfg, **kw)


def test_photometric_modes_default_to_the_prepass_and_yaml_turns_it_off(tmp_path):
    assert default_config("direct").td_prepass_s > 0 and default_config("hybrid").td_prepass_s > 0
    assert default_config("stereo").td_prepass_s == 0 and default_config("features").td_prepass_s == 0
    y = tmp_path / "c.yaml"
    y.write_text("td_prepass_s: 0.0\n")
    assert load_config(y, mode="hybrid").td_prepass_s == 0.0
    y.write_text("td_prepass_s: -1.0\n")
    with pytest.raises(ValueError, match="td_prepass_s"):
        load_config(y, mode="hybrid")


def test_prepass_config_is_stereo_with_the_runs_sync_layer_and_imu():
    imu = dataclasses.replace(ImuNoiseConfig(), scale_walk=3.0)
    cfg = _cfg(td_s=0.012, imu_lookahead_s=0.03)
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, imu=imu))
    stereo = default_config("stereo")
    p = prepass_config(cfg, stereo)
    assert p.td_s == 0.012 and p.imu_lookahead_s == 0.03 and p.td_prepass_s == 0.0
    assert p.backend.imu == imu and p.backend.calib.estimate_td
    # everything else is stereo mode's: its landmarks, keyframes and extrinsic calibration
    assert p.backend.vision == stereo.backend.vision and p.backend.keyframe == stereo.backend.keyframe
    assert p.frontend.max_features == stereo.frontend.max_features
    # direct mode holds td in its own run, but the pre-pass estimates it
    assert prepass_config(default_config("direct"), stereo).backend.calib.estimate_td


def _fake(t_first_pose_s: float, t_last_pose_s: float, td_s: float):
    """A ``run`` stand-in recording its arguments; its outputs span the given times."""
    calls = []

    def run(data, cfg, max_frames=None, mode="auto"):
        calls.append((cfg, max_frames, mode))
        res = RunResult()
        for t in (t_first_pose_s, t_last_pose_s):
            res.outputs.append(SimpleNamespace(t_ns=int(t * 1e9), td_s=td_s))
        return res
    return run, calls


def test_prepass_runs_stereo_over_the_first_seconds_and_takes_its_td():
    t = np.arange(0, 20_000_000_000, 50_000_000)      # 20 Hz, 20 s
    run, calls = _fake(0.5, 6.0, 0.0117)
    assert prepass_td(None, _cfg(td_prepass_s=6.0), default_config("stereo"), t, run) == 0.0117
    cfg, n, mode = calls[0]
    assert mode == "stereo" and n == 121 and cfg.td_prepass_s == 0.0     # frames at 0, 0.05, ..., 6.0 s
    prepass_td(None, _cfg(td_prepass_s=6.0), default_config("stereo"), t[:40], run)
    assert calls[1][1] == 40                                               # never past --max-frames


def test_prepass_that_posed_too_little_keeps_the_sync_layers_td(caplog):
    t = np.arange(0, 20_000_000_000, 50_000_000)
    run, _ = _fake(4.0, 6.0, 0.03)
    with caplog.at_level(logging.WARNING, logger="vio.td_prepass"):
        assert prepass_td(None, _cfg(td_prepass_s=6.0, td_s=0.002), default_config("stereo"), t, run) is None
    assert "posed 2.0 s of the first 6.0 s" in caplog.text and "2.00 ms" in caplog.text
    empty = lambda *a, **k: RunResult()   # noqa: E731  (never initialized)
    assert prepass_td(None, _cfg(td_prepass_s=6.0), default_config("stereo"), t, empty) is None


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["hybrid", "direct"])
def test_photometric_run_starts_at_the_prepass_td(tmp_path_factory, mode):
    """A 6-s half-resolution render whose camera runs 8 ms behind its stamps, synced at 0:
    the stereo pre-pass finds td within 1.5 ms, and the photometric run's sync layer
    applies it from its first frame (without the pre-pass it holds 0)."""
    from vio.sim import simulate
    from vio.sim.config import SimConfig
    root = tmp_path_factory.getbasetemp() / "td_prepass_sim"
    if not (root / "mav0").exists():
        simulate(root, SimConfig(seconds=6.0, seed=5, image_scale=0.5, td_s=0.008))
    data = load_euroc(root)
    d = default_config(mode).direct
    d = dataclasses.replace(d, select=dataclasses.replace(d.select, n_points=200, block=16),
                            points=dataclasses.replace(d.points, max_points=80))
    cfg = dataclasses.replace(default_config(mode), direct=d, td_prepass_s=4.0)
    res = run_dataset(data, cfg, mode=mode)
    assert len(res.outputs) == len(data.cam0.t_ns)
    applied = (res.outputs[0].t_ns - int(data.cam0.t_ns[0])) * 1e-9      # the sync layer's offset
    assert abs(applied - 0.008) < 0.0015, f"applied {applied * 1e3:.2f} ms"
    assert abs(res.outputs[-1].td_s - 0.008) < 0.002
    held = run_dataset(data, dataclasses.replace(cfg, td_prepass_s=0.0), mode=mode)
    assert held.outputs[0].t_ns == int(data.cam0.t_ns[0])
    assert isinstance(res.outputs[0].T_w_b, gtsam.Pose3)
