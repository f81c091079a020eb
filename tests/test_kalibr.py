"""Kalibr calibration (``vio.io.kalibr``): files written from EuRoC's sensor.yaml read
back to the same calibration and give the same run; every missing or malformed key is
a one-line error naming file and key. Ground truth that does not overlap the run is
reported in one line (``vio.evaluation.overlap_problem``)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from tests.conftest import shared
from vio.errors import DataError
from vio.evaluation import evaluate_files, overlap_problem
from vio.io.euroc import load_euroc
from vio.io.kalibr import read_camchain, read_kalibr_imu, write_camchain, write_kalibr_imu
from vio.io.load import load_dataset, load_groundtruth
from vio.io.types import GroundTruth
from vio.run import run_dataset
from vio.run_summary import summary
from vio.trajectory import write_tum


@pytest.fixture(scope="module")
def euroc_kalibr(tmp_path_factory):
    data = load_euroc(shared("euroc_MH_01_stereo_synimu"))
    d = tmp_path_factory.mktemp("kalibr")
    write_camchain(d / "camchain.yaml", [data.cam0.calib, data.cam1.calib], td_s=0.0025)
    write_kalibr_imu(d / "imu.yaml", data.imu_calib)
    return data, d


def test_roundtrip_matches_sensor_yaml(euroc_kalibr):
    data, d = euroc_kalibr
    kc, ki = read_camchain(d / "camchain.yaml"), read_kalibr_imu(d / "imu.yaml")
    assert kc.topics == ("/cam0/image_raw", "/cam1/image_raw") and kc.td_s == 0.0025
    for got, ref in zip(kc.cams, (data.cam0.calib, data.cam1.calib)):
        np.testing.assert_allclose(got.T_b_c.matrix(), ref.T_b_c.matrix(), atol=1e-12)
        assert (got.intrinsics, got.distortion, got.distortion_model, got.resolution) == \
               (ref.intrinsics, ref.distortion, ref.distortion_model, ref.resolution)
    assert ki.calib.gyro_noise_density == data.imu_calib.gyro_noise_density
    assert ki.calib.accel_random_walk == data.imu_calib.accel_random_walk
    assert ki.calib.rate_hz == 200.0 and ki.topic == "/imu0"
    folder = load_dataset(shared("euroc_MH_01_stereo_synimu"), calib=d / "camchain.yaml")
    assert folder.td_s == 0.0025 and folder.imu_calib.gyro_noise_density == data.imu_calib.gyro_noise_density
    assert folder.cam1.calib.intrinsics == data.cam1.calib.intrinsics


def test_cam1_from_T_cn_cnm1_and_nested_imu(euroc_kalibr, tmp_path):
    data, d = euroc_kalibr
    chain = yaml.safe_load((d / "camchain.yaml").read_text())
    del chain["cam1"]["T_cam_imu"]
    chain["cam0"]["distortion_model"] = "equidistant"
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(chain))
    kc = read_camchain(tmp_path / "c.yaml")
    np.testing.assert_allclose(kc.cams[1].T_b_c.matrix(), data.cam1.calib.T_b_c.matrix(), atol=1e-12)
    assert kc.cams[0].distortion_model == "equidistant"
    imu = yaml.safe_load((d / "imu.yaml").read_text())
    (tmp_path / "i.yaml").write_text(yaml.safe_dump({"imu0": {**imu, "T_i_b": np.eye(4).tolist()}}))
    assert read_kalibr_imu(tmp_path / "i.yaml").calib.gyro_random_walk == data.imu_calib.gyro_random_walk


def test_rolling_shutter_line_delay_round_trips(euroc_kalibr, tmp_path):
    """Kalibr's rolling-shutter ``line_delay`` (s per row) is the cameras' line time
    (the photometric and KLT modes' row times); a global-shutter camchain writes none."""
    import dataclasses
    data, d = euroc_kalibr
    assert "line_delay" not in (d / "camchain.yaml").read_text()
    cams = [dataclasses.replace(c, line_time_s=3.4e-5) for c in (data.cam0.calib, data.cam1.calib)]
    write_camchain(tmp_path / "rs.yaml", cams)
    assert [c.line_time_s for c in read_camchain(tmp_path / "rs.yaml").cams] == [3.4e-5, 3.4e-5]
    assert read_camchain(d / "camchain.yaml").cams[0].line_time_s == 0.0


@pytest.mark.parametrize("edit, words", [
    (lambda c: c["cam0"].pop("intrinsics"), "missing key cam0.intrinsics"),
    (lambda c: c["cam1"].pop("resolution"), "missing key cam1.resolution"),
    (lambda c: c["cam0"].update(T_cam_imu=[[1, 0, 0]]), "cam0.T_cam_imu must be a 4x4 matrix"),
    (lambda c: c["cam0"]["T_cam_imu"][0].__setitem__(0, 3.0), "cam0.T_cam_imu is not a rigid transform"),
    (lambda c: c["cam0"].update(distortion_model="fov"), "cam0.distortion_model 'fov' not in"),
    (lambda c: c["cam0"].update(camera_model="omni"), "cam0.camera_model 'omni' unsupported"),
    (lambda c: c["cam0"].update(distortion_coeffs=[0.1, "x", 0, 0]), "cam0.distortion_coeffs must be"),
    (lambda c: c["cam0"].update(timeshift_cam_imu="soon"), "cam0.timeshift_cam_imu must be a number"),
    (lambda c: c["cam1"].update(line_delay=0.002), "cam1.line_delay 0.002 s per row out of range"),
    (lambda c: c["cam0"].update(line_delay="fast"), "cam0.line_delay must be a number"),
    (lambda c: c.pop("cam0"), "missing key cam0"),
    (lambda c: (c["cam1"].pop("T_cam_imu"), c["cam1"].pop("T_cn_cnm1")), "missing key cam1.T_cn_cnm1"),
])
def test_camchain_errors_name_file_and_key(euroc_kalibr, tmp_path, edit, words):
    chain = yaml.safe_load((euroc_kalibr[1] / "camchain.yaml").read_text())
    edit(chain)
    path = tmp_path / "camchain.yaml"
    path.write_text(yaml.safe_dump(chain))
    with pytest.raises(DataError) as e:
        read_camchain(path)
    assert str(e.value).startswith(str(path)) and words in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("key, value, words", [
    ("gyroscope_noise_density", None, "missing key gyroscope_noise_density"),
    ("update_rate", None, "missing key update_rate"),
    ("accelerometer_random_walk", -1.0, "accelerometer_random_walk must be a positive number"),
    ("gyroscope_random_walk", "x", "gyroscope_random_walk must be a positive number"),
])
def test_imu_yaml_errors_name_file_and_key(euroc_kalibr, tmp_path, key, value, words):
    imu = yaml.safe_load((euroc_kalibr[1] / "imu.yaml").read_text())
    imu.pop(key) if value is None else imu.update({key: value})
    path = tmp_path / "imu.yaml"
    path.write_text(yaml.safe_dump(imu))
    with pytest.raises(DataError, match=words) as e:
        read_kalibr_imu(path)
    assert str(e.value).startswith(str(path))


def test_folder_with_kalibr_gives_the_sensor_yaml_run(tmp_path):
    """V1_01 feature tracks: Kalibr files written from sensor.yaml override it and the
    run is the same; timeshift_cam_imu becomes the initial td."""
    folder = shared("euroc_V1_01_30s_features")
    data = load_euroc(folder)
    write_camchain(tmp_path / "camchain.yaml", [data.cam0.calib])
    write_kalibr_imu(tmp_path / "imu.yaml", data.imu_calib)
    kal = load_dataset(folder, calib=tmp_path / "camchain.yaml", imu_calib=tmp_path / "imu.yaml")
    assert kal.td_s == 0.0 and kal.cam1 is None
    a = run_dataset(data, max_frames=120).arrays()
    b = run_dataset(kal, max_frames=120).arrays()
    assert len(a[0]) > 60
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], atol=1e-6)


def _gt(t0_s: float, n: int = 50) -> GroundTruth:
    t = (t0_s + np.arange(n) * 0.05) * 1e9
    p = np.c_[np.arange(n) * 0.1, np.sin(np.arange(n) * 0.2), np.zeros(n)]
    return GroundTruth(t.astype(np.int64), p, np.tile([1.0, 0, 0, 0], (n, 1)))


def test_groundtruth_without_overlap_is_one_line(tmp_path):
    gt, far = _gt(100.0), _gt(500.0)
    assert overlap_problem(gt.t_ns, gt) is None
    msg = overlap_problem(gt.t_ns, far)
    assert "does not overlap" in msg and "[500.000, 502.450] s" in msg
    res = run_dataset(load_euroc(shared("euroc_V1_01_30s_features")), max_frames=60)
    data = load_dataset(shared("euroc_V1_01_30s_features"), groundtruth=shared("euroc_imu_gt", "MH_03_medium"))
    lines = summary(res, data)
    assert any(line.startswith("ATE             not evaluated: ground truth") for line in lines)
    write_tum(tmp_path / "e.tum", gt.t_ns, [gt.pose(i) for i in range(len(gt))])
    (tmp_path / "far.txt").write_text("".join(f"{t * 1e-9:.9f} {p[0]} {p[1]} 0 0 0 0 1\n"
                                              for t, p in zip(far.t_ns, far.p_w)))
    with pytest.raises(ValueError, match="e.tum vs .*far.txt: ground truth .* does not overlap"):
        evaluate_files(tmp_path / "e.tum", tmp_path / "far.txt")
    assert evaluate_files(tmp_path / "e.tum", tmp_path / "e.tum").ate_rmse < 1e-9


def test_groundtruth_sources(tmp_path):
    folder = shared("euroc_MH_01_stereo_synimu")
    a = load_groundtruth(folder)
    b = load_groundtruth(folder / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    mocap = tmp_path / "mav0" / "mocap0"
    mocap.mkdir(parents=True)
    (mocap / "data.csv").write_text("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],"
                                    "q_RS_x [],q_RS_y [],q_RS_z []\n"
                                    "1000,1,2,3,1,0,0,0\n2000,1,2,4,1,0,0,0\n")
    gt = load_groundtruth(tmp_path)
    assert len(gt) == 2 and gt.p_w[1, 2] == 4.0
    with pytest.raises(DataError, match="not found"):
        load_groundtruth(tmp_path / "nope.txt")


def test_summary_names_a_rolling_shutter_and_its_lens():
    """The run summary's rolling-shutter line: the line time and readout, and whether a
    row's time is its sensor row through a lens (the camera has distortion coefficients)."""
    import dataclasses
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    res = run_dataset(data, max_frames=40)

    def line(**calib):
        cam0 = dataclasses.replace(data.cam0, calib=dataclasses.replace(data.cam0.calib, **calib))
        return [ln for ln in summary(res, dataclasses.replace(data, cam0=cam0)) if ln.startswith("rolling")]

    assert line(line_time_s=0.0) == []
    lens = line(line_time_s=3e-5, distortion_model="radial-tangential", distortion=(-0.28, 0.07, 0.0, 0.0))
    bare = line(line_time_s=3e-5, distortion_model="none", distortion=())
    assert lens[0].endswith("each row at its own time (its sensor row through the lens)"), lens
    assert bare[0].endswith("each row at its own time") and "30.0 us a row" in bare[0], bare
