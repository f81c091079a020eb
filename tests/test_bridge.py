"""The IMU-gap bridge's pieces: the bridged keyframe located by RANSAC PnP on the window's
points (``vio.backend.bridge``) and the motion prior's noise (``factors.motion_prior``);
the end-to-end gap runs are in ``tests/test_faults.py``."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.motion_prior import motion_prior_covariance, motion_prior_factor
from vio.backend.bridge import locate
from vio.io.types import FeatureFrame

X, V = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V


def _frame(T_w_c: gtsam.Pose3, p_w: np.ndarray, noise: float, rng) -> FeatureFrame:
    q = np.array([T_w_c.transformTo(p) for p in p_w])
    uv = q[:, :2] / q[:, 2:3] + rng.normal(0, noise, (len(p_w), 2))
    n = len(p_w)
    return FeatureFrame(0, np.arange(n, dtype=np.int64), uv, np.zeros((n, 2)), np.full(n, np.nan))


def _scene(rng, n: int, noise: float) -> tuple[gtsam.Pose3, gtsam.Pose3, np.ndarray, FeatureFrame]:
    """(T_b_c, T_w_b, ``n`` world points 2-6 m in front of the camera, their observations
    with ``noise`` (normalized) from T_w_b)."""
    T_b_c = gtsam.Pose3(gtsam.Rot3.Ypr(-1.57, 0.0, -1.57), np.array([0.05, -0.02, 0.01]))
    T_w_b = gtsam.Pose3(gtsam.Rot3.Ypr(0.4, 0.1, -0.05), np.array([1.0, 2.0, 1.5]))
    T_w_c = T_w_b.compose(T_b_c)
    p_w = np.array([T_w_c.transformFrom(np.r_[rng.uniform(-1, 1, 2), 1.0] * rng.uniform(2, 6)) for _ in range(n)])
    return T_b_c, T_w_b, p_w, _frame(T_w_c, p_w, noise, rng)


def test_pnp_locates_the_bridged_keyframe_and_leaves_out_jumped_tracks():
    rng = np.random.default_rng(3)
    T_b_c, T_w_b, p_w, fr = _scene(rng, 13, 0.5 / 460)
    uv = fr.uv.copy()
    uv[[2, 7, 11]] += np.array([0.06, -0.04])            # three tracks jump by ~30 px
    fr = FeatureFrame(0, fr.ids, uv, fr.velocity, fr.row)
    pred = T_w_b.compose(gtsam.Pose3(gtsam.Rot3.Rz(0.05), np.array([0.1, -0.08, 0.05])))   # prior 14 cm off
    T, kept = locate(np.arange(13), p_w, fr, pred, T_b_c, 6.0 / 460, 6)
    assert T is not None
    assert np.linalg.norm(T.translation() - T_w_b.translation()) < 0.01
    assert np.linalg.norm(gtsam.Rot3.Logmap(T.rotation().between(T_w_b.rotation()))) < 0.005
    assert sorted(set(range(13)) - set(kept.ids.tolist())) == [2, 7, 11]
    assert kept.uv.shape == (10, 2) and kept.row.shape == (10,)


def test_pnp_without_enough_landmarks_keeps_the_prediction_and_every_observation():
    rng = np.random.default_rng(4)
    T_w_c = gtsam.Pose3(gtsam.Rot3(), np.zeros(3))
    p_w = np.array([[0.1, 0.2, 3.0], [-0.3, 0.1, 4.0], [0.2, -0.2, 2.5], [0.0, 0.3, 5.0]])
    fr = _frame(T_w_c, p_w, 0.0, rng)
    T, kept = locate(np.arange(4), p_w, fr, gtsam.Pose3(), gtsam.Pose3(), 0.01, 6)
    assert T is None and kept is fr


def test_motion_prior_is_decoupled_from_attitude_and_grows_with_the_interval():
    """Unlike preintegrated still readings, tilting the start attitude moves nothing but the
    rotation residual; position sigma q dt^1.5 / sqrt(3), velocity q sqrt(dt)."""
    C = motion_prior_covariance(0.5, 1.0, 0.5)
    np.testing.assert_allclose(np.sqrt(np.diag(C))[[0, 3, 6]],
                               [0.5 * np.sqrt(0.5), 0.5 ** 1.5 / np.sqrt(3), np.sqrt(0.5)])
    assert np.all(np.diag(motion_prior_covariance(3.0, 1.0, 0.5)) > np.diag(C))
    f = motion_prior_factor([X(0), V(0), X(1), V(1)], 0.5, 1.0, 0.5)
    vals = gtsam.Values()
    v0 = np.array([0.5, -0.2, 0.1])
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([1.0, 2.0, 3.0])))
    vals.insert(V(0), v0)
    vals.insert(X(1), gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([1.0, 2.0, 3.0]) + 0.5 * v0))
    vals.insert(V(1), v0)
    assert f.error(vals) < 1e-18
    tilted = gtsam.Values(vals)
    tilted.update(X(1), gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.1, 0.1), np.array([1.0, 2.0, 3.0]) + 0.5 * v0))
    # 0.1 rad of tilt costs (0.1 / (0.5 sqrt(0.5)))^2 / 2 = 0.04, independent of position
    assert abs(f.error(tilted) - 0.5 * (0.1 / (0.5 * np.sqrt(0.5))) ** 2) < 2e-3


def test_pnp_failing_leaves_out_the_observations_far_from_the_prediction():
    """Too few landmarks for PnP: the prediction gates the observations instead
    (``BridgeConfig.pred_gate_px``); without the gate every observation stays."""
    rng = np.random.default_rng(5)
    T_w_c = gtsam.Pose3(gtsam.Rot3(), np.zeros(3))
    p_w = np.array([[0.1, 0.2, 3.0], [-0.3, 0.1, 4.0], [0.2, -0.2, 2.5], [0.0, 0.3, 5.0]])
    fr = _frame(T_w_c, p_w, 0.0, rng)
    uv = fr.uv.copy()
    uv[1] += 0.05                                   # one track jumps by ~23 px at fx 460
    fr = FeatureFrame(0, fr.ids, uv, fr.velocity, fr.row)
    T, kept = locate(np.arange(4), p_w, fr, gtsam.Pose3(), gtsam.Pose3(), 6 / 460, 6, 10 / 460)
    assert T is None and kept.ids.tolist() == [0, 2, 3]
    assert locate(np.arange(4), p_w, fr, gtsam.Pose3(), gtsam.Pose3(), 6 / 460, 6)[1] is fr


def test_gyro_rotation_factor_holds_the_relative_attitude_and_frees_the_translation():
    from vio.backend.bridge import gyro_rotation_factor
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(9.81)
    params.setGyroscopeCovariance(1e-6 * np.eye(3))
    params.setAccelerometerCovariance(1e-4 * np.eye(3))
    params.setIntegrationCovariance(1e-8 * np.eye(3))
    params.setBiasAccCovariance(1e-8 * np.eye(3))
    params.setBiasOmegaCovariance(1e-10 * np.eye(3))
    pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
    for _ in range(40):
        pim.integrateMeasurement(np.array([0.0, 0.0, 9.81]), np.array([0.3, -0.2, 0.5]), 0.005)
    f = gyro_rotation_factor(0, 1, pim, 0.002)
    T0 = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, 0.1, -0.2), np.array([1.0, 2.0, 3.0]))
    vals = gtsam.Values()
    vals.insert(X(0), T0)
    vals.insert(X(1), gtsam.Pose3(T0.rotation().compose(pim.deltaRij()), np.array([5.0, -4.0, 0.3])))
    assert f.error(vals) < 1e-4                      # any translation (sigma 1 km)
    vals.update(X(1), gtsam.Pose3(T0.rotation().compose(pim.deltaRij()).compose(gtsam.Rot3.Rx(0.01)),
                                  np.zeros(3)))
    assert f.error(vals) > 10.0                      # 0.01 rad against sigmas below 1e-3 rad


def _contradiction_case(pred_offset: gtsam.Pose3, n_jumped: int = 0):
    """A stand-in ``Estimator`` with 20 window landmarks, the new keyframe's observations of
    them from the true pose (``n_jumped`` tracks moved by 25-50 px), and the IMU prediction
    ``pred_offset`` away from the truth."""
    from types import SimpleNamespace
    from vio.backend.config import BackendConfig
    rng = np.random.default_rng(7)
    T_b_c, T_w_b, p_w, fr = _scene(rng, 20, 0.3 / 460)
    uv = fr.uv.copy()
    uv[:n_jumped] += rng.choice([-1.0, 1.0], (n_jumped, 2)) * rng.uniform(0.04, 0.08, (n_jumped, 2))
    fr = FeatureFrame(0, fr.ids, uv, fr.velocity, fr.row)
    lms = (np.arange(20), p_w)
    est = SimpleNamespace(cfg=BackendConfig(), cam=SimpleNamespace(intrinsics=np.array([460.0, 460.0, 376.0, 240.0])),
                          check_points=lambda: lms, frame_points=lambda: lms, extrinsic=lambda: T_b_c, k=4,
                          contradicted_k=None, contradicted_t=None, check_fired_t=None, imu_contradictions=0,
                          frame_contradictions=0)
    pred = gtsam.NavState(T_w_b.compose(pred_offset), np.array([0.7, 0.0, 0.0]))
    return est, fr, pred, T_w_b


def test_vision_contradicting_the_imu_prediction_gives_the_pnp_pose():
    """``bridge.imu_contradicted``: a prediction 12 cm off re-projects none of the
    observations within ``outlier_px`` while PnP explains them all: the PnP pose is returned
    and the interval counted. A prediction within a few pixels, one 1 cm off (below
    ``imu_check_min_m``) with 1.5 deg of attitude error (as right after an
    initialization), one 5 cm and 1.7 deg off (beyond ``imu_check_max_deg``: a timing
    error, td or rolling shutter, not an accelerometer's), and observations PnP explains
    only 60 % of (8 of 20 jumped) leave the IMU factor in."""
    from vio.backend.bridge import imu_contradicted
    est, fr, pred, T_w_b = _contradiction_case(gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])))
    T = imu_contradicted(est, fr, pred)
    assert T is not None and np.linalg.norm(T.translation() - T_w_b.translation()) < 0.01
    assert est.imu_contradictions == 1 and (est.contradicted_k, est.contradicted_t) == (5, None)
    for off, jumped in [(gtsam.Pose3(gtsam.Rot3.Rz(0.002), np.array([0.004, 0.0, 0.0])), 0),
                        (gtsam.Pose3(gtsam.Rot3.Rz(0.026), np.array([0.01, 0.0, 0.0])), 0),
                        (gtsam.Pose3(gtsam.Rot3.Rz(0.03), np.array([0.05, 0.0, 0.0])), 0),
                        (gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])), 8)]:
        est, fr, pred, _ = _contradiction_case(off, jumped)
        assert imu_contradicted(est, fr, pred) is None and est.imu_contradictions == 0
    est, fr, pred, _ = _contradiction_case(gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])))
    est.cfg = est.cfg.__class__(bridge=est.cfg.bridge.__class__(imu_check=False))
    assert imu_contradicted(est, fr, pred) is None


def test_landmarks_that_entered_without_parallax_do_not_contradict_the_imu():
    """Issue 20's random-pick MH_03 excerpt at td 25 ms: in a hover, tracks waited out
    ``max_wait_keyframes`` and entered at triangulations over noise-sized angles, 0.15-0.5 m
    where the walls were 4-12 m away; 2 s later the camera moved, the IMU prediction
    re-projected 8 % of the observations and PnP put 19 of 24 on those points at the hover
    pose, 5 cm from a right prediction: the interval's IMU was bridged and the run went
    0.036 -> 0.064 m. Here 32 of 40 landmarks sit at a twentieth of their depth on their
    rays from a pose 4 cm back: counted, they contradict a right prediction; as
    ``weak_ids`` (``Track.weak``) ``Estimator.check_points`` leaves them out and the 8
    others agree with it."""
    from types import SimpleNamespace
    from vio.backend.bridge import imu_contradicted
    from vio.backend.estimator import Estimator
    est, fr, pred, T_w_b = _contradiction_case(gtsam.Pose3())
    rng = np.random.default_rng(3)
    T_b_c, _, p_w, _ = _scene(rng, 40, 0.0)
    hover = T_w_b.compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.04, 0.0]))).compose(T_b_c)
    fr = _frame(T_w_b.compose(T_b_c), p_w, 0.3 / 460, rng)
    near = np.array([hover.transformFrom(hover.transformTo(p) / 20.0) for p in p_w[8:]])
    lms = (np.arange(40), np.vstack([p_w[:8], near]))
    est.check_points = est.frame_points = lambda: lms
    est.extrinsic = lambda: T_b_c
    T = imu_contradicted(est, fr, pred)
    assert T is not None and np.linalg.norm(T.translation() - T_w_b.translation()) > 0.03
    est.imu_contradictions, est.check_fired_t = 0, None
    est.landmarks_w, est.lm = (lambda: lms), SimpleNamespace(weak_ids=lambda: np.arange(8, 40))
    est.check_points = lambda: Estimator.check_points(est)
    assert imu_contradicted(est, fr, pred) is None and est.imu_contradictions == 0


def test_right_after_a_contradicted_interval_a_milder_disagreement_counts():
    """A prediction 7 cm off re-projects 40 % of the observations: on its own not a
    contradiction (``imu_check_max_frac``), but within ``imu_check_hold_s`` after an
    interval that was one (the fault goes on; the prediction now starts from the PnP pose)
    the limit is ``imu_check_hold_frac``. On real MH_01 stereo with 6 m/s^2 for 1 s from
    frame 180 the intervals between the contradicted ones re-projected 24-35 %."""
    from vio.backend.bridge import imu_contradicted
    off = gtsam.Pose3(gtsam.Rot3(), np.array([0.07, 0.0, 0.01]))
    for fired, expected in [(None, False), (-0.2e9, True), (-0.4e9, False)]:
        est, fr, pred, T_w_b = _contradiction_case(off)
        est.check_fired_t = fired
        T = imu_contradicted(est, fr, pred)
        assert (T is not None) == expected, fired
        if expected:
            assert np.linalg.norm(T.translation() - T_w_b.translation()) < 0.01 and est.check_fired_t == fr.t_ns


def test_a_frame_vision_contradicts_is_output_at_its_pnp_pose():
    """``bridge.frame_state``: between keyframes, a prediction 12 cm off (the IMU
    propagated through an accelerometer fault) gives way to the PnP pose with the
    prediction's velocity, counted in ``frame_contradictions`` and leaving the keyframe
    check's state alone; one within a few pixels, one PnP explains only 60 % of, and any
    with the check off are returned as they are."""
    from vio.backend.bridge import frame_state
    est, fr, pred, T_w_b = _contradiction_case(gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])))
    nav = frame_state(est, fr, pred)
    assert np.linalg.norm(nav.pose().translation() - T_w_b.translation()) < 0.01
    assert np.allclose(nav.velocity(), pred.velocity())
    assert est.frame_contradictions == 1 and est.imu_contradictions == 0 and est.check_fired_t is None
    for off, jumped in [(gtsam.Pose3(gtsam.Rot3.Rz(0.002), np.array([0.004, 0.0, 0.0])), 0),
                        (gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])), 8)]:
        est, fr, pred, _ = _contradiction_case(off, jumped)
        assert frame_state(est, fr, pred) is pred and est.frame_contradictions == 0
    est, fr, pred, _ = _contradiction_case(gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])))
    est.cfg = est.cfg.__class__(bridge=est.cfg.bridge.__class__(imu_check=False))
    assert frame_state(est, fr, pred) is pred and frame_state(est, None, pred) is pred


def test_the_live_frame_path_checks_its_prediction_on_the_reported_landmarks():
    """``vio.live.checked``: with ``--live`` each frame's pose is the IMU prediction from the
    newest state the backend worker reported; that state carries its window landmarks, so
    a prediction 12 cm off is output at the PnP pose there too (counted); a good one, and
    a state without landmarks, leave the prediction as it is."""
    from types import SimpleNamespace
    from vio.live import KeyState, checked
    from vio.pipeline import PipelineConfig
    est, fr, pred, T_w_b = _contradiction_case(gtsam.Pose3(gtsam.Rot3(), np.array([0.12, 0.0, 0.03])))
    ids, pts = est.check_points()
    state = KeyState(0, T_w_b.matrix(), np.zeros(3), np.zeros(6), 0.0, est.extrinsic().matrix(), len(ids), 3, 0,
                     ids, pts)
    pipe = SimpleNamespace(state=state, cfg=PipelineConfig(), frame_contradictions=0,
                           cam=SimpleNamespace(intrinsics=(460.0, 460.0, 376.0, 240.0), line_time_s=0.0))
    pkt = SimpleNamespace(t_ns=fr.t_ns, stamp_ns=fr.t_ns, features=fr, imu=SimpleNamespace(gyro=np.zeros((1, 3))))
    nav = checked(pipe, pred, pkt)
    assert np.linalg.norm(nav.pose().translation() - T_w_b.translation()) < 0.01 and pipe.frame_contradictions == 1
    _, _, good, _ = _contradiction_case(gtsam.Pose3(gtsam.Rot3.Rz(0.002), np.array([0.004, 0.0, 0.0])))
    assert checked(pipe, good, pkt) is good and pipe.frame_contradictions == 1
    pipe.state = KeyState(0, T_w_b.matrix(), np.zeros(3), np.zeros(6), 0.0, est.extrinsic().matrix(), 0, 3, 0)
    assert checked(pipe, pred, pkt) is pred


def test_a_long_interval_widens_what_contradicts_the_imu():
    """Over a keyframe interval (up to ``imu_check_ref_s``) an alignment 3 cm from the IMU
    prediction contradicts it; over a 1.2-s camera gap the prediction's own error is that
    large (real MH_01: 27 mm from a right prediction), so the limit grows with the square
    of the interval; a 6 m/s^2 accelerometer offset over it (4.3 m) still contradicts."""
    from vio.backend.bridge import contradicts, long_interval
    from vio.backend.health import BridgeConfig
    bc = BridgeConfig()
    assert long_interval(bc, 0.0) == long_interval(bc, bc.imu_check_ref_s) == 1.0
    assert np.isclose(long_interval(bc, 2 * bc.imu_check_ref_s), 4.0)
    assert contradicts(bc, 0.031, 0.001, 0.2) and not contradicts(bc, 0.029, 0.001, 0.2)
    assert not contradicts(bc, 0.031, 0.001, 1.2) and not contradicts(bc, 0.15, 0.001, 1.2)
    assert contradicts(bc, 0.5 * 6.0 * 1.2 ** 2, 0.001, 1.2)
    assert not contradicts(bc, 0.5, np.radians(1.5), 1.2)      # an attitude error is a timing error
