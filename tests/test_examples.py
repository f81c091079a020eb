"""The examples stay runnable: the sample config loads strictly, the custom-factor
example's Jacobian check passes."""

from __future__ import annotations

import runpy
from pathlib import Path

from vio.run import default_config, load_config

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_example_config_loads_strictly():
    cfg = load_config(EXAMPLES / "config.yaml")
    assert cfg.backend.solver.lag_s == 2.5 and cfg.frontend.max_features == 150
    d = default_config("features")     # the fault groups as listed are the defaults
    assert (cfg.backend.health, cfg.backend.bridge, cfg.backend.realign) == (
        d.backend.health, d.backend.bridge, d.backend.realign)


def test_photometric_td_example_loads_strictly():
    cfg = load_config(EXAMPLES / "photometric_td.yaml", mode="hybrid")
    assert cfg.direct.points.exposure_td and cfg.backend.solver.relinearize_skip == 1
    assert cfg.backend.calib.estimate_td and cfg.backend.calib.td_feedback_after_s == 3.0


def test_custom_factor_example_runs(capsys):
    runpy.run_path(str(EXAMPLES / "custom_factor.py"), run_name="__main__")
    assert "whitened block" in capsys.readouterr().out
