"""Feature-track files: ``cam0/features.csv`` with undistorted normalized coordinates.

Format (header line first)::

    timestamp_ns,frame_idx,landmark_id,u_norm,v_norm
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio.errors import DataError
from vio.io.csvio import read_text_lines
from vio.io.types import FeatureFrame

HEADER = "timestamp_ns,frame_idx,landmark_id,u_norm,v_norm"


def read_features(path: Path, frame_stamps: np.ndarray | None = None) -> list[FeatureFrame]:
    """Group observations by frame (in file order, stamps strictly increasing).

    Velocities (1/s) come from :func:`track_velocities`. ``row`` is NaN (unknown).
    ``frame_stamps``: if given, every stamp must be one of them.
    """
    lines = read_text_lines(path)
    if not lines or lines[0].strip().replace(" ", "") != HEADER:
        raise DataError(path, f"expected header {HEADER!r}", 1)
    t, ids, uv, nos = [], [], [], []
    for no, raw in enumerate(lines[1:], start=2):
        s = raw.strip()
        if not s:
            continue
        parts = s.split(",")
        if len(parts) != 5:
            raise DataError(path, f"expected 5 fields, found {len(parts)}", no)
        try:
            t.append(int(parts[0]))
            ids.append(int(parts[2]))
            u, v = float(parts[3]), float(parts[4])
        except ValueError as exc:
            raise DataError(path, f"malformed row ({exc})", no) from None
        if not (np.isfinite(u) and np.isfinite(v)):
            raise DataError(path, "non-finite coordinate", no)
        uv.append((u, v))
        nos.append(no)
    if not t:
        raise DataError(path, "no observations")
    return _group(path, np.array(t, np.int64), np.array(ids, np.int64), np.array(uv),
                  np.array(nos), frame_stamps)


def _group(path: Path, t: np.ndarray, ids: np.ndarray, uv: np.ndarray, nos: np.ndarray,
           frame_stamps: np.ndarray | None) -> list[FeatureFrame]:
    d = np.diff(t)
    if (d < 0).any():
        i = int(np.flatnonzero(d < 0)[0]) + 1
        raise DataError(path, f"timestamp {t[i]} goes back in time (rows must be grouped by "
                              f"frame in time order)", int(nos[i]))
    starts = np.concatenate([[0], np.flatnonzero(d > 0) + 1, [len(t)]])
    known = set(int(x) for x in frame_stamps) if frame_stamps is not None else None
    frames: list[FeatureFrame] = []

    for a, b in zip(starts[:-1], starts[1:]):
        t_ns = int(t[a])
        if known is not None and t_ns not in known:
            raise DataError(path, f"timestamp {t_ns} is not a frame of cam0/data.csv", int(nos[a]))
        fid = ids[a:b]
        uniq, counts = np.unique(fid, return_counts=True)
        if (counts > 1).any():
            dup = int(uniq[counts > 1][0])
            row = a + int(np.flatnonzero(fid == dup)[1])
            raise DataError(path, f"landmark {dup} observed twice in frame {t_ns}", int(nos[row]))
        frames.append(FeatureFrame(t_ns, fid.copy(), uv[a:b].copy(), np.zeros((b - a, 2)),
                                   np.full(b - a, np.nan)))
    track_velocities(frames)
    return frames


def track_velocities(frames: list[FeatureFrame]) -> None:
    """Fill each observation's normalized-plane velocity (1/s), in place.

    The td factor multiplies this velocity by td, so it must be accurate (a
    2%-too-slow velocity biases td by 2%) and its noise must not be correlated
    with the observation itself (a backward difference that includes the current
    point biases td towards zero by about ``sigma^2 / (dt |v|^2)``, 1 ms for 0.7 px
    noise at 0.2 /s). Candidates, all second-order accurate and all excluding
    observation i: central differences over (i-1, i+1) and (i-2, i+2), and the
    derivative at t_i of the parabola through (i-3, i-2, i-1) or (i+1, i+2, i+3).
    The median of those available resists a single mistracked neighbour; tracks of
    two frames use their plain difference, single observations get zero.
    """
    where: dict[int, list[tuple[int, int]]] = {}
    for fi, fr in enumerate(frames):
        for k, lid in enumerate(fr.ids):
            where.setdefault(int(lid), []).append((fi, k))
    for obs in where.values():
        if len(obs) < 2:
            continue
        t = np.array([frames[fi].t_ns for fi, _ in obs], np.int64)
        uv = np.array([frames[fi].uv[k] for fi, k in obs])
        vel = _velocities(t, uv)
        for (fi, k), v in zip(obs, vel):
            frames[fi].velocity[k] = v


def _velocities(t_ns: np.ndarray, uv: np.ndarray) -> np.ndarray:
    n = len(t_ns)
    t = (t_ns - t_ns[0]) * 1e-9
    out = np.zeros((n, 2))

    def central(i: int, h: int):
        if i - h >= 0 and i + h < n:
            return (uv[i + h] - uv[i - h]) / (t[i + h] - t[i - h])
        return None

    def parabola(i: int, idx: tuple[int, int, int]):
        if min(idx) < 0 or max(idx) >= n:
            return None
        A = np.stack([np.ones(3), t[list(idx)] - t[i], (t[list(idx)] - t[i]) ** 2], 1)
        return np.linalg.solve(A, uv[list(idx)])[1]

    for i in range(n):
        cands = [c for c in (central(i, 1), central(i, 2), parabola(i, (i - 3, i - 2, i - 1)),
                             parabola(i, (i + 1, i + 2, i + 3))) if c is not None]
        if not cands:
            j = i - 1 if i > 0 else i + 1
            cands = [(uv[max(i, j)] - uv[min(i, j)]) / (t[max(i, j)] - t[min(i, j)])]
        out[i] = np.median(np.array(cands), axis=0)
    return out


def write_features(path: Path, frames: list[FeatureFrame]) -> None:
    """Write frames in the ``features.csv`` format (frame_idx = position in the list)."""
    with open(path, "w") as f:
        f.write(HEADER + "\n")
        for k, fr in enumerate(frames):
            for lid, (u, v) in zip(fr.ids, fr.uv):
                f.write(f"{fr.t_ns},{k},{int(lid)},{u:.10g},{v:.10g}\n")
