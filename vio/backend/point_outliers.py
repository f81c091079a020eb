"""The world points' outlier check (``vio.backend.point_tracks``): which observations
of which points the reprojection errors after an update reject.

A point whose worst error exceeds the limit either loses only its observation past the
limit, when that error is isolated (``VisionConfig.outlier_obs``: its factor is rebuilt
from the others and the point retired, as ORB-SLAM3 drops a map point's outlier edges in
its local bundle adjustment), or is dropped whole (its id restarted from the front end's
next observation), when its errors are spread, a depth left the valid range, or most of
the window's points are flagged at once.
"""

from __future__ import annotations

import numpy as np

from factors.jit import njit


@njit
def point_row_errors(start: np.ndarray, j: np.ndarray, uv: np.ndarray, vel: np.ndarray, off: np.ndarray,
                     P: np.ndarray, R: np.ndarray, t: np.ndarray, td: float, min_depth: float,
                     max_depth: float, out: np.ndarray) -> None:
    """``out[o]``: the normalized reprojection error of observation ``o`` of point ``P[i]``
    (world, m; its observations are rows ``start[i]:start[i + 1]``, seen by cam0 of window
    row ``j[o]``: ``R_w_c`` / ``t_w_c``), the observation moved by ``(td + off[o]) vel[o]``;
    every row of a point is inf when one of its depths leaves [min_depth, max_depth]."""
    for i in range(P.shape[0]):
        inside = True
        for o in range(start[i], start[i + 1]):
            f = j[o]
            q2 = (R[f, 0, 2] * (P[i, 0] - t[f, 0]) + R[f, 1, 2] * (P[i, 1] - t[f, 1])
                  + R[f, 2, 2] * (P[i, 2] - t[f, 2]))
            if not (q2 >= min_depth and q2 <= max_depth):
                inside = False
                break
        for o in range(start[i], start[i + 1]):
            if not inside:
                out[o] = np.inf
                continue
            f = j[o]
            d0, d1, d2 = P[i, 0] - t[f, 0], P[i, 1] - t[f, 1], P[i, 2] - t[f, 2]
            q0 = R[f, 0, 0] * d0 + R[f, 1, 0] * d1 + R[f, 2, 0] * d2
            q1 = R[f, 0, 1] * d0 + R[f, 1, 1] * d1 + R[f, 2, 1] * d2
            q2 = R[f, 0, 2] * d0 + R[f, 1, 2] * d1 + R[f, 2, 2] * d2
            s = td + off[o]
            ex = q0 / q2 - (uv[o, 0] - s * vel[o, 0])
            ey = q1 / q2 - (uv[o, 1] - s * vel[o, 1])
            out[o] = np.sqrt(ex * ex + ey * ey)


def worst_per_point(rows: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Each point's worst row error (NaN if any is NaN, as ``np.max``); ``start`` (n + 1,)
    with every point holding at least one row."""
    return np.maximum.reduceat(rows, start[:-1])


def rejections(rows: np.ndarray, start: np.ndarray, limit: float, keep_obs: bool, agree: float = 0.5,
               min_keep: int = 3, max_trim: int = 1) -> tuple[list[int], dict[int, np.ndarray]]:
    """The check's verdict on the points whose row errors ``rows`` (same units as
    ``limit``; point ``i`` holds rows ``start[i]:start[i + 1]``) exceed ``limit``:
    ``(dropped, trimmed)``, dropped = indices of the points rejected whole, trimmed =
    {point index: bool mask of its rows to drop}. With ``keep_obs`` a point loses only
    its rows past the limit when they are an isolated error: at most ``max_trim`` of them,
    at least ``min_keep`` rows stay, and those agree within ``agree * limit``. A point
    whose errors are spread (several rows near the limit: a poorly triangulated point,
    or a track drifting off its feature), with an infinite (depth range) or a NaN error,
    is dropped whole, and so is every flagged point when more than half of the points
    are flagged at once: then the estimate is at fault, not single observations (after
    an IMU gap, one trimmed point among 9 flagged of 9 kept the tilted map's geometry in
    the window: real V1_01, 3-s gap at 4 s, 0.120 -> 0.265 m)."""
    dropped: list[int] = []
    trimmed: dict[int, np.ndarray] = {}
    flagged = np.flatnonzero(~(worst_per_point(rows, start) <= limit))
    keep_obs = keep_obs and 2 * len(flagged) <= len(start) - 1
    for i in flagged:
        r = rows[start[i]:start[i + 1]]
        bad = r > limit
        n_bad = int(bad.sum())
        if (keep_obs and np.all(np.isfinite(r)) and n_bad <= max_trim and len(r) - n_bad >= min_keep
                and r[~bad].max() <= agree * limit):
            trimmed[int(i)] = bad
        else:
            dropped.append(int(i))
    return dropped, trimmed
