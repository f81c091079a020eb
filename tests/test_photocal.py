"""Photometric calibration of the direct modes (``vio.direct.photocal``): DSO's file
formats, the irradiance it recovers, discovery next to a camera's data.csv, the radial
fallback and the errors that name the file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vio.direct.keyframe import StereoRig
from vio.direct.photocal import (PhotoCalConfig, PhotometricCalibration, load_calibration,
                                 radial_vignette, read_pcalib)
from vio.errors import ConfigError


def _camera(tmp_path, shape=(48, 64)):
    """A response G(x) = 255 (x / 255)^(1/2.2) and a radial vignette written in DSO's
    formats, and the raw image of a known irradiance through them."""
    d = tmp_path / "cam0"
    d.mkdir()
    x = np.arange(256) / 255.0
    (d / "pcalib.txt").write_text(" ".join(f"{v:.9f}" for v in 3.0 * x ** 2.2 + 0.5))  # affine of G^-1
    V = radial_vignette(shape, -0.4, 0.0)
    cv2.imwrite(str(d / "vignette.png"), np.round(V * 65535).astype(np.uint16))
    rng = np.random.default_rng(0)
    B = rng.uniform(20, 200, shape)
    raw = np.round(255.0 * ((V * B) / 255.0) ** (1 / 2.2)).astype(np.uint8)
    (d / "data.csv").write_text("#timestamp [ns],filename\n")
    return d, B, raw


def test_files_next_to_the_camera_recover_the_irradiance(tmp_path):
    d, B, raw = _camera(tmp_path)
    cal = load_calibration(d, raw.shape, PhotoCalConfig())
    assert not cal.identity and "pcalib.txt" in cal.source and "vignette.png" in cal.source
    out = cal.apply(raw)
    # 8-bit quantization of a gamma curve: ~1.5% relative at the dark end
    np.testing.assert_allclose(out, B, rtol=0.03, atol=1.0)
    assert load_calibration(d, raw.shape, PhotoCalConfig(use_files=False)).identity
    assert load_calibration(None, raw.shape, PhotoCalConfig()).identity


def test_radial_model_without_a_file(tmp_path):
    cal = load_calibration(tmp_path, (48, 64), PhotoCalConfig(vignette_poly=(-0.3, 0.0)))
    assert cal.inv_response is None and cal.source == "radial vignetting model"
    V = cal.vignette
    assert V.max() == pytest.approx(1.0) and V[0, 0] == pytest.approx(0.7 / 1.0, rel=0.02)
    img = np.full((48, 64), 100, np.uint8)
    out = cal.apply(img)
    assert out[24, 32] < out[0, 0]        # the dark corner is brightened


def test_rig_corrects_before_undistorting(tmp_path):
    from vio.sim.render import sim_camera
    d, B, raw = _camera(tmp_path, (480, 752))
    cal = load_calibration(d, raw.shape, PhotoCalConfig())
    cam = sim_camera("cam0")
    rig = StereoRig(cam, sim_camera("cam1"), cal, PhotometricCalibration())
    assert not any(cam.distortion)                  # the remap is then a no-op
    left, right = rig.undistort(raw, raw)
    np.testing.assert_allclose(left, cal.apply(raw))
    np.testing.assert_array_equal(right, raw)       # cam1 has no calibration


@pytest.mark.parametrize("text,msg", [("1 2 3", "expected 256"), ("a b", "not a list"),
                                      (" ".join(["1"] * 256), "increase")])
def test_bad_pcalib_names_the_file(tmp_path, text, msg):
    p = tmp_path / "pcalib.txt"
    p.write_text(text)
    with pytest.raises(ConfigError, match=msg) as e:
        read_pcalib(p)
    assert str(p) in str(e.value)
    with pytest.raises(ConfigError, match="not found"):
        load_calibration(tmp_path, (4, 4), PhotoCalConfig(pcalib=str(tmp_path / "missing.txt")))
