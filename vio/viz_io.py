"""Helpers of the Rerun sink (``vio.viz``): the ``logging`` handler feeding its event
log, image encoding, a colour ramp, and compaction of a finished .rrd file."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from collections import deque
from pathlib import Path

import cv2
import numpy as np
import rerun as rr

log = logging.getLogger(__name__)


class EventLog(logging.Handler):
    """Buffers the ``vio`` package's log records (INFO and above) for the sink's
    ``events`` TextLog; holds no reference to the sink. While any is attached, the
    ``vio`` logger passes INFO records (the CLI's console handler still filters)."""

    _lock = threading.Lock()
    _attached = 0
    _saved_level = logging.NOTSET
    LEVELS = {logging.DEBUG: "DEBUG", logging.INFO: "INFO", logging.WARNING: "WARN",
              logging.ERROR: "ERROR", logging.CRITICAL: "CRITICAL"}

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: deque[tuple[str, str]] = deque(maxlen=10000)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level = self.LEVELS.get(record.levelno, record.levelname)
            self.records.append((level, f"{record.name}: {record.getMessage()}"))
        except Exception:  # noqa: BLE001 - a handler never raises
            self.handleError(record)

    def attach(self) -> None:
        lg = logging.getLogger("vio")
        with EventLog._lock:
            if EventLog._attached == 0:
                EventLog._saved_level = lg.level
                if lg.getEffectiveLevel() > logging.INFO:
                    lg.setLevel(logging.INFO)
            EventLog._attached += 1
        lg.addHandler(self)

    def detach(self) -> None:
        lg = logging.getLogger("vio")
        lg.removeHandler(self)
        with EventLog._lock:
            EventLog._attached -= 1
            if EventLog._attached == 0:
                lg.setLevel(EventLog._saved_level)


def optimize_rrd(path: Path) -> bool:
    """Compact ``path`` in place with the wheel's ``rerun rrd optimize`` (the logger writes
    one chunk per entity every 200 ms; merged, a 16-s stereo run drops from ~1800 chunks
    to ~60 and by ~20% in size, and the web viewer ingests it many times faster).
    False (with a warning; the file is kept as written) if that fails."""
    tmp = path.with_name(path.name + ".opt")
    cmd = [sys.executable, "-m", "rerun", "rrd", "optimize", str(path), "-o", str(tmp)]
    try:
        subprocess.run(cmd, check=True, capture_output=True, timeout=600)
        os.replace(tmp, path)
        return True
    except (OSError, subprocess.SubprocessError) as exc:
        log.warning("rerun: could not compact %s (%s); kept as written", path, exc)
        tmp.unlink(missing_ok=True)
        return False


def jpeg(img: np.ndarray, quality: int | None) -> rr.EncodedImage | rr.Image:
    """(H, W) grey or (H, W, 3) BGR uint8 image -> JPEG at ``quality`` (None: raw)."""
    if quality is None:
        return rr.Image(img, color_model="L" if img.ndim == 2 else "BGR")
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"JPEG encoding failed for an image of shape {img.shape}")
    return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")


def ramp(t: np.ndarray) -> np.ndarray:
    """(N,) values in [0, 1] -> (N, 3) uint8 colours cyan (0) -> magenta (1), apart from
    the red-yellow-green of the track lengths drawn on the same image."""
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
    rgb = np.stack([t, 1.0 - t, np.ones_like(t)], 1)
    return (rgb * 255).astype(np.uint8)
