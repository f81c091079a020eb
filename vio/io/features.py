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

    All tracks at once, as arrays ordered by (landmark, frame): a 60-s generated excerpt
    (~60 tracks a frame) took 2.8 s observation by observation.
    """
    sizes = [len(fr.ids) for fr in frames]
    if not sum(sizes):
        return
    fi = np.repeat(np.arange(len(frames)), sizes)
    lid = np.concatenate([np.asarray(fr.ids, np.int64) for fr in frames])
    order = np.lexsort((fi, lid))            # each track's observations in frame order
    lid, t_ns = lid[order], np.repeat([fr.t_ns for fr in frames], sizes).astype(np.int64)[order]
    uv = np.concatenate([fr.uv for fr in frames])[order]
    first = np.r_[True, lid[1:] != lid[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(len(lid)), 0))
    n = np.bincount(np.cumsum(first) - 1)[np.cumsum(first) - 1]   # its track's length
    pos = np.arange(len(lid)) - start                              # index within the track
    vel, keep = np.empty((len(lid), 2)), np.zeros(len(lid), bool)
    vel[order] = _velocities((t_ns - t_ns[start]) * 1e-9, uv, pos, n)
    keep[order] = n >= 2                     # (a single observation keeps its zero)
    for fr, a, b in zip(frames, np.cumsum([0] + sizes[:-1]), np.cumsum(sizes)):
        fr.velocity[keep[a:b]] = vel[a:b][keep[a:b]]


def _velocities(t: np.ndarray, uv: np.ndarray, pos: np.ndarray, n: np.ndarray) -> np.ndarray:
    """:func:`track_velocities`' median of the available candidates for every observation;
    ``t`` (s) from its track's first observation, ``pos`` its index in the track of
    length ``n`` (the arrays are ordered by track, then time)."""
    m = len(t)
    i = np.arange(m)
    cands = np.full((4, m, 2), np.nan)
    for c, h in enumerate((1, 2)):
        ok = (pos - h >= 0) & (pos + h < n)
        j = i[ok]
        cands[c, ok] = (uv[j + h] - uv[j - h]) / (t[j + h] - t[j - h])[:, None]
    for c, offs in ((2, (-3, -2, -1)), (3, (1, 2, 3))):
        ok = (pos + min(offs) >= 0) & (pos + max(offs) < n)
        j = i[ok]
        idx = j[:, None] + np.array(offs)[None, :]
        dt = t[idx] - t[j][:, None]
        A = np.stack([np.ones_like(dt), dt, dt ** 2], 2)
        cands[c, ok] = np.linalg.solve(A, uv[idx])[:, 1]
    s = np.sort(cands, axis=0)              # NaN (unavailable) last
    k = (~np.isnan(cands[:, :, 0])).sum(0)
    out = np.where((k % 2 == 1)[:, None], s[np.maximum(k - 1, 0) // 2, i],
                   (s[np.maximum(k // 2 - 1, 0), i] + s[k // 2 % 4, i]) / 2)
    none = (k == 0) & (n >= 2)               # two-frame tracks and the ends of three-frame ones
    j = i[none]
    a = np.where(pos[none] > 0, j - 1, j)
    out[none] = (uv[a + 1] - uv[a]) / (t[a + 1] - t[a])[:, None]
    return out


def write_features(path: Path, frames: list[FeatureFrame]) -> None:
    """Write frames in the ``features.csv`` format (frame_idx = position in the list)."""
    with open(path, "w") as f:
        f.write(HEADER + "\n")
        for k, fr in enumerate(frames):
            for lid, (u, v) in zip(fr.ids, fr.uv):
                f.write(f"{fr.t_ns},{k},{int(lid)},{u:.10g},{v:.10g}\n")
