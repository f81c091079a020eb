"""The re-initialization after a divergence (``vio.reinit``): the aligned state moved to
the restart's position and yaw; the end-to-end switch is checked by
``tests/test_faults.py::test_forced_divergence_restarts_softly_without_a_jump``."""

from __future__ import annotations

import gtsam
import numpy as np

from vio.backend.init import InitialState
from vio.reinit import moved_to


def test_aligned_state_takes_the_restarts_position_and_yaw_and_keeps_its_tilt_and_body_velocity():
    bias = gtsam.imuBias.ConstantBias(np.array([0.1, -0.05, 0.2]), np.array([0.01, 0.02, -0.01]))
    R = gtsam.Rot3.Ypr(0.0, 0.08, -0.05)                      # the alignment's yaw is arbitrary (0)
    state = InitialState(7, gtsam.Pose3(R, np.zeros(3)), np.array([0.4, 0.1, -0.05]), bias, "dynamic",
                         0.02, 0.1, 0.003)
    ref = gtsam.Pose3(gtsam.Rot3.Ypr(1.2, -0.3, 0.2), np.array([3.0, -1.0, 1.5]))
    out = moved_to(state, ref)
    np.testing.assert_allclose(out.T_w_b.translation(), ref.translation())
    assert abs(out.T_w_b.rotation().yaw() - 1.2) < 1e-9
    # roll and pitch: the gravity direction in the body is the alignment's
    g_b = lambda T: T.rotation().unrotate(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(g_b(out.T_w_b), g_b(state.T_w_b), atol=1e-12)
    # the velocity turns with the body: the same in the body frame
    np.testing.assert_allclose(out.T_w_b.rotation().unrotate(out.v_w), R.unrotate(state.v_w), atol=1e-12)
    assert (out.t_ns, out.method, out.rp_sigma, out.vel_sigma, out.td_s) == (7, "reinit", 0.02, 0.1, 0.003)
    assert out.bias.equals(bias, 0.0)
