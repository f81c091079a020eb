"""Landmark bookkeeping: which keyframes observed a track, its anchor and its keys.

This holds measurements and graph bookkeeping only; every estimate (inverse
depth, poses) lives in the smoother's ``Values``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import gtsam
import numpy as np


@dataclass(frozen=True)
class Obs:
    """One observation: normalized coordinates (2,), velocity (2,) 1/s, pixel row;
    ``right_uv`` / ``right_velocity``: the same point in cam1 (None without stereo);
    ``td_obs`` (s): the part of the td variable its keyframe's time already holds (the
    sync layer's offset for this frame minus the estimator's constant ``td_applied_s``),
    so the observation is ``td - td_obs`` after its keyframe; ``right_row``: cam1's pixel
    row of ``right_uv`` (its rolling-shutter time; NaN: unknown, ``row`` stands in)."""

    uv: np.ndarray
    velocity: np.ndarray
    row: float
    right_uv: np.ndarray | None = None
    right_velocity: np.ndarray | None = None
    td_obs: float = 0.0
    right_row: float = float("nan")

    @property
    def right_time_row(self) -> float:
        """The row whose rolling-shutter time the cam1 observation has: ``right_row``, or
        cam0's ``row`` where it is unknown."""
        return self.right_row if np.isfinite(self.right_row) else self.row

    @cached_property
    def packed(self) -> np.ndarray:
        """(12,): ``uv``, ``velocity``, ``row``, ``td_obs``, 1.0 with a cam1 match (else 0),
        ``right_uv``, ``right_velocity`` (zeros without), ``right_time_row``: one row of
        ``vio.backend.track_arrays.track_rows``' gather."""
        r = self.right_uv is not None
        if r and self.right_velocity is None:
            raise ValueError("an observation with right_uv needs right_velocity")
        right = (*self.right_uv, *self.right_velocity) if r else (0.0, 0.0, 0.0, 0.0)
        return np.array([*self.uv, *self.velocity, self.row, self.td_obs, float(r), *right,
                         self.right_time_row], float)


@dataclass
class Track:
    """A landmark's observations by keyframe index, its current inverse-depth key
    (anchored in keyframe ``anchor``), and the smoother indices of its factors
    (one factor per landmark; with stereo it carries the cam1 observations too).
    ``td_shift[f]``: (vel (2,) 1/s, time offset s) of the cam0 observation in keyframe f
    as its current factor shifts it, ``uv - (td + offset) * vel`` (seed 004).
    ``lam``: the inverse depth (1/m) when it is eliminated inside the factor
    (``VisionConfig.eliminate_depth``, ``vio.backend.bundles``) instead of a variable;
    ``lam_prior`` (mean 1/m, information in whitened units): what the observations of
    keyframes that left the window said about it; ``entry``: (frames, arrays) of its last
    eliminated-depth factor, reused while it is no longer observed. ``shift_rows``: (frames,
    (n, 5) rows ``uv``, td ``vel``, ``offset``) of ``td_shift``'s frames in order, both set by
    :meth:`set_shifts`: the outlier check's observations in one array
    (``graph.worst_reprojection_errors``). ``weak``: it entered after waiting out
    ``VisionConfig.max_wait_keyframes`` without parallax, so its depth is a guess."""

    lid: int
    obs: dict[int, Obs] = field(default_factory=dict)
    key: int | None = None
    anchor: int | None = None
    factor_indices: list[int] = field(default_factory=list)
    td_shift: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)
    waited: int = 0
    rejected: bool = False
    lam: float = 0.0
    lam_prior: tuple[float, float] | None = None
    entry: tuple | None = None
    shift_rows: tuple[tuple[int, ...], np.ndarray] | None = None
    weak: bool = False

    def frames(self) -> list[int]:
        return sorted(self.obs)

    def set_shifts(self, frames: list[int], rows: np.ndarray) -> None:
        """Record how its factor shifts the cam0 observations in ``frames``: ``rows`` (n, 5)
        ``uv``, td ``vel``, ``offset``, kept whole (``shift_rows``) and per frame
        (``td_shift``)."""
        self.td_shift = {f: (rows[i, 2:4], float(rows[i, 4])) for i, f in enumerate(frames)}
        self.shift_rows = (tuple(frames), rows)

    def stereo_frames(self) -> list[int]:
        return [f for f in self.frames() if self.obs[f].right_uv is not None]

    def shifted_uv(self, f: int, td: float) -> np.ndarray:
        """The cam0 observation (2,) of keyframe ``f`` moved to the keyframe's time as its
        factor moves it (``td_shift``, seed 004) at the td estimate ``td`` (the td
        variable, s); unshifted where the track has no factor yet."""
        s = self.td_shift.get(f)
        uv = self.obs[f].uv
        return uv if s is None else uv - (td + s[1]) * s[0]

    def anchor_point(self, T_w_c: gtsam.Pose3, lam: float, td: float) -> np.ndarray:
        """The point (3,) at inverse depth ``lam`` (1/m) on the anchor observation's ray,
        in the frame ``T_w_c`` (the anchor camera's pose) maps into; ``td`` as in
        :func:`anchor_points`."""
        uv = self.shifted_uv(self.anchor, td)
        return T_w_c.transformFrom(np.array([uv[0], uv[1], 1.0]) / lam)


def anchor_points(tracks: list[Track], lams: np.ndarray, cams: dict[int, gtsam.Pose3],
                  td: float) -> np.ndarray:
    """World points (N, 3) of ``tracks`` at inverse depths ``lams`` (N,) 1/m, each on its
    anchor observation's ray from its anchor camera ``cams[track.anchor]`` (T_w_c).
    ``td``: the td estimate (the td variable, s): the ray is that of the anchor
    observation moved to the keyframe's time as the factors move it
    (:meth:`Track.shifted_uv`), so the points are those the factors place (with td at
    25 ms and the camera turning at 0.5 rad/s the raw ray is ~6 px off)."""
    if not tracks:
        return np.zeros((0, 3))
    M = {f: cams[f].matrix() for f in {tr.anchor for tr in tracks}}
    A = np.array([M[tr.anchor] for tr in tracks])
    uv = np.array([tr.shifted_uv(tr.anchor, td) for tr in tracks])
    ray = np.c_[uv, np.ones(len(tracks))] / np.asarray(lams, float)[:, None]
    return np.einsum("nij,nj->ni", A[:, :3, :3], ray) + A[:, :3, 3]


def bearing_depth(anchor_uv: np.ndarray, T_w_ca: gtsam.Pose3,
                  others: list[tuple[np.ndarray, gtsam.Pose3]]) -> tuple[float, float]:
    """Depth along the anchor ray (z in the anchor camera, m) by linear least squares
    over the other views, and the largest ray angle (deg) between anchor and others.

    For each other camera j: ``m_j x (R_ja d m_a + t_ja) = 0`` is linear in ``d``.
    Returns ``(nan, angle)`` when the system is degenerate.
    """
    m_a = np.array([anchor_uv[0], anchor_uv[1], 1.0])
    A, b, max_angle = [], [], 0.0
    ray_a_w = T_w_ca.rotation().matrix() @ m_a
    for uv, T_w_cj in others:
        m_j = np.array([uv[0], uv[1], 1.0])
        T_j_a = T_w_cj.between(T_w_ca)
        R, t = T_j_a.rotation().matrix(), T_j_a.translation()
        A.append(cross3(m_j, R @ m_a))
        b.append(-cross3(m_j, t))
        ray_j_w = T_w_cj.rotation().matrix() @ m_j
        cosang = ray_a_w @ ray_j_w / (np.linalg.norm(ray_a_w) * np.linalg.norm(ray_j_w))
        max_angle = max(max_angle, float(np.degrees(np.arccos(np.clip(cosang, -1, 1)))))
    a, bb = np.concatenate(A), np.concatenate(b)
    denom = float(a @ a)
    if denom < 1e-12:
        return float("nan"), max_angle
    return float(a @ bb) / denom, max_angle


def stereo_depth(uv0: np.ndarray, uv1: np.ndarray, T_c0_c1: gtsam.Pose3) -> float:
    """Depth (z in cam0, m) of a point seen at ``uv0`` in cam0 and ``uv1`` in cam1,
    by the same linear least squares as :func:`bearing_depth`."""
    d, _ = bearing_depth(uv0, gtsam.Pose3(), [(uv1, T_c0_c1)])
    return d


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors (the same arithmetic, without its ~20 us of overhead)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
