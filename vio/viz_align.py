"""Pure-numpy helpers of the Rerun view: track lengths, colours, and the 4-DoF
(yaw + translation) alignment that draws ground truth in the estimate's world.

Kept apart from ``vio.viz`` so they can be tested and reused without rerun.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from vio.io.types import GroundTruth

if TYPE_CHECKING:
    import gtsam


class Rows:
    """Append-only (N, k) float64 array with amortized O(1) appends."""

    def __init__(self, k: int) -> None:
        self._a = np.zeros((256, k))
        self.n = 0

    def append(self, row: np.ndarray) -> None:
        if self.n == len(self._a):
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self.n] = row
        self.n += 1

    @property
    def data(self) -> np.ndarray:
        return self._a[:self.n]


class TrackLengths:
    """Consecutive-frame appearance count per feature id (1 = first seen in this frame)."""

    def __init__(self) -> None:
        self._ids = np.zeros(0, np.int64)   # sorted ids of the previous frame
        self._n = np.zeros(0, np.int64)

    def update(self, ids: np.ndarray) -> np.ndarray:
        """(M,) ids of this frame -> (M,) int64 track lengths, in the order given."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        n = np.ones(ids.size, np.int64)
        if self._ids.size and ids.size:
            k = np.searchsorted(self._ids, ids).clip(max=self._ids.size - 1)
            hit = self._ids[k] == ids
            n[hit] = self._n[k[hit]] + 1
        order = np.argsort(ids, kind="stable")
        self._ids, self._n = ids[order], n[order]
        return n


def _rgba(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8-range RGB -> (...,) uint32 packed 0xRRGGBBAA (opaque); rerun takes
    packed colours without a per-call conversion."""
    c = np.asarray(rgb, np.uint32)
    return (c[..., 0] << 24) | (c[..., 1] << 16) | (c[..., 2] << 8) | np.uint32(0xFF)


def track_colors(full: int) -> np.ndarray:
    """(full + 1,) packed RGBA lookup by track length: 1 red, ``full`` // 2 yellow, ``full`` green."""
    f = np.clip((np.arange(full + 1) - 1) / max(full - 1, 1), 0.0, 1.0)
    rgb = np.stack([np.minimum(1.0, 2.0 * (1.0 - f)), np.minimum(1.0, 2.0 * f), np.zeros_like(f)], 1)
    return _rgba((rgb * 255).astype(np.uint8))


ORANGE, GREEN, BLUE = _rgba([[255, 140, 0]]), _rgba([[40, 180, 40]]), _rgba([[90, 90, 220]])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def fit_yaw_translation(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares 4-DoF fit of ``dst ~ R src + t`` with ``R`` a rotation about z.

    ``src``, ``dst``: (N, 3) matched points (both worlds gravity-aligned, z up).
    Returns ``R`` (3, 3) and ``t`` (3,). The yaw maximizes ``sum b . R a`` over the
    centred horizontal parts ``a``, ``b``: ``atan2(sum a x b, sum a . b)``.
    """
    ms, md = src.mean(0), dst.mean(0)
    a, b = src[:, :2] - ms[:2], dst[:, :2] - md[:2]
    yaw = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
                     float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))
    R = _rot_z(yaw)
    return R, md - R @ ms


class GroundTruthAligner:
    """Maps ground-truth positions into the estimate's world (display only).

    The VIO world and the ground-truth world differ by a yaw and a translation
    (both gravity-aligned). The first matched pose pair gives the initial
    transform; once the matched positions spread over ``min_spread_m`` (horizontal
    RMS), ``refit`` replaces it by the least-squares fit over all matched positions.
    ``R`` (3, 3), ``t`` (3,): ``p_est ~ R p_gt + t``.
    """

    def __init__(self, gt: GroundTruth, max_gap_s: float = 0.1, min_spread_m: float = 0.3) -> None:
        if len(gt) < 2:
            raise ValueError("ground truth needs at least 2 poses")
        self.gt = gt
        self._t = np.asarray(gt.t_ns, np.int64)
        self._p = np.asarray(gt.p_w, float)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.min_spread_m = min_spread_m
        self.R: np.ndarray | None = None
        self.t: np.ndarray | None = None
        self._est, self._ref = Rows(3), Rows(3)
        self._span: tuple[int, int] | None = None

    def position(self, t_ns: int) -> np.ndarray | None:
        """Ground-truth position (3,) interpolated at ``t_ns``; None outside the data or in a gap."""
        k = int(np.searchsorted(self._t, t_ns))
        if k < len(self._t) and self._t[k] == t_ns:
            return self._p[k]
        if k == 0 or k == len(self._t) or self._t[k] - self._t[k - 1] > self.max_gap_ns:
            return None
        w = (t_ns - self._t[k - 1]) / (self._t[k] - self._t[k - 1])
        return (1.0 - w) * self._p[k - 1] + w * self._p[k]

    def add(self, t_ns: int, T_w_b: "gtsam.Pose3") -> float | None:
        """Record one estimate; returns its distance (m) to the aligned ground truth."""
        p_gt = self.position(t_ns)
        if p_gt is None:
            return None
        p_est = np.asarray(T_w_b.translation(), float)
        if self.R is None:
            k = int(np.argmin(np.abs(self._t - t_ns)))
            R_rel = T_w_b.rotation().matrix() @ self.gt.pose(k).rotation().matrix().T
            self.R = _rot_z(math.atan2(R_rel[1, 0], R_rel[0, 0]))
            self.t = p_est - self.R @ p_gt
        self._est.append(p_est)
        self._ref.append(p_gt)
        self._span = (t_ns if self._span is None else self._span[0], t_ns)
        return float(np.linalg.norm(self.R @ p_gt + self.t - p_est))

    @property
    def n_matched(self) -> int:
        return self._est.n

    def refit(self) -> bool:
        """Refit from all matched positions if they spread enough; True if refitted."""
        if self._est.n < 3:
            return False
        ref = self._ref.data
        spread = math.sqrt(float(np.mean(np.sum((ref[:, :2] - ref[:, :2].mean(0)) ** 2, 1))))
        if spread < self.min_spread_m:
            return False
        self.R, self.t = fit_yaw_translation(ref, self._est.data)
        return True

    def strip(self) -> np.ndarray:
        """(N, 3) aligned ground-truth positions over the matched time span."""
        if self._span is None:
            return np.zeros((0, 3))
        i0, i1 = np.searchsorted(self._t, self._span[0]), np.searchsorted(self._t, self._span[1], "right")
        return self._p[i0:i1] @ self.R.T + self.t

    def matched_strip(self) -> np.ndarray:
        """(N, 3) aligned ground-truth positions at the estimate's matched times (one
        per ``add`` that returned a distance), under the current alignment."""
        if self.R is None:
            return np.zeros((0, 3))
        return self._ref.data @ self.R.T + self.t
