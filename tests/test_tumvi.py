"""TUM-VI layout: equidistant fisheye 512x512 calibrated by ``dso/camchain.yaml`` (no
sensor.yaml), ``mocap0`` ground truth; a short TUM-VI-like render (``vio.sim.fisheye``)
loads, runs in stereo and mono, and ``vio eval`` reads its ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from vio.cli import main
from vio.frontend.camera import Camera
from vio.io.load import load_dataset
from vio.sim import SimConfig
from vio.sim.fisheye import fisheye_camera, pinhole_for, simulate_tumvi
from vio.sim.render import sim_camera


@pytest.fixture(scope="module")
def tumvi(tmp_path_factory):
    return simulate_tumvi(tmp_path_factory.mktemp("tumvi") / "room", SimConfig(seconds=3.0, seed=1))


def test_fisheye_remap_follows_the_equidistant_model():
    """A fisheye pixel maps to the pinhole pixel of the same ray (via cv2.fisheye)."""
    fish = fisheye_camera(sim_camera("cam0"))
    pin, mx, my = pinhole_for(fish)
    cam = Camera(fish)
    px = np.array([[256.0, 256.0], [100.0, 300.0], [400.0, 120.0], [30.0, 256.0]])
    uv = cam.undistort_px(px)                      # normalized pinhole coordinates
    f, _, c, _ = pin.intrinsics
    inside = mx[px[:, 1].astype(int), px[:, 0].astype(int)] >= 0
    np.testing.assert_allclose(mx[px[:, 1].astype(int), px[:, 0].astype(int)][inside],
                               (f * uv[:, 0] + c)[inside], atol=1e-3)
    assert inside[:3].all() and not inside[3]      # the far left edge is beyond the lens FOV


def test_tumvi_folder_loads_runs_stereo_and_mono(tumvi, tmp_path, capsys):
    data = load_dataset(tumvi)
    assert not (tumvi / "mav0" / "cam0" / "sensor.yaml").exists()
    assert data.kind == "stereo" and data.groundtruth is not None
    assert data.cam0.calib.distortion_model == "equidistant" and data.cam0.calib.resolution == (512, 512)
    assert data.imu_calib.rate_hz == 200.0
    for mode, tol in (("stereo", 0.03), ("mono", 0.05)):
        out = tmp_path / f"{mode}.tum"
        assert main(["run", str(tumvi), "--mode", mode, "--out", str(out), "--no-progress"]) == 0
        text = capsys.readouterr().out
        ate = float(text.split("ATE RMSE")[1].split()[0])
        assert ate < tol, (mode, ate)
        assert main(["eval", str(out), str(tumvi)]) == 0
        assert f"ATE RMSE        {ate:.4f}" in capsys.readouterr().out
