"""Robust gyro bias from visual rotations (``vio.backend.gyro_init.robust_gyro_bias``)."""

from __future__ import annotations


import gtsam
import numpy as np
import pytest

from vio.backend.gyro_init import gyro_bias, pair_rotation, robust_gyro_bias
from vio.imu import ImuNoiseConfig, combined_params, integrate
from vio.io.types import ImuCalib, ImuData

CALIB = ImuCalib(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3, 200.0)
BG = np.array([-0.002, 0.021, 0.077])


def _window(seed: int, n_bad: int):
    """Keyframes every 0.1 s for 1.5 s of a rotating body; gyro readings = true rate +
    ``BG``; visual pairs 3 and 5 keyframes apart with 0.2-degree noise, ``n_bad`` of
    them replaced by rotations 8-20 degrees off (failed essential matrices)."""
    rng = np.random.default_rng(seed)
    params = combined_params(CALIB, ImuNoiseConfig())
    rates = rng.normal(0, 0.6, (15, 3))
    pims, R = [], [gtsam.Rot3()]
    for w in rates:
        t = np.arange(21) * 0.005
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
        integrate(pim, ImuData((t * 1e9).astype(np.int64), np.tile(w + BG, (21, 1)),
                               np.tile([9.81, 0, 0], (21, 1))))
        pims.append(pim)
        R.append(R[-1].compose(gtsam.Rot3.Expmap(w * 0.1)))
    pairs = []
    for s in (3, 5):
        for i in range(0, 15 - s + 1):
            Rij = R[i].between(R[i + s]).compose(gtsam.Rot3.Expmap(rng.normal(0, np.radians(0.2), 3)))
            pairs.append((i, i + s, Rij.matrix()))
    for m in rng.choice(len(pairs), n_bad, replace=False):
        ax = rng.normal(size=3)
        ang = np.radians(rng.uniform(8, 20))
        i, j, Rij = pairs[m]
        pairs[m] = (i, j, Rij @ gtsam.Rot3.Expmap(ax / np.linalg.norm(ax) * ang).matrix())
    return pims, pairs


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_robust_bias_ignores_wrong_visual_rotations(seed):
    pims, pairs = _window(seed, n_bad=12)   # 12 of 23 pairs wrong
    bg, agree = robust_gyro_bias(pims, pairs, max_bias=0.3)
    assert np.abs(bg - BG).max() < 0.01
    assert len(agree) >= 8
    assert np.abs(gyro_bias(pims, pairs) - BG).max() > 0.02   # least squares is pulled off


def test_robust_bias_equals_least_squares_on_clean_pairs():
    pims, pairs = _window(3, n_bad=0)
    bg, agree = robust_gyro_bias(pims, pairs, max_bias=0.3)
    assert len(agree) == len(pairs)
    assert np.allclose(bg, gyro_bias(pims, pairs), atol=1e-9)
    assert np.abs(bg - BG).max() < 0.005


def test_no_plausible_pair_gives_no_bias():
    pims, pairs = _window(4, n_bad=0)
    far = [(i, j, R @ gtsam.Rot3.Rz(np.radians(40)).matrix()) for i, j, R in pairs]
    bg, agree = robust_gyro_bias(pims, far, max_bias=0.3)
    assert agree == [] and np.all(bg == 0)


def _pair(seed: int, depth: tuple[float, float], baseline_m: float, fx: float = 458.0):
    """Normalized correspondences (N, 2) of 60 points at ``depth`` (m) in camera a, seen
    from camera b turned 3 degrees and moved ``baseline_m``; 0.3-px noise. Returns
    (uv_a, uv_b, R_ca_cb)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-0.6, 0.6, (60, 2))
    P_a = np.c_[uv, np.ones(60)] * rng.uniform(*depth, (60, 1))
    ax = rng.normal(size=3)
    R_ab = gtsam.Rot3.Expmap(ax / np.linalg.norm(ax) * np.radians(3.0)).matrix()
    t = rng.normal(size=3)
    t_ab = t / np.linalg.norm(t) * baseline_m
    P_b = (P_a - t_ab) @ R_ab       # R_ab^T (P_a - t_ab)
    noise = lambda: rng.normal(0, 0.3 / fx, (60, 2))   # noqa: E731
    return P_a[:, :2] / P_a[:, 2:] + noise(), P_b[:, :2] / P_b[:, 2:] + noise(), R_ab


@pytest.mark.parametrize("depth, baseline_m", [((8.0, 20.0), 0.03),    # ~1 px of parallax
                                                ((2.0, 5.0), 0.30)])   # tens of px
def test_pair_rotation_from_little_or_much_translation(depth, baseline_m):
    """With ~1 px of translation parallax most points triangulate beyond any cheirality
    check's distance limit (the real MH_05 start at 6.7 Hz: 0-5 of 50 points passed and
    the pair was lost); the essential matrix's rotation is still accurate, and of its
    two candidates the one next to the rotation-only fit is taken."""
    for seed in range(5):
        uv_a, uv_b, R_ab = _pair(seed, depth, baseline_m)
        R = pair_rotation(uv_a, uv_b, 458.0)
        assert R is not None
        assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R_ab.T @ R)))) < 0.3
