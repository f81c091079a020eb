"""TrackFrame's numba rows (``factors.trackframe_kernel``) against the numpy temporal residual
(``factors.photometric.temporal_eval`` + ``sqrt_weights``, whose Jacobians the shared
suite checks numerically): same whitened residuals, pose/affine Jacobian and validity,
with and without the inverse-depth variance term, and with a rolling shutter (its row
times from the pinhole rows, or from the sensor rows through a lens)."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from cases_photometric import H, LENS, W, K, analytic_image
from factors.image_ops import BilinearImage
from factors.photometric import PhotometricParams, make_host_patch, sqrt_weights, temporal_eval
from factors.photometric_shutter import Shutter, rolled_bearings
from factors.photometric_warp import pixel_row_s, row_model
from factors.trackframe_kernel import track_rows


@pytest.mark.parametrize("seed,use_var,rolling,lens", [(1, False, False, None), (2, True, False, None),
                                                       (3, True, False, None), (4, True, True, None),
                                                       (5, True, True, "radial-tangential"),
                                                       (6, False, True, "equidistant")])
def test_track_rows_match_the_numpy_residual(seed: int, use_var: bool, rolling: bool, lens: str | None) -> None:
    rng = np.random.default_rng(seed)
    ref, new = (BilinearImage(analytic_image(rng).render()) for _ in range(2))
    n = 40
    uv = np.stack([rng.uniform(-20, W + 20, n), rng.uniform(-20, H + 20, n)], 1)  # some off-image
    patch = make_host_patch(ref, uv, K)
    rho = rng.uniform(0.2, 1.5, n)
    var = rng.uniform(0.0, 0.05, n) if use_var else np.zeros(n)
    T = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.1)
    ab_i, ab_j = np.array([0.1, 3.0]), np.array([-0.05, 7.0])
    rows = None if lens is None else row_model((K.fx, K.fy, K.cx, K.cy), lens, LENS[lens])
    sh = Shutter(1e-4, rng.normal(0, 0.5, 6), rng.normal(0, 0.5, 6), rows, rows) if rolling else None
    ev = temporal_eval(gtsam.Pose3(), T, rho, ab_i, ab_j, patch, new, K, gtsam.Pose3(), shutter=sh)
    sw = sqrt_weights(ev, patch, PhotometricParams(4.0, 50.0, None), var if use_var else 0.0)
    oob = 2.0
    r_ref = np.where(ev.valid, sw * ev.r, oob).reshape(-1)
    J_ref = (np.concatenate([ev.J["pose_j"], ev.J["ab_j"]], -1) * sw[..., None]).reshape(-1, 8)
    N, P = patch.intensity.shape
    r_w, J = np.empty(N * P), np.empty((N * P, 8))
    r_raw, valid = np.empty((N, P)), np.empty((N, P), bool)
    if rolling:
        bearing, sv = rolled_bearings(patch.bearing, pixel_row_s(sh.line_time_s, patch.uv, rows), sh.host)
        rm = row_model((K.fx, K.fy, K.cx, K.cy)) if rows is None else rows
        rs = (sv, sh.target[:3].copy(), sh.target[3:].copy(), sh.line_time_s, rm)
    else:
        bearing, rs = patch.bearing, (np.zeros((n, 3)), np.zeros(3), np.zeros(3), 0.0, np.zeros(9))
    track_rows(bearing, patch.intensity, patch.grad_sq, patch.valid, rho, var,
               T.inverse().rotation().matrix(), T.inverse().translation(), np.array([K.fx, K.fy, K.cx, K.cy]),
               new._stack, math.exp(ab_j[0] - ab_i[0]), ab_i[1], ab_j[1], 50.0 ** 2, 2 * 4.0 ** 2,
               oob, r_w, J, r_raw, valid, *rs)
    assert 0 < valid.sum() < valid.size
    np.testing.assert_array_equal(valid, ev.valid)
    np.testing.assert_allclose(r_w, r_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(J, J_ref, rtol=1e-9, atol=1e-9 * np.abs(J_ref).max())
    np.testing.assert_allclose(r_raw, np.where(ev.valid, ev.r, 0.0), atol=1e-9)
