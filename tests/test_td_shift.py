"""The outlier check moves observations to their keyframe's time as the td factor does."""

from __future__ import annotations

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.config import BackendConfig
from vio.backend.landmarks import Obs, Track, anchor_points

TD = 0.008        # s, exposure = keyframe time + td
RATES = np.array([[0.3, -1.2, 0.4], [-0.9, 0.8, 0.1], [1.1, 0.2, -0.6], [0.0, -1.5, 0.3]])  # rad/s
VEL_B = np.array([0.8, 0.1, 0.0])   # m/s, body frame


def _scene() -> tuple[Track, gtsam.Values, list[int]]:
    """Keyframe poses along a pan; each frame seen ``TD`` later, moving with its own
    body rate (changing from frame to frame, so the shift is no common rotation)."""
    p_w = np.array([0.4, -0.2, 3.0])
    frames = [0, 1, 2, 3]
    tr, vals = Track(7), gtsam.Values()
    for f in frames:
        T = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.0, -0.15, 0.05]) * f), np.array([0.1 * f, 0.0, 0.0]))
        T_exp = T.compose(gtsam.Pose3(gtsam.Rot3.Expmap(RATES[f] * TD), VEL_B * TD))
        pc, pk = T_exp.transformTo(p_w), T.transformTo(p_w)
        vel = graph.image_velocity(pk[:2] / pk[2], pk[2], RATES[f], VEL_B)
        tr.obs[f] = Obs(pc[:2] / pc[2], vel, float("nan"))
        vals.insert(graph.X(f), T)
    pa = vals.atPose3(graph.X(0)).transformTo(p_w)
    tr.key, tr.anchor = graph.L(0), 0
    vals.insert(tr.key, np.array([1.0 / pa[2]]))
    vals.insert(graph.EXTRINSIC, gtsam.Pose3())
    vals.insert(graph.TD, np.array([TD]))
    return tr, vals, frames


def test_reprojection_errors_apply_the_factor_shift():
    tr, vals, frames = _scene()
    raw = graph.reprojection_errors(tr, frames, vals) * 458.0
    assert raw.max() > 2.0                                   # td * vel seen as error
    graph.build_landmark_factor(tr, frames, BackendConfig(), 1.0 / 458.0, 0.0,
                                np.array([tr.obs[f].velocity for f in frames]))
    assert set(tr.td_shift) == set(frames)
    shifted = graph.reprojection_errors(tr, frames, vals) * 458.0
    assert shifted.max() < 0.1                               # px: first-order shift, small residue
    # at td = 0 the shift is the factor's too: the raw errors come back
    vals.update(graph.TD, np.array([0.0]))
    np.testing.assert_allclose(graph.reprojection_errors(tr, frames, vals) * 458.0, raw, rtol=1e-9)


def test_world_points_lie_where_the_factors_place_them():
    """``anchor_points`` (the window's world points: the IMU check, the bridged windows'
    PnP, the viewer) takes the anchor ray the factor takes, moved to the keyframe's time."""
    tr, vals, frames = _scene()
    graph.build_landmark_factor(tr, frames, BackendConfig(), 1.0 / 458.0, 0.0,
                                np.array([tr.obs[f].velocity for f in frames]))
    cams = graph.anchor_cameras(vals, {0})
    lam = np.array([vals.atVector(tr.key)[0]])
    p_w = np.array([0.4, -0.2, 3.0])
    shifted = anchor_points([tr], lam, cams, graph.td_value(vals))[0]
    raw = cams[0].transformFrom(np.array([*tr.obs[0].uv, 1.0]) / lam[0])   # on the unshifted ray
    assert np.linalg.norm(shifted - p_w) < 2e-4            # m: the first-order shift's residue
    assert np.linalg.norm(raw - p_w) > 10 * np.linalg.norm(shifted - p_w)
    # the outlier check re-projects that very point into the other frames: no error left
    T = vals.atPose3(graph.X(2))
    q = T.transformTo(shifted)
    np.testing.assert_allclose(q[:2] / q[2], tr.shifted_uv(2, TD), atol=0.1 / 458.0)
