"""The backend's Numba kernels loaded (or compiled) before the first keyframe needs them."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.landmark import landmark_anchor_jacobian, landmark_residual, make_track
from factors.bearing_model import tangent_basis
from factors.projection import anchor_jacobian_batch, project_batch, transfer_point
from factors.robust import RobustKernel, reweight_blocks
from factors.track_kernel import whitening
from vio.backend.graph import image_velocity
from vio.backend.td_velocity import points_velocities, predicted_velocities

_COMPILED = False


def compile_kernels() -> None:
    """Load (or compile) the factors' Numba kernels now, once per process, with the
    argument types the backend uses: their first call otherwise stalls the first
    keyframe after initialization by ~0.3-0.9 s (loading from Numba's disk cache)."""
    global _COMPILED
    if _COMPILED:
        return
    _COMPILED = True
    T, uv, B = np.eye(4), np.zeros((1, 2)), tangent_basis(np.zeros((1, 2)))
    p = project_batch(T, T[None], T, 1.0, np.zeros(2), uv, "pinhole", B, np.zeros(2), uv)
    anchor_jacobian_batch(T, T[None], T, 1.0, np.zeros(2), uv, "pinhole", B)
    reweight_blocks(p.r, p.J, 1.0, RobustKernel("huber", 3.0))
    lm = make_track(0, np.zeros(2), [1], uv)
    args = [np.ones(1), gtsam.Pose3(), gtsam.Pose3(), gtsam.Pose3(), np.zeros(1)]
    for use_td in (False, True):   # factors.track_kernel, with and without whitening
        W = whitening(landmark_anchor_jacobian(args, lm, "pinhole", use_td))
        for w in (None, W):
            landmark_residual(args[:4] + args[4:] * use_td, lm, "pinhole", 1.0,
                              RobustKernel("huber", 3.0), use_td, whiten=w)
    image_velocity(uv, np.ones(1), np.zeros((1, 3)), np.zeros((1, 3)))
    z2, z3 = np.zeros((1, 2)), np.zeros((1, 3))
    predicted_velocities(np.zeros(1, np.int64), z2, z2, np.ones(1, np.bool_), z2, z2, T[None, :3, :3].copy(),
                         z3, z3, z3, 1.0, np.eye(3), np.zeros(3), 0.1, 5.0, z2.copy(), z2.copy())
    points_velocities(np.array([0, 1]), np.zeros(1, np.int64), T[None, :3, :3].copy(), z3, z3, z3, z3.copy(), z2.copy(),
                      0.1, 5.0, 20.0, z2.copy())
    transfer_point(T, T, T, 1.0, np.zeros(2))   # the depth-transfer factor of a re-anchoring
