"""The residual rows of many landmark tracks in one compiled pass.

A landmark factor (``vio.backend.track_factor`` per landmark, ``vio.backend.bundles`` per
anchor keyframe) needs, for each track over its frames (anchor first): the td velocity of
every cam0 observation (predicted from the state, ``vio.backend.td_velocity``, or
measured; capped at ``VisionConfig.td_velocity_max``), its row offset (seed 004), and the
residual rows (cam0 observations of the non-anchor keyframes, then the cam1 observations
of every keyframe with a match) with their tangent bases. Built one track at a time, that
was ~40 small numpy and Python calls per track at every keyframe (8 of a real MH_01
stereo keyframe's 32 ms). Here the observations of all tracks of an update are gathered
into flat arrays (``Obs.packed``) and one Numba pass fills every track's rows; each
track gets views into them. The arithmetic is the per-track code's, in the same order:
the numbers are identical (``tests/test_factor_speedups.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.jit import njit as _njit
from factors.bearing_model import tangent_basis
from vio.backend.graph import _zero_fast_rows, row_offsets
from vio.backend.landmarks import Obs, Track
from vio.backend.td_velocity import predicted_velocities

_NO_RIG = (np.eye(3), np.zeros(3))        # cam1 placeholders without a rig (never read)
_NO_TABLE = (np.zeros((1, 3, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)))


@dataclass(frozen=True)
class TrackRows:
    """One track's residual rows: ``uv`` (n, 2) normalized, ``vel`` (n, 2) td velocities
    (1/s), ``target`` (n,) index into the track's frames (0 = anchor), ``right`` (n,) cam1
    flags, ``offset`` (n,) row offsets (s), ``basis`` (n, 2, 3); the anchor's ray ``a_uv``
    (2,), td velocity ``a_vel`` (2,) and offset ``a_off`` (s)."""

    uv: np.ndarray
    vel: np.ndarray
    target: np.ndarray
    right: np.ndarray
    offset: np.ndarray
    basis: np.ndarray
    a_uv: np.ndarray
    a_vel: np.ndarray
    a_off: float


def track_rows(items: list[tuple[Track, list[int], float]], stereo: bool, predicted: bool,
               table: tuple | None, rig_c1: tuple | None, min_depth: float, gate: float,
               vmax: float, line_time_s: float) -> list[TrackRows]:
    """The rows of each ``(track, frames, lam)`` in ``items`` (frames anchor first, ``lam``
    the inverse depth, 1/m); records each track's cam0 velocity and offset per frame for
    the outlier check (``Track.set_shifts``).

    ``stereo``: cam1 rows for the observations with a match; ``predicted``: the td
    velocities predicted at ``lam`` (tracks with ``lam > 0``; the others, measured) from
    ``table`` (``vio.backend.motion.motion_table``; needed only then) and, for cam1,
    ``rig_c1`` (``td_velocity.rig_c1``; None: cam1 velocities measured); ``min_depth`` (m)
    and ``gate`` (1/s) as in ``td_velocity.predicted_velocities``; ``vmax`` (1/s) the cap
    of every td velocity; ``line_time_s`` the rolling shutter's row time."""
    if not items:
        return []
    P, start, off = gather([[tr.obs[f] for f in fr] for tr, fr, _ in items], line_time_s)
    n_obs = np.diff(start)
    has_r = P[:, 6] > 0
    n_r = np.add.reduceat(has_r.astype(np.int64), start[:-1]) if stereo else np.zeros(len(items), np.int64)
    n_rows = n_obs - 1 + n_r
    if np.any(n_rows < 1):
        raise ValueError("landmark track has no observation outside its anchor frame")
    lam = np.array([it[2] for it in items], float)
    pred = (lam > 0) & predicted
    if pred.any():
        pos = table[0]
        idx = np.array([pos[f] for _, fr, _ in items for f in fr], np.int64)
        R, t, w, v = table[1:]
    else:
        idx = np.zeros(len(P), np.int64)
        R, t, w, v = _NO_TABLE
    R10, t01 = _NO_RIG if rig_c1 is None else rig_c1
    c = np.ascontiguousarray
    uv_o, meas, ruv, rmeas = c(P[:, 0:2]), c(P[:, 2:4]), c(P[:, 7:9]), c(P[:, 9:11])
    rstart = run_starts(n_rows)
    m = int(rstart[-1])
    v0, rv = np.empty((len(P), 2)), np.empty((len(P), 2))
    uv, vel, offset = np.empty((m, 2)), np.empty((m, 2)), np.empty(m)
    target, right = np.empty(m, np.int64), np.zeros(m, np.bool_)
    roff = row_offsets(P[:, 11], P[:, 5], line_time_s)      # cam1's own rows (rolling shutter)
    _fill(start, rstart, idx, uv_o, meas, has_r, ruv, rmeas, off, roff, lam, pred, rig_c1 is not None, stereo,
          R, t, w, v, R10, t01, float(min_depth), float(gate), float(vmax), v0, rv, uv, vel, target, right,
          offset)
    basis = tangent_basis(uv)
    shift = np.concatenate([uv_o, v0, off[:, None]], axis=1)    # Track.set_shifts: each track a view
    out = []
    for j, (tr, fr, _) in enumerate(items):
        s, r0, r1 = start[j], rstart[j], rstart[j + 1]
        tr.set_shifts(fr, shift[s:s + len(fr)])
        out.append(TrackRows(uv[r0:r1], vel[r0:r1], target[r0:r1], right[r0:r1], offset[r0:r1],
                             basis[r0:r1], uv_o[s], v0[s], float(off[s])))
    return out


def gather(groups: list[list[Obs]], line_time_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observations of every group (one landmark's, in its frames' order) in one
    array: ``P`` (N, 12) their ``Obs.packed`` rows, ``start`` (G + 1,) where each group's
    rows begin (and the total), ``off`` (N,) their row offsets (s, ``graph.row_offsets``
    at ``line_time_s``)."""
    P = np.array([o.packed for obs in groups for o in obs], float).reshape(-1, 12)
    start = run_starts(np.array([len(obs) for obs in groups], np.int64))
    return P, start, row_offsets(P[:, 4], P[:, 5], line_time_s)


def run_starts(counts: np.ndarray) -> np.ndarray:
    """(n + 1,) start of each of n runs of ``counts`` (n,) rows, and the total."""
    out = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=out[1:])
    return out


@_njit
def _fill(start, rstart, idx, uv_o, meas, has_r, ruv, rmeas, off, roff, lam, pred, pred_r, stereo,
          R, t, w, v, R10, t01, min_depth, gate, vmax, v0, rv, uv, vel, target, right, offset):
    """Per track j (observations ``start[j]:start[j+1]``, rows ``rstart[j]:rstart[j+1]``):
    the cam0 / cam1 td velocities ``v0`` / ``rv`` (predicted where ``pred[j]``, cam1 only
    with ``pred_r``; else measured), capped at ``vmax``; then the rows."""
    for j in range(start.shape[0] - 1):
        s, e = start[j], start[j + 1]
        hr = has_r[s:e] & pred_r
        if pred[j]:
            predicted_velocities(idx[s:e], uv_o[s:e], meas[s:e], hr, ruv[s:e], rmeas[s:e], R, t, w, v,
                                 lam[j], R10, t01, min_depth, gate, v0[s:e], rv[s:e])
        if not (pred[j] and pred_r):
            rv[s:e] = rmeas[s:e]
        if not pred[j]:
            v0[s:e] = meas[s:e]
        _zero_fast_rows(v0[s:e], vmax)
        _zero_fast_rows(rv[s:e], vmax)
        r = rstart[j]
        for i in range(1, e - s):
            uv[r], vel[r], target[r], right[r], offset[r] = uv_o[s + i], v0[s + i], i, False, off[s + i]
            r += 1
        if not stereo:
            continue
        for i in range(e - s):
            if has_r[s + i]:
                uv[r], vel[r], target[r], right[r], offset[r] = ruv[s + i], rv[s + i], i, True, roff[s + i]
                r += 1


def compile_kernel() -> None:
    """Load (or compile) :func:`_fill` now with the argument types :func:`track_rows`
    passes, not at the first keyframe (a stall of ~0.3 s from Numba's disk cache, ~4 s
    compiling)."""
    z2, z1, i1 = np.zeros((1, 2)), np.zeros(1), np.zeros(2, np.int64)
    b1 = np.zeros(1, np.bool_)
    R, t, w, v = _NO_TABLE
    R10, t01 = _NO_RIG
    _fill(i1, i1, i1[:1].copy(), z2, z2, b1, z2, z2, z1, z1, z1, b1, False, False, R, t, w, v, R10, t01,
          0.1, 1.0, 1.0, z2.copy(), z2.copy(), z2.copy(), z2.copy(), np.zeros(1, np.int64), b1.copy(), z1.copy())
