"""ROS 1 / ROS 2 bags (``vio.io.bag``), written with ``rosbags`` from the real EuRoC
folders by ``vio convert``: the same trajectory as the folder, topic choice, image
encodings, and one-line errors."""

from __future__ import annotations

import pickle
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from tests.conftest import shared
from vio.cli import main
from vio.errors import DataError
from vio.io.bag import BagFrame, choose_topics, load_bag, pair_stereo, to_gray
from vio.io.bag_write import convert
from vio.io.euroc import load_euroc, read_image, read_tum
from vio.io.load import load_dataset
from vio.io.types import CameraStream
from vio.run import run_dataset

N = 40   # frames: a short stretch keeps the suite fast


@pytest.fixture(scope="module")
def mh01(tmp_path_factory):
    """MH_01 stereo: the first N frames as ROS 1 and ROS 2 (sqlite3) bags + Kalibr files,
    and the folder's own trajectory over those frames."""
    folder = shared("euroc_MH_01_stereo_synimu")
    d = tmp_path_factory.mktemp("mh01")
    convert(folder, d / "mh01.bag", N, kalibr_dir=d)
    convert(folder, d / "mh01_ros2", N, storage="sqlite3")
    res = run_dataset(load_euroc(folder), max_frames=N, mode="stereo")
    t, p, q = res.arrays()
    return SimpleNamespace(folder=folder, dir=d, t=t, p=p, q=q)


def _same(a_t, a_p, b_t, b_p):
    assert len(a_t) > N // 2
    np.testing.assert_array_equal(a_t, b_t)
    np.testing.assert_allclose(a_p, b_p, atol=1e-6)


def test_ros1_bag_cli_gives_the_folder_trajectory(mh01, capsys):
    out = mh01.dir / "ros1.tum"
    rc = main(["run", str(mh01.dir / "mh01.bag"), "--calib", str(mh01.dir / "camchain.yaml"),
               "--imu-calib", str(mh01.dir / "imu.yaml"), "--mode", "stereo", "--out", str(out),
               "--groundtruth", str(mh01.folder), "--no-progress"])
    assert rc == 0
    assert "ATE RMSE" in capsys.readouterr().out
    est = read_tum(out)
    _same(mh01.t, mh01.p, est.t_ns, est.p_w)


def test_ros2_sqlite_bag_gives_the_folder_trajectory(mh01):
    data = load_dataset(mh01.dir / "mh01_ros2", calib=mh01.dir / "camchain.yaml", imu_calib=mh01.dir / "imu.yaml")
    assert data.kind == "stereo" and len(data.cam0) == N
    t, p, _ = run_dataset(data, mode="stereo").arrays()
    _same(mh01.t, mh01.p, t, p)


def test_ros2_mcap_compressed_mono(tmp_path):
    """MH_05 mono (real IMU) as mcap with png CompressedImage: same as the folder."""
    folder = shared("euroc_MH_05_mono_15s")
    convert(folder, tmp_path / "mh05", N, storage="mcap", compressed=True, kalibr_dir=tmp_path)
    data = load_dataset(tmp_path / "mh05", calib=tmp_path / "camchain.yaml", imu_calib=tmp_path / "imu.yaml")
    ref = load_euroc(folder)
    assert data.kind == "mono"
    np.testing.assert_array_equal(read_image(data.cam0.files[7]), read_image(ref.cam0.files[7]))
    t, p, _ = run_dataset(data, mode="mono").arrays()
    rt, rp, _ = run_dataset(ref, max_frames=N, mode="mono").arrays()
    _same(rt, rp, t, p)


def test_frames_are_lazy_picklable_and_seekable(mh01):
    data = load_dataset(mh01.dir / "mh01.bag", calib=mh01.dir / "camchain.yaml", imu_calib=mh01.dir / "imu.yaml")
    ref = load_euroc(mh01.folder)
    assert all(isinstance(f, BagFrame) for f in data.cam0.files)
    np.testing.assert_array_equal(data.cam0.t_ns, ref.cam0.t_ns[:N])
    for k in (5, 6, 2, 30, 3):            # forward, backward, jumps: the cursor reseeks
        f = pickle.loads(pickle.dumps(data.cam1.files[k]))
        np.testing.assert_array_equal(read_image(f), read_image(ref.cam1.files[k]))


def test_bag_without_the_topics_lists_what_it_has(tmp_path, mh01):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "other.bag"
    with Writer(bag) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        w.write(c, 1, ts.serialize_ros1(ts.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    with pytest.raises(DataError) as e:
        load_dataset(bag, calib=mh01.dir / "camchain.yaml", imu_calib=mh01.dir / "imu.yaml")
    msg = str(e.value)
    assert "\n" not in msg and "no sensor_msgs/Imu topic" in msg and "/chatter (std_msgs/String)" in msg
    with pytest.raises(DataError, match="no calibration"):
        load_dataset(mh01.dir / "mh01.bag")


def test_topic_choice():
    av = {"/imu0": "sensor_msgs/msg/Imu", "/cam1/image_raw": "sensor_msgs/msg/Image",
          "/cam0/image_raw": "sensor_msgs/msg/Image", "/cam0/image_raw/compressed": "sensor_msgs/msg/CompressedImage"}
    with pytest.raises(DataError, match="3 image topics.*--topics"):
        choose_topics(av, "b.bag")
    tp = choose_topics(av, "b.bag", cam_hints=("/cam0/image_raw", "/cam1/image_raw"))
    assert tp.cams == ("/cam0/image_raw", "/cam1/image_raw") and tp.imu == "/imu0"
    tp = choose_topics(av, "b.bag", wanted=["/cam0/image_raw/compressed", "/imu0"])
    assert tp.cams == ("/cam0/image_raw/compressed",)
    two = {k: v for k, v in av.items() if "compressed" not in k}
    assert choose_topics(two, "b.bag").cams == ("/cam0/image_raw", "/cam1/image_raw")
    with pytest.raises(DataError, match="2 IMU topics"):
        choose_topics({**two, "/imu1": "sensor_msgs/msg/Imu"}, "b.bag")
    with pytest.raises(DataError, match="neither an image"):
        choose_topics({**two, "/x": "std_msgs/msg/String"}, "b.bag", wanted=["/x", "/imu0"])


def _img(enc, data, h=3, w=4, step=None, big=0):
    return SimpleNamespace(height=h, width=w, step=step or data.size // h, encoding=enc, is_bigendian=big,
                           data=data.reshape(-1))


def test_image_encodings():
    rng = np.random.default_rng(0)
    g = rng.integers(0, 256, (3, 4), dtype=np.uint8)
    padded = np.zeros((3, 6), np.uint8)
    padded[:, :4] = g
    np.testing.assert_array_equal(to_gray(_img("mono8", padded, step=6), "sensor_msgs/msg/Image", "x"), g)
    w16 = (g.astype(np.uint16) * 256 + 7).astype(">u2")
    np.testing.assert_array_equal(to_gray(_img("mono16", w16.view(np.uint8), big=1), "sensor_msgs/msg/Image", "x"), g)
    rgb = np.dstack([g, g, g])
    np.testing.assert_array_equal(to_gray(_img("rgb8", rgb), "sensor_msgs/msg/Image", "x"), g)
    np.testing.assert_array_equal(to_gray(_img("bgra8", np.dstack([g, g, g, g])), "sensor_msgs/msg/Image", "x"), g)
    ok, png = cv2.imencode(".png", g)
    comp = SimpleNamespace(format="png", data=png.reshape(-1))
    np.testing.assert_array_equal(to_gray(comp, "sensor_msgs/msg/CompressedImage", "x"), g)
    with pytest.raises(DataError, match="encoding '32FC1' unsupported"):
        to_gray(_img("32FC1", np.zeros((3, 16), np.uint8)), "sensor_msgs/msg/Image", "x")
    with pytest.raises(DataError, match="cannot be decoded"):
        to_gray(SimpleNamespace(format="jpeg", data=np.zeros(5, np.uint8)), "sensor_msgs/msg/CompressedImage", "x")


def test_stereo_pairing_tolerates_small_offsets():
    cal = object()
    c0 = CameraStream(cal, np.array([0, 50, 100, 150]) * 1_000_000, ("a", "b", "c", "d"))
    c1 = CameraStream(cal, np.array([0.3, 50.2, 120, 149.9]) * 1_000_000 // 1, ("A", "B", "C", "D"))
    warnings: list[str] = []
    a, b = pair_stereo(c0, c1, "bag", warnings)
    assert a.files == ("a", "b", "d") and b.files == ("A", "B", "D")
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    assert "1 cam0 frame(s) without a cam1 frame" in warnings[0]


def test_load_bag_needs_imu_before_images(tmp_path, mh01):
    """Frames outside the IMU span are dropped with a warning, not an error."""
    data = load_euroc(mh01.folder)
    convert(mh01.folder, tmp_path / "b.bag", 10, imu_margin_s=-0.06)   # IMU starts after frame 1
    d = load_bag(tmp_path / "b.bag", [data.cam0.calib], data.imu_calib, cam_hints=("/cam0/image_raw",))
    assert len(d.cam0) < 10 and any("outside the IMU span" in w for w in d.warnings)


def test_convert_cli_and_topics_flag(tmp_path, capsys):
    """``vio convert`` writes a bag + Kalibr files; ``--topics`` picks a mono run from it."""
    folder = shared("euroc_V1_01_static_stereo")
    assert main(["convert", str(folder), str(tmp_path / "s.bag"), "--max-frames", "5", "--kalibr", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "/cam0/image_raw    5 messages" in out and "/cam1/image_raw    5 messages" in out
    assert main(["convert", str(folder), str(tmp_path / "s.bag")]) == 2
    assert "output exists" in capsys.readouterr().err
    data = load_dataset(tmp_path / "s.bag", topics=["/cam1/image_raw", "/imu0"], calib=tmp_path / "camchain.yaml",
                        imu_calib=tmp_path / "imu.yaml")
    assert data.kind == "mono" and len(data.cam0) == 5
    ref = load_euroc(folder)
    assert data.cam0.calib.intrinsics == ref.cam1.calib.intrinsics      # matched by rostopic
    np.testing.assert_array_equal(read_image(data.cam0.files[4]), read_image(ref.cam1.files[4]))


def test_unstamped_messages_use_recording_times(tmp_path, mh01):
    """A driver that leaves header stamps at 0: recording times, with a warning."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC)
    out = tmp_path / "unstamped.bag"
    with AnyReader([mh01.dir / "mh01.bag"]) as r, Writer(out) as w:
        conns = {}
        for c in r.connections:
            if c.topic in ("/imu0", "/cam0/image_raw"):
                conns[c.topic] = w.add_connection(c.topic, c.msgtype, typestore=ts)
        for c, t, raw in r.messages(connections=[c for c in r.connections if c.topic in conns]):
            msg = r.deserialize(raw, c.msgtype)
            msg.header.stamp.sec, msg.header.stamp.nanosec = 0, 0
            w.write(conns[c.topic], t, ts.serialize_ros1(msg, c.msgtype))
    data = load_dataset(out, calib=mh01.dir / "camchain.yaml", imu_calib=mh01.dir / "imu.yaml")
    ref = load_euroc(mh01.folder)
    assert sum("every header stamp is 0" in w for w in data.warnings) == 2
    np.testing.assert_array_equal(data.cam0.t_ns, ref.cam0.t_ns[:N])
    np.testing.assert_array_equal(read_image(data.cam0.files[3]), read_image(ref.cam0.files[3]))
