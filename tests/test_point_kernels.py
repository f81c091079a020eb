"""The compiled world-point kernels against the numpy arithmetic they replace, to the bit:
the predicted td velocities (vio.backend.td_velocity.point_velocities, and
points_velocities over many points at once) and the outlier check's worst reprojection
error (vio.backend.point_tracks.point_worst_errors)."""

import gtsam
import numpy as np
import pytest

from vio.backend import graph
from vio.backend.landmarks import cross3
from vio.backend.point_tracks import point_worst_errors
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


def _worst_numpy(j, uv, vel, off, p, R, t, td, min_depth, max_depth):
    q = np.einsum("nab,na->nb", R[j], p - t[j])
    if not np.all((q[:, 2] >= min_depth) & (q[:, 2] <= max_depth)):
        return np.inf
    moved = uv - (td + off)[:, None] * vel
    return float(np.max(np.linalg.norm(q[:, :2] / q[:, 2:3] - moved, axis=1)))


@pytest.mark.parametrize("seed", range(5))
def test_point_worst_errors_match_numpy(seed):
    rng = np.random.default_rng(100 + seed)
    R, t, _, _ = _table(rng)
    counts = rng.integers(1, 9, 40)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    N = int(start[-1])
    j = rng.integers(0, len(R), N).astype(np.int64)
    uv, vel, off = rng.normal(size=(N, 2)) * 0.3, rng.normal(size=(N, 2)), rng.normal(size=N) * 0.01
    P = rng.normal(size=(40, 3)) * 3           # some points behind or too close: inf
    out = np.empty(40)
    point_worst_errors(start, j, uv, vel, off, P, R, t, 0.004, 0.1, 20.0, out)
    want = [_worst_numpy(j[a:b], uv[a:b], vel[a:b], off[a:b], P[i], R, t, 0.004, 0.1, 20.0)
            for i, (a, b) in enumerate(zip(start[:-1], start[1:]))]
    assert np.isinf(want).any() and np.isfinite(want).any()
    assert np.array_equal(out, np.array(want))


def test_cross_matches_numpy():
    rng = np.random.default_rng(7)
    for _ in range(1000):
        a, b = rng.normal(size=3) * rng.uniform(0, 50), rng.normal(size=3)
        assert np.array_equal(cross3(a, b), np.cross(a, b))
