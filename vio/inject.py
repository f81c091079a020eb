"""Fault injection on a *copy* of an EuRoC/ASL folder (fault tests and benchmarks).

Every function edits the CSV text of the copy in place and never the source: rows are
kept verbatim except the ones removed or overwritten, so a fault-free copy runs exactly
like the original. Times are seconds relative to the first IMU sample of the source
(``t0``); the edited stamps stay integer nanoseconds.

- :func:`copy_dataset` copies a folder (optionally cut to ``[start_s, end_s]``);
- :func:`imu_gap` removes the IMU rows of ``[t_s, t_s + dur_s)``;
- :func:`imu_spike` overwrites the accelerometer/gyro of the row nearest ``t_s``;
- :func:`imu_offset` adds a constant to the accelerometer over a stretch (a bias step that
  passes the sample screen);
- :func:`drop_frames` removes the camera frames (and their feature rows) of a stretch;
- :func:`shift_camera_stamps` moves every camera stamp, as a camera-IMU time offset does;
- :func:`image_fault` alters a camera's images over a stretch (covered, black, blurred,
  over-exposed); :func:`frame_window` gives the stretch of a run of frames.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from vio.io.euroc import find_mav0


def _stamp(line: str) -> int | None:
    """The leading integer stamp (ns) of a CSV data row; None for headers/blank lines."""
    head = line.split(",", 1)[0].strip()
    return int(head) if head.isdigit() else None


def _edit_csv(path: Path, edit: Callable[[int, str], str | None]) -> int:
    """Rewrite ``path`` with ``edit(stamp, line)`` applied to every data row (None:
    remove the row); headers stay. Returns the number of rows changed or removed."""
    if not path.is_file():
        return 0
    lines = path.read_text().splitlines(keepends=True)
    out, n = [], 0
    for line in lines:
        t = _stamp(line)
        new = line if t is None else edit(t, line)
        n += new != line
        if new is not None:
            out.append(new)
    path.write_text("".join(out))
    return n


def _t0(mav0: Path) -> int:
    for line in (mav0 / "imu0" / "data.csv").read_text().splitlines():
        t = _stamp(line)
        if t is not None:
            return t
    raise ValueError(f"{mav0 / 'imu0' / 'data.csv'}: no data rows")


def _csvs(mav0: Path) -> list[Path]:
    """The time-stamped CSVs of a folder (IMU, cameras, features, ground truth)."""
    return [p for p in mav0.rglob("*.csv") if p.parent.name in ("imu0", "cam0", "cam1",
                                                                  "state_groundtruth_estimate0")]


def copy_dataset(src: str | Path, dst: str | Path, start_s: float | None = None,
                 end_s: float | None = None) -> Path:
    """Copy the folder ``src`` to ``dst`` (replaced if present; image folders are
    symlinked, not copied), keeping only rows with stamps in ``[start_s, end_s]`` s after
    ``src``'s first IMU sample when given. Returns ``dst``."""
    src_mav0, dst = find_mav0(src), Path(dst)
    if dst.exists():
        shutil.rmtree(dst)
    t0 = _t0(src_mav0)
    for p in src_mav0.rglob("*"):
        rel = p.relative_to(src_mav0)
        q = dst / "mav0" / rel
        if p.is_dir():
            if p.name == "data" and p.parent.name.startswith("cam"):
                q.parent.mkdir(parents=True, exist_ok=True)
                q.symlink_to(p.resolve(), target_is_directory=True)
            continue
        if any(part == "data" and i > 0 and rel.parts[i - 1].startswith("cam")
               for i, part in enumerate(rel.parts[:-1])):
            continue   # inside a symlinked image folder
        q.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(p, q)
    for sib in Path(src_mav0.parent).glob("*.csv") if src_mav0.name == "mav0" else []:
        shutil.copyfile(sib, dst / sib.name)
    if start_s is not None or end_s is not None:
        lo = t0 + int(round((start_s or 0.0) * 1e9))
        hi = t0 + int(round(end_s * 1e9)) if end_s is not None else np.iinfo(np.int64).max
        for p in _csvs(dst / "mav0"):
            _edit_csv(p, lambda t, line: line if lo <= t <= hi else None)
    return dst


def imu_gap(root: str | Path, t_s: float, dur_s: float, t0_ns: int | None = None) -> int:
    """Remove the IMU rows with stamps in ``[t_s, t_s + dur_s)`` s after ``t0_ns``
    (default: the folder's first IMU sample). Returns the number removed."""
    mav0 = find_mav0(root)
    t0 = _t0(mav0) if t0_ns is None else t0_ns
    lo, hi = t0 + int(round(t_s * 1e9)), t0 + int(round((t_s + dur_s) * 1e9))
    return _edit_csv(mav0 / "imu0" / "data.csv", lambda t, line: None if lo <= t < hi else line)


def imu_spike(root: str | Path, t_s: float, accel: tuple[float, float, float] | None = None,
              gyro: tuple[float, float, float] | None = None, t0_ns: int | None = None) -> int:
    """Overwrite the accelerometer (m/s^2) and/or gyro (rad/s) reading of the IMU row
    nearest ``t_s`` s after ``t0_ns``; returns that row's stamp (ns)."""
    mav0 = find_mav0(root)
    path = mav0 / "imu0" / "data.csv"
    t0 = _t0(mav0) if t0_ns is None else t0_ns
    stamps = np.array([t for t in map(_stamp, path.read_text().splitlines()) if t is not None])
    target = int(stamps[np.argmin(np.abs(stamps - (t0 + int(round(t_s * 1e9)))))])

    def edit(t: int, line: str) -> str:
        if t != target:
            return line
        vals = line.strip().split(",")
        if gyro is not None:
            vals[1:4] = [repr(float(x)) for x in gyro]
        if accel is not None:
            vals[4:7] = [repr(float(x)) for x in accel]
        return ",".join(vals) + "\n"

    _edit_csv(path, edit)
    return target


def imu_offset(root: str | Path, t_s: float, dur_s: float, accel: tuple[float, float, float],
               t0_ns: int | None = None) -> int:
    """Add ``accel`` (3,) m/s^2 to the accelerometer readings of ``[t_s, t_s + dur_s)`` s
    after ``t0_ns`` (default: the folder's first IMU sample). Returns the rows changed."""
    mav0 = find_mav0(root)
    t0 = _t0(mav0) if t0_ns is None else t0_ns
    lo, hi = t0 + int(round(t_s * 1e9)), t0 + int(round((t_s + dur_s) * 1e9))
    n = 0

    def edit(t: int, line: str) -> str:
        nonlocal n
        if not lo <= t < hi:
            return line
        vals = line.strip().split(",")
        for i, a in enumerate(accel):
            if a:
                vals[4 + i] = repr(float(vals[4 + i]) + float(a))
        n += 1
        return ",".join(vals) + "\n"

    _edit_csv(mav0 / "imu0" / "data.csv", edit)
    return n


def drop_frames(root: str | Path, t_s: float, dur_s: float, t0_ns: int | None = None) -> int:
    """Remove the camera frames with stamps in ``[t_s, t_s + dur_s)`` (both cameras,
    their feature rows too). Returns the number of cam0 frames removed."""
    mav0 = find_mav0(root)
    t0 = _t0(mav0) if t0_ns is None else t0_ns
    lo, hi = t0 + int(round(t_s * 1e9)), t0 + int(round((t_s + dur_s) * 1e9))

    def keep(t: int, line: str) -> str | None:
        return None if lo <= t < hi else line

    n = _edit_csv(mav0 / "cam0" / "data.csv", keep)
    for p in (mav0 / "cam0" / "features.csv", mav0 / "cam1" / "data.csv"):
        _edit_csv(p, keep)
    return n


def shift_camera_stamps(root: str | Path, dt_s: float) -> int:
    """Move every camera stamp (both cameras' ``data.csv`` and cam0's feature rows) by
    ``dt_s`` s, the image file names kept: the frames then carry an extra camera-IMU
    offset of ``td = -dt_s`` (``t_imu = t_stamp + td``). Returns the number of cam0
    frames moved."""
    mav0 = find_mav0(root)
    dt = int(round(dt_s * 1e9))

    def move(t: int, line: str) -> str:
        return str(t + dt) + line[len(line.split(",", 1)[0]):]

    n = _edit_csv(mav0 / "cam0" / "data.csv", move)
    for p in (mav0 / "cam0" / "features.csv", mav0 / "cam1" / "data.csv"):
        _edit_csv(p, move)
    return n


IMAGE_FAULTS = ("cover", "black", "blur", "exposure")
"""``cover``: a lens covered (every pixel 12); ``black``: every pixel 0; ``blur``: a 15-px
horizontal motion blur; ``exposure``: intensities x2.2, clipped at 255."""


def _altered(img: np.ndarray, kind: str) -> np.ndarray:
    import cv2

    if kind == "cover":
        return np.full_like(img, 12)
    if kind == "black":
        return np.zeros_like(img)
    if kind == "blur":
        return cv2.filter2D(img, -1, np.full((1, 15), 1.0 / 15, np.float32))
    return np.clip(img.astype(np.float64) * 2.2, 0, 255).astype(img.dtype)


def frame_window(root: str | Path, first: int, n: int) -> tuple[float, float]:
    """(t_s, dur_s) after the folder's first IMU sample that take in exactly cam0 frames
    ``first`` .. ``first + n - 1`` (halfway to the neighbouring frames; ``n`` is cut at the
    last frame)."""
    mav0 = find_mav0(root)
    t_cam = [t for t in map(_stamp, (mav0 / "cam0" / "data.csv").read_text().splitlines()) if t is not None]
    i, j = first, min(first + n, len(t_cam))
    if not 0 <= i < j:
        raise ValueError(f"{mav0}: frames {i}..{j} outside its {len(t_cam)} cam0 frames")
    lo = (t_cam[i] + t_cam[i - 1]) / 2 if i > 0 else t_cam[i] - 1
    hi = (t_cam[j - 1] + t_cam[j]) / 2 if j < len(t_cam) else t_cam[-1] + 1
    t0 = _t0(mav0)
    return (lo - t0) * 1e-9, (hi - lo) * 1e-9


def image_fault(root: str | Path, cam: str, t_s: float, dur_s: float, kind: str,
                t0_ns: int | None = None) -> int:
    """Replace the images of camera ``cam`` ("cam0", "cam1") with stamps in
    ``[t_s, t_s + dur_s)`` s after ``t0_ns`` (default: the folder's first IMU sample) by
    the fault ``kind`` (``IMAGE_FAULTS``) of each. The copy's image folder becomes a
    folder of links to the source images, the altered ones written in their place (the
    source is never written). Returns the number of images altered."""
    import cv2

    if kind not in IMAGE_FAULTS:
        raise ValueError(f"image_fault: unknown fault {kind!r} (choose from {IMAGE_FAULTS})")
    mav0 = find_mav0(root)
    t0 = _t0(mav0) if t0_ns is None else t0_ns
    lo, hi = t0 + int(round(t_s * 1e9)), t0 + int(round((t_s + dur_s) * 1e9))
    data = mav0 / cam / "data"
    if data.is_symlink():                 # copy_dataset's link to the whole folder
        src = data.resolve()
        data.unlink()
        data.mkdir()
        for f in src.iterdir():
            (data / f.name).symlink_to(f)
    n = 0
    for line in (mav0 / cam / "data.csv").read_text().splitlines():
        t = _stamp(line)
        if t is None or not lo <= t < hi:
            continue
        f = data / line.split(",", 1)[1].strip()
        img = cv2.imread(str(f.resolve()), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{f}: not a readable image")
        f.unlink()
        cv2.imwrite(str(f), _altered(img, kind))
        n += 1
    return n
