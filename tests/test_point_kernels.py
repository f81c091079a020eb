"""The compiled world-point kernels against the numpy arithmetic they replace, to the bit:
the predicted td velocities (vio.backend.td_velocity.point_velocities, and
points_velocities over many points at once) and the outlier check's worst reprojection
errors per observation (vio.backend.point_outliers.point_row_errors), and the check's
verdict (vio.backend.point_outliers.rejections)."""

import gtsam
import numpy as np
import pytest

from vio.backend import graph
from vio.backend.landmarks import cross3
from vio.backend.point_outliers import point_row_errors, rejections, worst_per_point
from vio.backend.td_velocity import point_velocities, points_velocities


def _table(rng, K=10):
    R = np.array([gtsam.Rot3.Expmap(rng.normal(size=3)).matrix() for _ in range(K)])
    return R, rng.normal(size=(K, 3)), rng.normal(size=(K, 3)), rng.normal(size=(K, 3))


def _velocities_numpy(j, R, t, w, v, p_w, meas, min_depth, gate, vmax):
    pc = np.einsum("nab,na->nb", R[j], p_w - t[j])
    dp = -np.cross(w[j], pc) - v[j]
    z = pc[:, 2:3]
    front = z[:, 0] >= min_depth
    zs = np.where(front[:, None], z, 1.0)
    pred = (dp[:, :2] * zs - pc[:, :2] * dp[:, 2:3]) / zs ** 2
    ok = front & (np.linalg.norm(pred - meas, axis=1) <= gate)
    return graph._td_velocity(np.where(ok[:, None], pred, 0.0), vmax)


@pytest.mark.parametrize("seed", range(5))
def test_point_velocities_match_numpy(seed):
    rng = np.random.default_rng(seed)
    for _ in range(200):
        R, t, w, v = _table(rng)
        n = int(rng.integers(1, 12))
        j = rng.integers(0, len(R), n).astype(np.int64)
        p = rng.normal(size=3) * 4
        meas = graph._td_velocity(rng.normal(size=(n, 2)), 3.0)
        out = np.empty((n, 2))
        point_velocities(j, R, t, w, v, p, meas, 0.1, 1.5, 3.0, out)
        assert np.array_equal(out, _velocities_numpy(j, R, t, w, v, p, meas, 0.1, 1.5, 3.0))


def test_points_velocities_equal_the_per_point_kernel():
    rng = np.random.default_rng(7)
    R, t, w, v = _table(rng)
    n = np.array([3, 1, 6, 2])
    start = np.r_[0, np.cumsum(n)].astype(np.int64)
    j = rng.integers(0, len(R), start[-1]).astype(np.int64)
    P = rng.normal(size=(len(n), 3)) * 4
    meas = graph._td_velocity(rng.normal(size=(start[-1], 2)), 3.0)
    out = np.full((start[-1], 2), np.nan)
    points_velocities(start, j, R, t, w, v, P, meas, 0.1, 1.5, 3.0, out)
    for i in range(len(n)):
        a, b = start[i], start[i + 1]
        ref = np.empty((b - a, 2))
        point_velocities(j[a:b].copy(), R, t, w, v, P[i].copy(), meas[a:b].copy(), 0.1, 1.5, 3.0, ref)
        assert np.array_equal(out[a:b], ref)
    assert out.any()


def _rows_numpy(j, uv, vel, off, p, R, t, td, min_depth, max_depth):
    q = np.einsum("nab,na->nb", R[j], p - t[j])
    if not np.all((q[:, 2] >= min_depth) & (q[:, 2] <= max_depth)):
        return np.full(len(j), np.inf)
    moved = uv - (td + off)[:, None] * vel
    return np.linalg.norm(q[:, :2] / q[:, 2:3] - moved, axis=1)


@pytest.mark.parametrize("seed", range(5))
def test_point_row_errors_match_numpy(seed):
    rng = np.random.default_rng(100 + seed)
    R, t, _, _ = _table(rng)
    counts = rng.integers(1, 9, 40)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    N = int(start[-1])
    j = rng.integers(0, len(R), N).astype(np.int64)
    uv, vel, off = rng.normal(size=(N, 2)) * 0.3, rng.normal(size=(N, 2)), rng.normal(size=N) * 0.01
    P = rng.normal(size=(40, 3)) * 3           # some points behind or too close: inf
    out = np.empty(N)
    point_row_errors(start, j, uv, vel, off, P, R, t, 0.004, 0.1, 20.0, out)
    want = np.concatenate([_rows_numpy(j[a:b], uv[a:b], vel[a:b], off[a:b], P[i], R, t, 0.004, 0.1, 20.0)
                           for i, (a, b) in enumerate(zip(start[:-1], start[1:]))])
    assert np.isinf(want).any() and np.isfinite(want).any()
    assert np.allclose(out, want, rtol=1e-12, atol=0) and np.array_equal(np.isinf(out), np.isinf(want))
    worst = worst_per_point(out, start)
    assert np.array_equal(worst, [out[a:b].max() for a, b in zip(start[:-1], start[1:])])


def test_rejections_trim_isolated_outliers_and_drop_inconsistent_points():
    counts = [4, 4, 2, 3, 3, 3] + [2] * 6
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    rows = np.array([1, 2, 1, 1,         # fine
                     1, 9, 1, 1,         # one of four past the limit: trimmed
                     1, 9,               # only one would stay: dropped
                     1, 9, 9,            # most disagree: dropped
                     1, 1, np.inf,       # a depth out of range: dropped
                     1, np.nan, 1]       # NaN: dropped
                    + [1, 1] * 6, float)  # fine (5 of 12 points flagged: not a mass rejection)
    dropped, trimmed = rejections(rows, start, 6.0, keep_obs=True, min_keep=3, max_trim=1)
    assert dropped == [2, 3, 4, 5] and list(trimmed) == [1]
    assert trimmed[1].tolist() == [False, True, False, False]
    dropped, trimmed = rejections(rows, start, 6.0, keep_obs=False, min_keep=3, max_trim=1)
    assert dropped == [1, 2, 3, 4, 5] and not trimmed
    # more than half of the points flagged at once: the estimate is suspect, all dropped
    dropped, trimmed = rejections(rows[:19], start[:7], 6.0, keep_obs=True)
    assert dropped == [1, 2, 3, 4, 5] and not trimmed
    one = np.array([0, 5, 7], np.int64)    # one isolated error next to a fine point
    # two past the limit among five: over max_trim, dropped
    dropped, trimmed = rejections(np.array([1, 9, 1, 9, 1, 1, 1.0]), one, 6.0, keep_obs=True)
    assert dropped == [0] and not trimmed
    # the others near the limit (spread errors, a poorly placed point): dropped
    dropped, trimmed = rejections(np.array([5, 9, 5, 5, 5, 1, 1.0]), one, 6.0, keep_obs=True)
    assert dropped == [0] and not trimmed
    dropped, trimmed = rejections(np.array([5, 9, 5, 5, 5, 1, 1.0]), one, 6.0, keep_obs=True, agree=1.0)
    assert not dropped and list(trimmed) == [0]


def test_cross_matches_numpy():
    rng = np.random.default_rng(7)
    for _ in range(1000):
        a, b = rng.normal(size=3) * rng.uniform(0, 50), rng.normal(size=3)
        assert np.array_equal(cross3(a, b), np.cross(a, b))
