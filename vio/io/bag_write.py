"""``vio convert``: an ASL/EuRoC folder -> a ROS 1 bag or a ROS 2 bag folder (sqlite3 or
mcap) with the topics EuRoC's own bags use (``/cam0/image_raw``, ``/cam1/image_raw``:
``sensor_msgs/Image`` mono8 or ``CompressedImage`` png; ``/imu0``: ``sensor_msgs/Imu``),
plus the calibration as Kalibr ``camchain.yaml`` and ``imu.yaml``.

Recording time = header stamp. Images are read one at a time, never all at once.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vio.config import positive_int
from vio.errors import DataError
from vio.io.euroc import EurocDataset, LoadOptions, load_euroc, read_image
from vio.io.kalibr import write_camchain, write_kalibr_imu

CAM_TOPICS = ("/cam0/image_raw", "/cam1/image_raw")
IMU_TOPIC = "/imu0"


@dataclass(frozen=True)
class ConvertResult:
    """What was written: message counts per topic and the Kalibr files (if any)."""

    out: Path
    counts: dict
    camchain: Path | None
    imu_yaml: Path | None


class _Msgs:
    """Message constructors of one type store (ROS 1 Noetic or ROS 2 Humble)."""

    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_typestore
        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.T = self.ts.types
        self.seq = 0

    def header(self, t_ns: int, frame: str):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000),
                                                      nanosec=int(t_ns % 1_000_000_000))
        self.seq += 1
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=self.seq, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def image(self, t_ns: int, img: np.ndarray, frame: str, compressed: bool):
        if compressed:
            ok, buf = cv2.imencode(".png", img)
            assert ok
            return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(t_ns, frame), format="mono8; png",
                                                             data=buf.reshape(-1).astype(np.uint8))
        h, w = img.shape
        return self.T["sensor_msgs/msg/Image"](header=self.header(t_ns, frame), height=h, width=w,
                                               encoding="mono8", is_bigendian=0, step=w,
                                               data=np.ascontiguousarray(img).reshape(-1))

    def imu(self, t_ns: int, w: np.ndarray, a: np.ndarray):
        V, Q = self.T["geometry_msgs/msg/Vector3"], self.T["geometry_msgs/msg/Quaternion"]
        unknown = np.zeros(9)
        unknown[0] = -1.0      # REP 145: no orientation estimate
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(t_ns, "imu0"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=unknown, angular_velocity=V(x=float(w[0]), y=float(w[1]), z=float(w[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V(x=float(a[0]), y=float(a[1]), z=float(a[2])),
            linear_acceleration_covariance=np.zeros(9))

    def serialize(self, msg, msgtype: str) -> bytes:
        return self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype)


def _writer(out: Path, ros1: bool, storage: str):
    if out.exists():
        raise DataError(out, "output exists; remove it first")
    if ros1:
        from rosbags.rosbag1 import Writer
        return Writer(out)
    from rosbags.rosbag2 import StoragePlugin, Writer
    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    if storage not in plugins:
        raise DataError(out, f"storage {storage!r} not in {sorted(plugins)}")
    return Writer(out, version=8, storage_plugin=plugins[storage])


def _events(data: EurocDataset, n: int | None, margin_s: float):
    """(t_ns, kind, index) in time order: camera frames (the first ``n``) and the IMU
    samples from ``margin_s`` before the first frame to ``margin_s`` after the last."""
    cams = [c for c in (data.cam0, data.cam1) if c is not None and c.has_images()]
    if not cams:
        raise DataError(data.root, "no camera images to convert")
    t_cam = [c.t_ns[:n] for c in cams]
    lo = min(t[0] for t in t_cam) - int(margin_s * 1e9)
    hi = max(t[-1] for t in t_cam) + int(margin_s * 1e9)
    imu_idx = np.flatnonzero((data.imu.t_ns >= lo) & (data.imu.t_ns <= hi)) if n else np.arange(len(data.imu))
    streams = [[(int(data.imu.t_ns[i]), 0, int(i)) for i in imu_idx]]
    streams += [[(int(t), k + 1, i) for i, t in enumerate(tc)] for k, tc in enumerate(t_cam)]
    return cams, heapq.merge(*streams)


def convert(folder: str | Path, out: str | Path, max_frames: int | None = None, storage: str = "sqlite3",
            compressed: bool = False, kalibr_dir: str | Path | None = None,
            imu_margin_s: float = 1.0) -> ConvertResult:
    """Write ``folder`` as a ROS 1 bag (``out`` ends in ``.bag``) or a ROS 2 bag folder
    (``storage`` sqlite3 or mcap); ``max_frames`` keeps the first frames (and the IMU
    within ``imu_margin_s`` of them); ``kalibr_dir`` also gets camchain.yaml + imu.yaml."""
    data = load_euroc(folder, LoadOptions(trim_to_imu=True))
    out = Path(out)
    ros1 = out.suffix == ".bag"
    msgs = _Msgs(ros1)
    cams, events = _events(data, max_frames, imu_margin_s)
    counts = {IMU_TOPIC: 0, **{CAM_TOPICS[k]: 0 for k in range(len(cams))}}
    writer = _writer(out, ros1, storage)
    img_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with writer:
        conns = [writer.add_connection(IMU_TOPIC, "sensor_msgs/msg/Imu", typestore=msgs.ts)]
        conns += [writer.add_connection(CAM_TOPICS[k], img_type, typestore=msgs.ts) for k in range(len(cams))]
        for t, kind, i in events:
            if kind == 0:
                msg, mtype = msgs.imu(t, data.imu.gyro[i], data.imu.accel[i]), "sensor_msgs/msg/Imu"
            else:
                msg, mtype = msgs.image(t, read_image(cams[kind - 1].files[i]), f"cam{kind - 1}", compressed), img_type
            writer.write(conns[kind], t, msgs.serialize(msg, mtype))
            counts[conns[kind].topic] += 1
    camchain = imu_yaml = None
    if kalibr_dir is not None:
        kd = Path(kalibr_dir)
        kd.mkdir(parents=True, exist_ok=True)
        camchain, imu_yaml = kd / "camchain.yaml", kd / "imu.yaml"
        write_camchain(camchain, [c.calib for c in cams], list(CAM_TOPICS[:len(cams)]))
        write_kalibr_imu(imu_yaml, data.imu_calib, IMU_TOPIC)
    return ConvertResult(out, counts, camchain, imu_yaml)


def add_parser(sub) -> None:
    """Register ``vio convert``."""
    p = sub.add_parser("convert", help="write an ASL/EuRoC folder as a ROS 1 bag or ROS 2 bag (+ Kalibr YAML)")
    p.add_argument("folder", type=Path, help="ASL/EuRoC folder with images")
    p.add_argument("out", type=Path, help="OUT.bag (ROS 1) or a new folder (ROS 2)")
    p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="ROS 2 storage")
    p.add_argument("--max-frames", type=positive_int, default=None, help="only the first N frames (IMU cropped)")
    p.add_argument("--compressed", action="store_true", help="sensor_msgs/CompressedImage (png)")
    p.add_argument("--kalibr", type=Path, help="also write camchain.yaml and imu.yaml into this folder")


def run(args) -> int:
    """Entry point of ``vio convert``."""
    r = convert(args.folder, args.out, args.max_frames, args.storage, args.compressed, args.kalibr)
    for topic, n in r.counts.items():
        print(f"{topic:18s} {n} messages")
    print(f"wrote           {r.out}")
    if r.camchain:
        print(f"kalibr          {r.camchain} {r.imu_yaml}")
    return 0
