"""ROS 1 bags and ROS 2 bag folders (sqlite3 or mcap) read without ROS (``rosbags``).

A bag becomes an ``EurocDataset`` like a folder: the IMU topic (``sensor_msgs/Imu``)
is read into ``ImuData``; each camera topic (``sensor_msgs/Image`` or
``sensor_msgs/CompressedImage``) becomes a ``CameraStream`` whose ``files`` are
``BagFrame`` references, decoded to grayscale only when the front end asks for them
(``vio.io.euroc.read_image``), by a cursor that streams the topic in recorded order.
Times are the messages' header stamps (int ns), never the recording times.

Bags carry no calibration: it comes from Kalibr files (``vio.io.kalibr``). Topics are
found by message type when unambiguous (Kalibr's ``rostopic`` entries break ties) or
given explicitly (``topics``). A bag without the needed topics is a one-line
``DataError`` listing the topics it has.
"""

from __future__ import annotations

import atexit
import logging
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from vio.errors import DataError
from vio.io.png import decode_png_gray8
from vio.io.types import CameraCalib, CameraStream, ImuCalib, ImuData

log = logging.getLogger(__name__)

IMU_TYPE = "sensor_msgs/msg/Imu"
RAW_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (RAW_TYPE, COMPRESSED_TYPE)


def is_bag(path: str | Path) -> bool:
    """A ROS 1 ``.bag`` file or a ROS 2 bag folder (``metadata.yaml`` inside)."""
    path = Path(path)
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file())


def open_reader(path: str | Path):
    """An opened ``rosbags.highlevel.AnyReader`` (ROS 2 bags without embedded message
    definitions use the Humble type store); problems become ``DataError``."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    path = Path(path)
    if not path.exists():
        raise DataError(path, "bag not found")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several reader errors
        raise DataError(path, f"not a readable ROS bag: {exc}".replace("\n", " ")) from None
    return reader


def stamp_ns(msg) -> int:
    """The header stamp of a message in integer nanoseconds."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def _short(msgtype: str) -> str:
    return msgtype.replace("/msg/", "/")


def topic_listing(available: dict[str, str]) -> str:
    """``/a (sensor_msgs/Imu), /b (...)`` for error messages."""
    return ", ".join(f"{t} ({_short(m)})" for t, m in sorted(available.items())) or "no topics"


@dataclass(frozen=True)
class BagTopics:
    """The IMU topic and the camera topics (cam0 first) of a run."""

    imu: str
    cams: tuple[str, ...]


def choose_topics(available: dict[str, str], path: Path, wanted: Sequence[str] | None = None,
                  cam_hints: Sequence[str | None] = (), imu_hint: str | None = None,
                  max_cams: int = 2) -> BagTopics:
    """Pick the topics of a run from ``available`` (topic -> message type).

    ``wanted``: explicit topics (any order; classified by type, cameras keep their
    order). Otherwise the hints (Kalibr ``rostopic``) when present in the bag, else the
    only IMU topic and the one or two image topics (sorted by name: cam0 < cam1).
    """
    listing = f"the bag has: {topic_listing(available)}"
    if wanted:
        for t in wanted:
            if t not in available:
                raise DataError(path, f"topic {t} not in the bag; {listing}")
        imus = [t for t in wanted if available[t] == IMU_TYPE]
        cams = [t for t in wanted if available[t] in IMAGE_TYPES]
        other = [t for t in wanted if t not in imus and t not in cams]
        if other:
            raise DataError(path, f"topic {other[0]} ({_short(available[other[0]])}) is neither an image "
                                  f"nor an IMU topic; {listing}")
        if len(imus) != 1 or not 1 <= len(cams) <= max_cams:
            raise DataError(path, f"--topics needs one IMU topic and 1-{max_cams} image topics, got "
                                  f"{len(imus)} and {len(cams)}; {listing}")
        return BagTopics(imus[0], tuple(cams))
    imus = sorted(t for t, m in available.items() if m == IMU_TYPE)
    if imu_hint in imus:
        imus = [imu_hint]
    if len(imus) != 1:
        what = "no sensor_msgs/Imu topic" if not imus else f"{len(imus)} IMU topics"
        raise DataError(path, f"{what} (choose with --topics); {listing}")
    images = sorted(t for t, m in available.items() if m in IMAGE_TYPES)
    hinted = [h for h in cam_hints if h]
    if hinted and hinted[0] in images:       # the camchain's cameras present in the bag, cam0 first
        return BagTopics(imus[0], tuple(h for h in hinted if h in images)[:max_cams])
    if not images:
        raise DataError(path, f"no sensor_msgs/Image or CompressedImage topic; {listing}")
    if len(images) > max_cams:
        raise DataError(path, f"{len(images)} image topics, which cameras? (choose with --topics); {listing}")
    return BagTopics(imus[0], tuple(images))


@dataclass(frozen=True)
class BagFrame:
    """A reference to one image message, decoded on demand (picklable, so a front-end
    worker process reads it itself). ``index``: position in the topic's recorded order;
    ``stamp_ns``: header stamp; ``log_ns``: recording time (for seeking)."""

    bag: str
    topic: str
    index: int
    stamp_ns: int
    log_ns: int

    def read_gray(self) -> np.ndarray:
        """The image as (H, W) uint8 (other encodings converted)."""
        return _cursor(self.bag, self.topic).read(self)

    def __str__(self) -> str:
        return f"{self.bag}:{self.topic}@{self.stamp_ns}"


class _Cursor:
    """Streams one image topic of an open bag; a frame that does not follow the last
    one read restarts the stream at its recording time."""

    def __init__(self, bag: str, topic: str) -> None:
        self.reader = open_reader(bag)
        self.conns = [c for c in self.reader.connections if c.topic == topic]
        if not self.conns:
            raise DataError(bag, f"topic {topic} not in the bag")
        self._it = None
        self._pos = -2

    def read(self, frame: BagFrame) -> np.ndarray:
        if self._it is None or frame.index != self._pos + 1:
            self._it = self.reader.messages(connections=self.conns, start=frame.log_ns)
        for _ in range(10_000):
            try:
                conn, log_ns, raw = next(self._it)
            except StopIteration:
                break
            msg = self.reader.deserialize(raw, conn.msgtype)
            hs = stamp_ns(msg)
            if hs == frame.stamp_ns or (hs == 0 and log_ns == frame.log_ns):   # unstamped: see _stamps
                self._pos = frame.index
                return to_gray(msg, conn.msgtype, str(frame))
        self._it = None
        raise DataError(frame.bag, f"image {frame.topic} stamped {frame.stamp_ns} ns not found")

    def close(self) -> None:
        self.reader.close()


_CURSORS: OrderedDict[tuple[str, str], _Cursor] = OrderedDict()
_MAX_CURSORS = 8


def _cursor(bag: str, topic: str) -> _Cursor:
    key = (bag, topic)
    if key in _CURSORS:
        _CURSORS.move_to_end(key)
        return _CURSORS[key]
    cur = _CURSORS[key] = _Cursor(bag, topic)
    while len(_CURSORS) > _MAX_CURSORS:
        _CURSORS.popitem(last=False)[1].close()
    return cur


@atexit.register
def close_all() -> None:
    """Close every open bag cursor."""
    while _CURSORS:
        _CURSORS.popitem()[1].close()


_COLOR = {"rgb8": (3, cv2.COLOR_RGB2GRAY), "bgr8": (3, cv2.COLOR_BGR2GRAY),
          "rgba8": (4, cv2.COLOR_RGBA2GRAY), "bgra8": (4, cv2.COLOR_BGRA2GRAY)}
# ROS names the Bayer pattern from the top-left 2x2 block, OpenCV from the second row
_BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2GRAY, "bayer_bggr8": cv2.COLOR_BayerRG2GRAY,
          "bayer_gbrg8": cv2.COLOR_BayerGR2GRAY, "bayer_grbg8": cv2.COLOR_BayerGB2GRAY}
_YUV = {"yuv422": cv2.COLOR_YUV2GRAY_UYVY, "uyvy": cv2.COLOR_YUV2GRAY_UYVY,
        "yuv422_yuy2": cv2.COLOR_YUV2GRAY_YUY2, "yuyv": cv2.COLOR_YUV2GRAY_YUY2}


def to_gray(msg, msgtype: str, what: str) -> np.ndarray:
    """A ``sensor_msgs/Image`` (mono8/16, 8UC1/16UC1, rgb/bgr(a)8, bayer_*8, yuv422) or
    ``CompressedImage`` (any format OpenCV decodes) as (H, W) uint8; 16-bit images are
    divided by 256 (as cv_bridge does)."""
    data = np.frombuffer(msg.data, np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    if msgtype == COMPRESSED_TYPE:
        img = None
        if data.size:   # vio.io.png's fast path, else OpenCV
            img = decode_png_gray8(data.tobytes())
            if img is None:
                img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DataError(what, f"CompressedImage ({msg.format!r}) cannot be decoded")
        return img
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), msg.encoding.lower()
    if h <= 0 or w <= 0 or data.size < h * step:
        raise DataError(what, f"Image {w}x{h} (step {step}) holds only {data.size} bytes")
    rows = data[:h * step].reshape(h, step)
    if enc in ("mono8", "8uc1"):
        return np.ascontiguousarray(rows[:, :w])
    if enc in ("mono16", "16uc1"):
        px = rows[:, :2 * w].copy().view(">u2" if msg.is_bigendian else "<u2")
        return (px >> 8).astype(np.uint8)
    if enc in _COLOR:
        c, code = _COLOR[enc]
        return cv2.cvtColor(np.ascontiguousarray(rows[:, :c * w]).reshape(h, w, c), code)
    if enc in _BAYER:
        return cv2.cvtColor(np.ascontiguousarray(rows[:, :w]), _BAYER[enc])
    if enc in _YUV:
        return cv2.cvtColor(np.ascontiguousarray(rows[:, :2 * w]).reshape(h, w, 2), _YUV[enc])
    raise DataError(what, f"image encoding {msg.encoding!r} unsupported (mono8/16, rgb8, bgr8, rgba8, "
                          f"bgra8, bayer_*8, yuv422)")


@dataclass
class _Scan:
    """Header stamps (and recording times) of the chosen topics, from one pass."""

    imu_t: list
    imu_log: list
    imu_w: list
    imu_a: list
    cam_t: dict
    cam_log: dict


def scan(reader, topics: BagTopics) -> _Scan:
    """One streamed pass over the bag: IMU samples and image stamps (images are not kept)."""
    wanted = {topics.imu, *topics.cams}
    conns = [c for c in reader.connections if c.topic in wanted]
    out = _Scan([], [], [], [], {t: [] for t in topics.cams}, {t: [] for t in topics.cams})
    for conn, log_ns, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.topic == topics.imu:
            w, a = msg.angular_velocity, msg.linear_acceleration
            out.imu_t.append(stamp_ns(msg))
            out.imu_log.append(int(log_ns))
            out.imu_w.append((w.x, w.y, w.z))
            out.imu_a.append((a.x, a.y, a.z))
        else:
            out.cam_t[conn.topic].append(stamp_ns(msg))
            out.cam_log[conn.topic].append(int(log_ns))
    return out


def _stamps(header: list, log_ns: list, where: str, warnings: list[str]) -> np.ndarray:
    """Header stamps (int64 ns); the recording times when every header stamp is zero
    (a driver that does not stamp its messages), with a warning."""
    t = np.array(header, np.int64)
    if t.size and not t.any():
        warnings.append(f"{where}: every header stamp is 0: using the recording times")
        return np.array(log_ns, np.int64)
    return t


def _sorted_unique(t: np.ndarray, where: str, warnings: list[str]) -> np.ndarray:
    """Indices that sort ``t`` and drop repeated stamps (with a warning)."""
    order = np.argsort(t, kind="stable")
    if np.any(np.diff(order) < 0):
        warnings.append(f"{where}: header stamps out of recording order (sorted)")
    keep = np.concatenate([[True], np.diff(t[order]) > 0]) if t.size else np.zeros(0, bool)
    if not keep.all():
        warnings.append(f"{where}: {int((~keep).sum())} message(s) with a repeated header stamp dropped")
    return order[keep]


def imu_data(sc: _Scan, where: str, warnings: list[str]) -> ImuData:
    """The scanned IMU samples, sorted by header stamp, non-finite samples dropped."""
    t = _stamps(sc.imu_t, sc.imu_log, where, warnings)
    w, a = np.array(sc.imu_w, float).reshape(-1, 3), np.array(sc.imu_a, float).reshape(-1, 3)
    ok = np.isfinite(w).all(1) & np.isfinite(a).all(1)
    if not ok.all():
        warnings.append(f"{where}: {int((~ok).sum())} non-finite IMU message(s) dropped")
        t, w, a = t[ok], w[ok], a[ok]
    idx = _sorted_unique(t, where, warnings)
    if idx.size < 2:
        raise DataError(where, f"only {idx.size} IMU message(s)")
    return ImuData(t[idx], w[idx], a[idx])


def camera_stream(bag: Path, topic: str, sc: _Scan, calib: CameraCalib, imu: ImuData,
                  warnings: list[str]) -> CameraStream:
    """The frames of one image topic inside the IMU span, as lazily read ``BagFrame``s."""
    where = f"{bag}:{topic}"
    log_ns = sc.cam_log[topic]
    t = _stamps(sc.cam_t[topic], log_ns, where, warnings)
    idx = _sorted_unique(t, where, warnings)
    inside = idx[(t[idx] >= imu.t_ns[0]) & (t[idx] <= imu.t_ns[-1])]
    if inside.size < idx.size:
        warnings.append(f"{where}: {idx.size - inside.size} frame(s) outside the IMU span dropped")
    if inside.size == 0:
        raise DataError(where, f"no image inside the IMU span [{imu.t_ns[0]}, {imu.t_ns[-1]}] ns")
    frames = tuple(BagFrame(str(bag), topic, int(i), int(t[i]), int(log_ns[i])) for i in inside)
    return CameraStream(calib, t[inside], frames)


def pair_stereo(cam0: CameraStream, cam1: CameraStream, where: str, warnings: list[str],
                tol_ns: int = 1_000_000) -> tuple[CameraStream, CameraStream]:
    """Keep the cam0 frames with a cam1 frame within ``tol_ns``; cam1 frames take the
    cam0 stamp (the pipeline pairs by equal stamps)."""
    j = np.clip(np.searchsorted(cam1.t_ns, cam0.t_ns), 1, max(len(cam1) - 1, 1))
    j = np.where(np.abs(cam1.t_ns[j - 1] - cam0.t_ns) <= np.abs(cam1.t_ns[j] - cam0.t_ns), j - 1, j) \
        if len(cam1) > 1 else np.zeros(len(cam0), np.int64)
    ok = np.abs(cam1.t_ns[j] - cam0.t_ns) <= tol_ns
    if not ok.any():
        raise DataError(where, f"no cam1 frame within {tol_ns * 1e-6:.1f} ms of a cam0 frame")
    if not ok.all():
        warnings.append(f"{where}: {int((~ok).sum())} cam0 frame(s) without a cam1 frame dropped")
    i, j = np.flatnonzero(ok), j[ok]
    t = cam0.t_ns[i]
    return (CameraStream(cam0.calib, t, tuple(cam0.files[k] for k in i)),
            CameraStream(cam1.calib, t.copy(), tuple(cam1.files[k] for k in j)))


def load_bag(path: str | Path, cams: Sequence[CameraCalib], imu_calib: ImuCalib,
             topics: Sequence[str] | None = None, cam_hints: Sequence[str | None] = (),
             imu_hint: str | None = None, td_s: float | None = None):
    """A bag as an ``EurocDataset`` (no ground truth, no feature tracks).

    ``cams``: the calibrated cameras, ``cam_hints`` their topics (Kalibr ``rostopic``);
    ``topics``: explicit topics (else found, see ``choose_topics``). A chosen image topic
    takes the calibration whose ``rostopic`` it is, else the next camera in order.
    Frames outside the IMU span are dropped with a warning.
    """
    from vio.io.euroc import EurocDataset, LoadOptions, imu_gap_warnings
    path = Path(path)
    reader = open_reader(path)
    try:
        available = {c.topic: c.msgtype for c in reader.connections}
        tp = choose_topics(available, path, topics, cam_hints, imu_hint, max_cams=min(2, len(cams)))
        warnings: list[str] = []
        sc = scan(reader, tp)
    finally:
        reader.close()
    imu = imu_data(sc, f"{path}:{tp.imu}", warnings)
    warnings += imu_gap_warnings(imu, f"{path}:{tp.imu}", LoadOptions().max_imu_gap_s)
    hints = list(cam_hints) + [None] * len(cams)
    calibs = [cams[hints.index(t)] if t in hints else cams[i] for i, t in enumerate(tp.cams)]
    streams = [camera_stream(path, t, sc, c, imu, warnings) for t, c in zip(tp.cams, calibs)]
    if len(streams) == 2:
        streams = list(pair_stereo(*streams, f"{path}:{tp.cams[1]}", warnings))
    for w in warnings:
        log.warning(w)
    return EurocDataset(path, imu, imu_calib, streams[0], streams[1] if len(streams) > 1 else None,
                        None, None, tuple(warnings), td_s=td_s)
