"""EuRoC reader: all shared real datasets load; broken copies give file:line errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import shared
from vio.errors import DataError
from vio.io.euroc import LoadOptions, load_euroc, read_image
from vio.trajectory import interpolate_pose


def test_feature_track_dataset_loads():
    d = load_euroc(shared("euroc_V1_01_30s_features"))
    assert d.kind == "features" and len(d.imu) == 6001 and len(d.cam0) == 601
    assert len(d.features) == 601 and sum(len(f.ids) for f in d.features) == 13316
    assert len({int(i) for f in d.features for i in f.ids}) == 307
    assert d.groundtruth is not None and d.groundtruth.bg is not None
    assert abs(d.groundtruth.bg[0, 2] - 0.077) < 0.001       # V1_01 gyro bias z
    assert d.imu_calib.gyro_noise_density == pytest.approx(1.6968e-4)
    fx = d.cam0.calib.intrinsics[0]
    assert fx == pytest.approx(458.654)
    # velocity of a continuing track is a finite backward difference
    moving = np.concatenate([f.velocity for f in d.features[1:50]])
    assert np.isfinite(moving).all() and np.abs(moving).max() > 0
    assert d.warnings == ()


def test_track_velocities_candidates_median_and_short_tracks():
    """vio.io.features.track_velocities on tracks interleaved across frames: a quadratic
    track (every candidate exact) gets its derivative at every observation, also when a
    gross outlier sits in it (the median of four candidates around it); two-frame tracks
    their plain difference; a single observation zero; the frames' own order kept."""
    from vio.io.features import track_velocities
    from vio.io.types import FeatureFrame
    t = 0.05 * np.arange(12)
    u = lambda tt: np.stack([0.1 + 0.4 * tt - 0.3 * tt ** 2, -0.2 + 0.1 * tt + 0.5 * tt ** 2], -1)
    du = lambda tt: np.stack([0.4 - 0.6 * tt, 0.1 + 1.0 * tt], -1)
    frames = []
    for i, ti in enumerate(t):
        ids, uv = [7, 3], [u(ti), u(ti) + 0.01]          # track 3 carries an outlier at frame 6
        if i == 6:
            uv[1] = uv[1] + 0.05
        if i in (4, 5):
            ids.append(11); uv.append(np.array([0.02 * i, 0.0]))     # two frames
        if i == 9:
            ids.append(5); uv.append(np.array([0.3, 0.3]))           # one frame
        ids, uv = np.array(ids[::-1]), np.array(uv[::-1])            # not sorted by id
        frames.append(FeatureFrame(int(ti * 1e9), ids, uv, np.zeros((len(ids), 2)), np.full(len(ids), np.nan)))
    track_velocities(frames)
    for i, fr in enumerate(frames):
        vel = dict(zip(fr.ids.tolist(), fr.velocity))
        np.testing.assert_allclose(vel[7], du(t[i]), atol=1e-9)
        if abs(i - 6) > 3:     # the outlier is no candidate's input there
            np.testing.assert_allclose(vel[3], du(t[i]), atol=1e-9)
        else:                  # ... and one of two to four there: the median stays near
            assert np.abs(vel[3] - du(t[i])).max() < 0.5, (i, vel[3])
        if 11 in vel:
            np.testing.assert_allclose(vel[11], [0.4, 0.0], atol=1e-9)
        if 5 in vel:
            assert (vel[5] == 0).all()


def test_static_stereo_dataset_loads_lazily():
    d = load_euroc(shared("euroc_V1_01_static_stereo"))
    assert d.kind == "stereo" and len(d.cam0) == len(d.cam1) == 95
    img = read_image(d.cam0.files[0])
    assert img.shape == (480, 752) and img.dtype == np.uint8
    assert d.cam1.calib.T_b_c.translation()[1] == pytest.approx(0.0453689425024)
    baseline = np.linalg.norm(d.cam0.calib.T_b_c.between(d.cam1.calib.T_b_c).translation())
    assert baseline == pytest.approx(0.110, abs=0.002)


@pytest.mark.parametrize("seq", ["MH_03_medium", "MH_04_difficult", "MH_05_difficult",
                                 "V1_02_medium", "V1_03_difficult", "V2_01_easy",
                                 "V2_02_medium", "V2_03_difficult"])
def test_imu_gt_sequences_load(seq):
    d = load_euroc(shared("euroc_imu_gt", seq))
    assert d.kind == "imu" and len(d.imu) > 15000
    gt = d.groundtruth
    assert len(gt) > 1000 and np.allclose(np.linalg.norm(gt.q_wxyz, axis=1), 1.0)
    mid = int(gt.t_ns[0] + (gt.t_ns[-1] - gt.t_ns[0]) // 2) + 1234
    interpolate_pose(gt, mid)  # inside the span
    if seq == "MH_03_medium":
        assert gt.bg is None  # TUM ground truth has no biases
        from vio.run import resolve_mode     # nothing to run on: the error names the folder and `vio tracks`
        with pytest.raises(ValueError, match=r"MH_03_medium: no camera data .*vio tracks"):
            resolve_mode(d, "auto")


# ---------------------------------------------------------------- broken copies

def _copy(tmp_path: Path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(shared("euroc_V1_01_30s_features"), dst)
    for p in dst.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    return dst


def _edit(path: Path, line: int, new: str | None) -> None:
    lines = path.read_text().splitlines()
    if new is None:
        del lines[line - 1]
    else:
        lines[line - 1] = new
    path.write_text("\n".join(lines) + "\n")


def _expect(root: Path, file_part: str, line: int | None, words: str, **opts) -> None:
    with pytest.raises(DataError) as exc:
        load_euroc(root, LoadOptions(**opts))
    msg = str(exc.value)
    assert "\n" not in msg and file_part in msg and words in msg, msg
    if line is not None:
        assert f":{line}:" in msg, msg


def test_missing_folder_and_files(tmp_path):
    _expect(tmp_path / "nope", "nope", None, "not found")
    root = _copy(tmp_path)
    (root / "mav0/imu0/data.csv").unlink()
    _expect(root, "imu0/data.csv", None, "file not found")


@pytest.mark.parametrize("line,new,words", [
    (5, "1403715273277143040,0.1,0.2", "expected 6 values"),
    (6, "1403715273282143040,0.1,abc,0.3,1,2,3", "'abc' is not a number"),
    (7, "1403715273287143040,0.1,nan,0.3,1,2,3", "non-finite"),
    (8, "1403715273287143040,0.1,0.2,0.3,1,2,3", "duplicate timestamp"),
    (9, "1403715273200000000,0.1,0.2,0.3,1,2,3", "decreasing timestamp"),
    (10, "14037152.5e3,0.1,0.2,0.3,1,2,3", "not an integer"),
])
def test_malformed_imu_rows(tmp_path, line, new, words):
    root = _copy(tmp_path)
    if "duplicate" in words:  # make line 8 repeat line 7's stamp
        prev = (root / "mav0/imu0/data.csv").read_text().splitlines()[line - 2].split(",")[0]
        new = prev + ",0.1,0.2,0.3,1,2,3"
    _edit(root / "mav0/imu0/data.csv", line, new)
    _expect(root, "imu0/data.csv", line, words)


def test_imu_gap_is_reported_not_fatal(tmp_path):
    root = _copy(tmp_path)
    path = root / "mav0/imu0/data.csv"
    lines = path.read_text().splitlines()
    del lines[100:120]  # 100 ms hole
    path.write_text("\n".join(lines) + "\n")
    d = load_euroc(root)
    assert len(d.warnings) == 1 and "IMU gap of 105.0 ms" in d.warnings[0]


def test_camera_outside_imu_span(tmp_path):
    root = _copy(tmp_path)
    path = root / "mav0/imu0/data.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:1] + lines[30:]) + "\n")  # IMU starts later
    _expect(root, "cam0/data.csv", 2, "outside the IMU span")
    d = load_euroc(root, LoadOptions(trim_to_imu=True))
    assert len(d.cam0) < 601 and any("dropped" in w for w in d.warnings)
    assert d.features[0].t_ns >= d.imu.t_ns[0]
    late = [f"{int(r.split(',', 1)[0]) + 100 * 10**9},{r.split(',', 1)[1]}" for r in lines[1:]]
    path.write_text("\n".join(lines[:1] + late) + "\n")   # the IMU only after the last frame
    with pytest.raises(DataError, match=r"cam0/data.csv: none of its 601 frames lies inside the IMU span"):
        load_euroc(root, LoadOptions(trim_to_imu=True))


def test_camera_list_without_frames(tmp_path):
    root = _copy(tmp_path)
    path = root / "mav0/cam0/data.csv"
    path.write_text(path.read_text().splitlines()[0] + "\n")
    with pytest.raises(DataError, match=r"cam0/data.csv: lists no frames"):
        load_euroc(root)


@pytest.mark.parametrize("line,new,words", [
    (3, "1403715273262142976,0,7,0.1", "expected 5 fields"),
    (3, "1403715273262142976,0,7,0.1,inf", "non-finite"),
    (3, "1403715273262142976,0,1,0.1,0.2", "landmark 1 observed twice"),
    (-1, "1403715303262142977,600,7,0.1,0.2", "not a frame of cam0/data.csv"),
])
def test_malformed_feature_rows(tmp_path, line, new, words):
    root = _copy(tmp_path)
    path = root / "mav0/cam0/features.csv"
    if line == -1:  # append an observation at a stamp that is no frame
        path.write_text(path.read_text() + new + "\n")
        line = len(path.read_text().splitlines())
    else:
        _edit(path, line, new)
    _expect(root, "features.csv", line, words)


@pytest.mark.parametrize("old,new,words", [
    ("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296]",
     "intrinsics must have 4 values"),
    ("0.0148655429818, -0.999880929698", "0.5148655429818, -0.999880929698",
     "not a rigid transform"),
    ("distortion_model: radial-tangential", "distortion_model: fisheye62",
     "distortion_model 'fisheye62'"),
    ("rate_hz: 20", "rate_hz: abc", "rate_hz must be a positive number, found 'abc'"),
])
def test_wrong_camera_calibration(tmp_path, old, new, words):
    root = _copy(tmp_path)
    path = root / "mav0/cam0/sensor.yaml"
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    _expect(root, "cam0/sensor.yaml", None, words)


@pytest.mark.parametrize("old,new,words", [
    ("gyroscope_noise_density: 1.6968e-04", "gyroscope_noise_density: -1", "must be a positive number"),
    ("rate_hz: 200", "rate_hz: -5", "rate_hz must be a positive number, found -5"),
])
def test_wrong_imu_calibration(tmp_path, old, new, words):
    root = _copy(tmp_path)
    path = root / "mav0/imu0/sensor.yaml"
    assert old in path.read_text()
    path.write_text(path.read_text().replace(old, new))
    _expect(root, "imu0/sensor.yaml", None, words)


def test_groundtruth_bad_quaternion(tmp_path):
    root = _copy(tmp_path)
    path = root / "mav0/state_groundtruth_estimate0/data.csv"
    lines = path.read_text().splitlines()
    parts = lines[4].split(",")
    parts[4] = "0.9"
    lines[4] = ",".join(parts)
    path.write_text("\n".join(lines) + "\n")
    _expect(root, "state_groundtruth_estimate0/data.csv", 5, "quaternion norm")


def test_image_of_the_wrong_resolution_is_an_error_naming_its_file(tmp_path):
    """read_image with the camera's calibration (the KLT stage, direct mode's keyframes):
    an image whose size is not the sensor.yaml resolution names its file."""
    import cv2
    calib = load_euroc(shared("euroc_V1_01_static_stereo")).cam0.calib
    good, small = tmp_path / "good.png", tmp_path / "small.png"
    cv2.imwrite(str(good), np.zeros((calib.height, calib.width), np.uint8))
    cv2.imwrite(str(small), np.zeros((480, 640), np.uint8))
    assert read_image(good, calib).shape == (480, 752)
    with pytest.raises(DataError, match=r"small\.png: image is 640x480 but camera cam0 is calibrated for 752x480"):
        read_image(small, calib)
    assert read_image(small).shape == (480, 640)          # without a calibration: as it is
    with pytest.raises(DataError, match="cam1 image: image is 640x480"):
        calib.check_resolution(np.zeros((480, 640), np.uint8), "cam1 image")


def test_missing_images_drop_their_frames_with_a_warning(tmp_path):
    """An image data.csv lists but the folder lacks is a dropped frame (warning naming the
    csv line), not a failed run; a stereo pair that lost one image is dropped whole; a
    camera with no image at all is an error for cam0 and unused for cam1."""
    from vio.io.euroc import image_files, stereo_stamps
    root = tmp_path / "s"
    shutil.copytree(shared("euroc_V1_01_static_stereo"), root)
    names0 = sorted(p.name for p in (root / "mav0/cam0/data").iterdir())
    names1 = sorted(p.name for p in (root / "mav0/cam1/data").iterdir())
    (root / "mav0/cam0/data" / names0[10]).unlink()
    (root / "mav0/cam1/data" / names1[20]).unlink()
    d = load_euroc(root)
    assert len(d.cam0) == 94 and len(d.cam1) == 94
    assert any("cam0/data.csv:12: 1 of 95 listed image(s) missing" in w for w in d.warnings)
    stamps = stereo_stamps(d, d.cam0.t_ns)
    assert len(stamps) == 93 and int(names1[20][:-4]) not in stamps
    pairs = image_files(d, True, stamps)
    assert all(a.is_file() and b.is_file() and a.name == b.name for a, b in pairs)
    for p in (root / "mav0/cam1/data").iterdir():
        p.unlink()
    d = load_euroc(root)
    assert d.cam1.files == () and any("the camera's images are not used" in w for w in d.warnings)
    for p in (root / "mav0/cam0/data").iterdir():
        p.unlink()
    with pytest.raises(DataError, match="none of its 95 images exists"):
        load_euroc(root)


def test_tum_round_trip_from_a_string_path_and_missing_file_named(tmp_path):
    """``read_tum`` takes the path as a user passes it (a string, as ``write_tum`` does);
    a missing file is a ``DataError`` naming it, not an AttributeError."""
    import gtsam
    from vio.io.euroc import read_tum
    from vio.trajectory import write_tum
    poses = [gtsam.Pose3(gtsam.Rot3.Yaw(0.1 * k), np.array([k, 0.5, 0.0])) for k in range(3)]
    out = str(tmp_path / "est.txt")
    write_tum(out, [1_000_000_000 + k * 50_000_000 for k in range(3)], poses)
    back = read_tum(out)
    assert back.t_ns.tolist() == [1_000_000_000, 1_050_000_000, 1_100_000_000]
    assert np.allclose(back.p_w[:, 0], [0, 1, 2])
    with pytest.raises(DataError, match="nope.txt: file not found"):
        read_tum(str(tmp_path / "nope.txt"))
    with pytest.raises(DataError, match="is a folder, not a file"):
        read_tum(tmp_path)
