"""The examples stay runnable: the sample config loads strictly, the custom-factor
example's Jacobian check passes."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest

from vio.errors import ConfigError
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


@pytest.mark.parametrize("yaml_text, words", [
    ("backend:\n  solver:\n    lag_s: -3\n", "backend.solver: SolverConfig.lag_s must be > 0"),
    ("backend:\n  vision:\n    pixel_sigma: 0\n", "backend.vision: VisionConfig.pixel_sigma must be > 0"),
    ("backend:\n  health:\n    min_inlier_ratio: 1.5\n", "HealthConfig.min_inlier_ratio must be in [0, 1]"),
    ("backend:\n  init:\n    dynamic:\n      window_s: .nan\n", "DynamicInitConfig.window_s must be a number"),
    ("backend:\n  bridge:\n    accel_density: -1\n", "BridgeConfig.accel_density must be > 0"),
    ("backend:\n  keyframe:\n    min_tracked: -2\n", "KeyframeConfig.min_tracked must be >= 0"),
    ("backend:\n  vision:\n    min_depth_m: 5\n    max_depth_m: 2\n", "max_depth_m must exceed min_depth_m"),
])
def test_out_of_range_backend_values_name_file_and_key(tmp_path, yaml_text, words):
    """A value the estimator cannot use (a negative window, a zero sigma) is a config
    error naming the file and the key, not a solver error mid-run (``vio.config.check_ranges``)."""
    path = tmp_path / "bad.yaml"
    path.write_text(yaml_text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(path) in str(err.value) and words in str(err.value)


def test_signed_and_optional_values_stay_allowed(tmp_path):
    path = tmp_path / "ok.yaml"
    path.write_text("td_s: -0.012\nbackend:\n  solver:\n    point_relinearize_threshold: null\n"
                    "  health:\n    max_speed: .inf\n")
    cfg = load_config(path)
    assert cfg.td_s == -0.012 and cfg.backend.solver.point_relinearize_threshold is None
    assert cfg.backend.health.max_speed == float("inf")


@pytest.mark.parametrize("value", ["0", "-5", "x"])
def test_frame_counts_on_the_command_line_must_be_positive(capsys, value):
    """``--max-frames 0`` ran every frame and ``-5`` all but the last five (a slice);
    both are now usage errors."""
    from vio.cli import main
    with pytest.raises(SystemExit) as err:
        main(["run", "--demo", "--max-frames", value])
    assert err.value.code == 2 and "argument --max-frames" in capsys.readouterr().err
