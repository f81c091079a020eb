"""Tests of the direct (photometric) stack: the photometric factors (zero residual at the
truth, invalid rows, Huber, a GTSAM solve), point selection, epipolar inverse-depth search (synthetic and
real EuRoC stereo), the generic LM against scipy, and TrackFrame on a known motion."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.optimize import least_squares

from cases_photometric import (CASES, PlaneSampler, analytic_image, box_scene, random_pose,
                               render_planes)
from conftest import shared
from factors.image_ops import BilinearImage
from factors.photometric import (Pinhole, PhotometricParams, make_host_patch, stereo_eval,
                                 stereo_factor, temporal_eval, temporal_factor)
from vio.config import from_dict
from vio.direct import (DirectConfig, EpipolarConfig, LMConfig, SelectConfig, TrackConfig,
                        epipolar_search, levenberg_marquardt, make_reference, select_points,
                        track_frame)
from vio.direct.epipolar import undistort_pinhole
from vio.direct.select import gradient_threshold
from vio.errors import ConfigError

W, H = 640, 480
KS = Pinhole(450.0, 450.0, 319.5, 239.5)


# ------------------------------------------------------------------ photometric factor

# The analytic-vs-numeric Jacobian checks of tests/cases_photometric.py run in the
# shared suite tests/test_jacobians.py.


def _plane_scene(rng):
    """One fronto-parallel textured plane at 2 m in front of camera c0 (world = c0)."""
    return box_scene(rng, depth=2.0)[:1]


def test_photometric_residual_zero_at_truth():
    """Exact ray-cast images with affine brightness: r = 0 at the true state (<1e-9)."""
    rng = np.random.default_rng(3)
    planes = _plane_scene(rng)
    T_b_c = random_pose(rng, 0.5, 0.05)
    T_w_ci = gtsam.Pose3()
    T_w_cj = gtsam.Pose3(gtsam.Rot3.Expmap([0.01, -0.02, 0.015]), [0.08, -0.03, 0.05])
    ab_i, ab_j, ratio = np.array([0.2, 7.0]), np.array([-0.15, -4.0]), 1.3
    gain_i, gain_j = np.exp(ab_i[0]), ratio * np.exp(ab_j[0])
    host_img = PlaneSampler(planes, KS, T_w_ci, W, H, gain_i, ab_i[1])
    target = PlaneSampler(planes, KS, T_w_cj, W, H, gain_j, ab_j[1])
    uv = rng.uniform([100, 100], [540, 380], (20, 2))
    host = make_host_patch(host_img, uv, KS)
    rho = np.full(len(uv), 0.5)
    T_w_bi, T_w_bj = T_w_ci.compose(T_b_c.inverse()), T_w_cj.compose(T_b_c.inverse())
    ev = temporal_eval(T_w_bi, T_w_bj, rho, ab_i, ab_j, host, target, KS, T_b_c, ratio)
    assert ev.valid.mean() > 0.9
    assert np.abs(ev.r[ev.valid]).max() < 1e-9
    ev_off = temporal_eval(T_w_bi, T_w_bj, rho * 1.05, ab_i, ab_j, host, target, KS, T_b_c, ratio)
    assert np.sqrt(np.mean(ev_off.r[ev_off.valid] ** 2)) > 1.0      # and not zero elsewhere
    # static stereo: right camera 11 cm to the right, affine relative to the left
    T_r_l = gtsam.Pose3(gtsam.Rot3.Expmap([0.003, 0.002, -0.001]), [-0.11, 0.001, 0.0])
    ab_r = np.array([0.1, 5.0])
    right = PlaneSampler(planes, KS, T_w_ci.compose(T_r_l.inverse()), W, H, gain_i * np.exp(ab_r[0]),
                         ab_r[1])
    host_l = make_host_patch(PlaneSampler(planes, KS, T_w_ci, W, H, gain_i, 0.0), uv, KS)
    ev_s = stereo_eval(rho, ab_r, host_l, right, KS, T_r_l)
    assert ev_s.valid.mean() > 0.9 and np.abs(ev_s.r[ev_s.valid]).max() < 1e-9


def test_analytic_image_render_is_the_pointwise_field():
    """``AnalyticImage.render`` (separable, two matrix products) equals the texture sampled
    pixel by pixel, to rounding."""
    img = analytic_image(np.random.default_rng(11))
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    pointwise = img.texture(uu, vv)[0]
    assert img.render().shape == (H, W)
    assert np.abs(img.render() - pointwise).max() < 1e-9 * np.abs(pointwise).max()
    assert pointwise.std() > 5.0           # a textured image, not a constant


def test_photometric_out_of_image_rows_are_zero_and_huber_reweights():
    rng = np.random.default_rng(4)
    case = next(c for c in CASES if c.name == "photometric_temporal_near_border")
    factor, values, residual, _ = case.build(rng)
    r, jacs = residual(values)
    dead = r == 0
    assert 0 < dead.sum() < len(r)
    assert all(np.all(J[dead] == 0) for J in jacs)
    # far outside: every row zero, no exception, no health failure
    v = gtsam.Values(values)
    v.update(gtsam.symbol_shorthand.X(1), values.atPose3(gtsam.symbol_shorthand.X(1)).compose(
        gtsam.Pose3(gtsam.Rot3.Expmap([0, 2.5, 0]), np.zeros(3))))
    assert factor.error(v) == 0.0
    # Huber: weighted residual is capped at sqrt(k |e|) per row (IRLS weight min(1, k/|e|))
    host = make_host_patch(BilinearImage(rng.uniform(0, 255, (H, W))), np.array([[300.0, 200.0]]), KS)
    target = BilinearImage(rng.uniform(0, 255, (H, W)))
    keys = [gtsam.symbol_shorthand.X(0), gtsam.symbol_shorthand.X(1), gtsam.symbol_shorthand.D(0),
            gtsam.symbol_shorthand.A(0), gtsam.symbol_shorthand.A(1)]
    vals = gtsam.Values()
    vals.insert(keys[0], gtsam.Pose3())
    vals.insert(keys[1], gtsam.Pose3(gtsam.Rot3(), [0.05, 0, 0]))
    vals.insert(keys[2], np.array([0.5]))
    vals.insert(keys[3], np.zeros(2))
    vals.insert(keys[4], np.zeros(2))
    p_ls, p_h = PhotometricParams(huber_k=None, grad_c=1e9), PhotometricParams(huber_k=1.345, grad_c=1e9)
    e_ls = np.abs(temporal_factor(keys, host, target, KS, gtsam.Pose3(), p_ls).whitenedError(vals))
    e_h = np.abs(temporal_factor(keys, host, target, KS, gtsam.Pose3(), p_h).whitenedError(vals))
    np.testing.assert_allclose(e_h, np.where(e_ls > 1.345, np.sqrt(1.345 * e_ls), e_ls), rtol=1e-9)


def test_photometric_factors_in_gtsam_graph():
    """Stereo + temporal factors in a GTSAM LM solve: inverse depths from 5 % off and the
    target frame's affine from zero converge to the truth (exact ray-cast images)."""
    from gtsam.symbol_shorthand import A, D, X
    rng = np.random.default_rng(5)
    planes = _plane_scene(rng)
    T_b_c = random_pose(rng, 0.3, 0.05)
    T_w_ci, T_w_cj = gtsam.Pose3(), gtsam.Pose3(gtsam.Rot3.Expmap([0.01, 0.02, 0.0]), [0.1, 0.02, 0.03])
    T_r_l = gtsam.Pose3(gtsam.Rot3(), [-0.11, 0.0, 0.0])
    ab_j = np.array([0.1, 5.0])
    left = PlaneSampler(planes, KS, T_w_ci, W, H)
    right = PlaneSampler(planes, KS, T_r_l.inverse(), W, H)
    target = PlaneSampler(planes, KS, T_w_cj, W, H, np.exp(ab_j[0]), ab_j[1])
    uv = rng.uniform([120, 100], [520, 380], (8, 2))
    graph, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    T_w_bi, T_w_bj = T_w_ci.compose(T_b_c.inverse()), T_w_cj.compose(T_b_c.inverse())
    for k, T in ((X(0), T_w_bi), (X(1), T_w_bj)):
        graph.add(gtsam.PriorFactorPose3(k, T, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        init.insert(k, T)
    graph.add(gtsam.PriorFactorVector(A(0), np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, 1e-6)))
    init.insert(A(0), np.zeros(2))
    init.insert(A(1), np.zeros(2))
    init.insert(A(2), np.zeros(2))                            # right camera vs left
    params = PhotometricParams(sigma_I=2.0)
    for n in range(len(uv)):
        host = make_host_patch(left, uv[n:n + 1], KS)
        graph.add(temporal_factor([X(0), X(1), D(n), A(0), A(1)], host, target, KS, T_b_c, params))
        graph.add(stereo_factor([D(n), A(2)], host, right, KS, T_r_l, params))
        init.insert(D(n), np.array([0.5 * (1.05 if n % 2 else 0.95)]))
    result = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    rho = np.array([result.atVector(D(n))[0] for n in range(len(uv))])
    np.testing.assert_allclose(rho, 0.5, rtol=1e-4)
    assert np.all(np.abs(result.atVector(A(1)) - ab_j) < [1e-4, 1e-2])
    assert np.all(np.abs(result.atVector(A(2))) < [1e-4, 1e-2])
    assert graph.error(result) < 1e-9 * graph.error(init)


# ------------------------------------------------------------------ synthetic scenes

@pytest.fixture(scope="module")
def stereo_scene():
    rng = np.random.default_rng(1)
    planes = box_scene(rng)
    T_c1_c0 = gtsam.Pose3(gtsam.Rot3.Expmap([0.002, -0.003, 0.001]), [-0.11, 0.001, 0.0005])
    left, idepth = render_planes(planes, KS, gtsam.Pose3(), W, H)
    right, _ = render_planes(planes, KS, T_c1_c0.inverse(), W, H)
    noise = 1.0
    return (left + rng.normal(0, noise, left.shape), right + rng.normal(0, noise, left.shape),
            idepth, T_c1_c0)


def test_select_points_spread_and_strength(stereo_scene):
    left = stereo_scene[0]
    cfg = SelectConfig(n_points=400)
    sel = select_points(left, cfg)
    assert 0.85 * 400 <= len(sel) <= 400
    u, v = sel.uv[:, 0], sel.uv[:, 1]
    assert u.min() >= cfg.border and u.max() < W - cfg.border
    assert v.min() >= cfg.border and v.max() < H - cfg.border
    occupied = np.unique((v // (H / 4)).astype(int) * 4 + (u // (W / 4)).astype(int))
    assert len(occupied) >= 15                                # spread over a 4x4 grid
    gx, gy = np.gradient(left, axis=1), np.gradient(left, axis=0)
    thr = gradient_threshold(np.hypot(gx, gy), cfg.block, cfg.grad_offset)
    ui, vi = u.astype(int), v.astype(int)
    assert np.all(sel.grad > thr[vi, ui] * cfg.level_factor ** (cfg.levels - 1) - 1e-9)
    assert np.median(sel.grad) > 2 * np.median(np.hypot(gx, gy))


def test_epipolar_synthetic_within_sigma(stereo_scene):
    left, right, idepth, T_c1_c0 = stereo_scene
    sel = select_points(left, SelectConfig(n_points=400))
    res = epipolar_search(left, right, sel.uv, KS, KS, T_c1_c0, EpipolarConfig())
    true = idepth[sel.uv[:, 1].astype(int), sel.uv[:, 0].astype(int)]
    ok = res.ok
    err, sig = np.abs(res.idepth - true)[ok], np.sqrt(res.variance[ok])
    assert ok.mean() >= 0.8
    assert np.mean(err <= sig) >= 0.95, np.mean(err <= sig)
    assert np.mean(err <= 3 * sig) >= 0.98
    assert np.median(err / true[ok]) < 0.01                  # sub-pixel: 4 cm at 2.5 m is 1 px
    assert np.median(sig / true[ok]) < 0.08                  # sigma informative, not inflated


def _euroc_pair(index: int):
    from vio.io.calib import read_camera_yaml
    from vio.io.euroc import read_image
    root = shared("euroc_V1_01_static_stereo", "mav0")
    c0 = read_camera_yaml(root / "cam0" / "sensor.yaml", "cam0")
    c1 = read_camera_yaml(root / "cam1" / "sensor.yaml", "cam1")
    f0 = sorted((root / "cam0" / "data").glob("*.png"))[index]
    left = undistort_pinhole(read_image(f0), c0.K, c0.distortion, c0.distortion_model)
    right = undistort_pinhole(read_image(root / "cam1" / "data" / f0.name), c1.K, c1.distortion,
                              c1.distortion_model)
    return left, right, Pinhole.from_K(c0.K), Pinhole.from_K(c1.K), c1.T_b_c.between(c0.T_b_c)


def test_epipolar_euroc_static_stereo_plausible():
    left, right, K0, K1, T_c1_c0 = _euroc_pair(40)
    sel = select_points(left, SelectConfig(n_points=500))
    cfg = EpipolarConfig(idepth_min=0.05, idepth_max=2.5)
    res = epipolar_search(left, right, sel.uv, K0, K1, T_c1_c0, cfg)
    depth = 1.0 / res.idepth[res.ok]
    assert res.ok.mean() >= 0.4, res.ok.mean()
    assert np.mean((depth > 0.5) & (depth < 10.0)) >= 0.95
    # left-right round trip: searching back from the match lands on the start pixel
    # within the reported match error (sigma_px: DSO's gradient/epipolar-angle term)
    back = epipolar_search(right, left, res.uv_match[res.ok], K1, K0, T_c1_c0.inverse(), cfg)
    dist = np.linalg.norm(back.uv_match - sel.uv[res.ok], axis=1)
    sig = res.sigma_px[res.ok]
    assert np.mean(dist <= np.maximum(1.0, 3 * sig)) >= 0.85
    sharp = sig <= np.median(sig)
    assert np.mean(dist[sharp] <= 1.0) >= 0.75, np.mean(dist[sharp] <= 1.0)


# ------------------------------------------------------------------ LM and TrackFrame

def _curve(rng, outliers: int = 0):
    t = np.linspace(0, 4, 60)
    x_true = np.array([2.5, 1.3, 0.7, 3.0])
    y = x_true[0] * np.exp(-x_true[1] * t) + x_true[2] * np.sin(x_true[3] * t) + rng.normal(0, 0.02, t.size)
    y[rng.choice(t.size, outliers, replace=False)] += 2.0

    def res(x):
        return x[0] * np.exp(-x[1] * t) + x[2] * np.sin(x[3] * t) - y

    def jac(x):
        e = np.exp(-x[1] * t)
        return np.stack([e, -x[0] * t * e, np.sin(x[3] * t), x[2] * t * np.cos(x[3] * t)], 1)
    return res, jac, np.array([1.0, 0.5, 0.3, 2.8])


@pytest.mark.parametrize("huber", [None, 0.05])
def test_lm_matches_scipy_on_curve_fit(huber):
    res, jac, x0 = _curve(np.random.default_rng(0), outliers=6 if huber else 0)
    cfg = LMConfig(huber_k=huber, eps1=1e-12, eps2=1e-12, eps4=1e-14)
    out = levenberg_marquardt(lambda x: (res(x), jac(x)), x0, cfg)
    ref = least_squares(res, x0, jac=jac, method="lm" if huber is None else "trf",
                        loss="linear" if huber is None else "huber", f_scale=huber or 1.0,
                        xtol=1e-14, ftol=1e-14, gtol=1e-14)
    assert out.converged, out.stop_reason
    np.testing.assert_allclose(out.x, ref.x, rtol=1e-6, atol=1e-8)
    assert abs(out.cost - ref.cost) <= 1e-9 * max(1.0, ref.cost)


def test_lm_rosenbrock_and_stop_reasons():
    fun = lambda x: (np.array([10 * (x[1] - x[0] ** 2), 1 - x[0]]),  # noqa: E731
                     np.array([[-20 * x[0], 10.0], [-1.0, 0.0]]))
    out = levenberg_marquardt(fun, np.array([-1.2, 1.0]), LMConfig(eps3=1e-10))
    np.testing.assert_allclose(out.x, [1.0, 1.0], atol=1e-6)
    assert out.converged and out.iterations < 100
    capped = levenberg_marquardt(fun, np.array([-1.2, 1.0]), LMConfig(max_iters=2))
    assert capped.stop_reason == "max_iters" and capped.iterations == 2


@pytest.fixture(scope="module")
def tracking_scene():
    rng = np.random.default_rng(2)
    planes = box_scene(rng, scales_m=(0.025, 0.08))
    T_true = gtsam.Pose3(gtsam.Rot3.Expmap(np.deg2rad([0.6, -0.7, 0.3])), [0.012, -0.01, 0.012])
    a_true, b_true = 0.1, 5.0
    kf, idepth = render_planes(planes, KS, gtsam.Pose3(), W, H)
    new, _ = render_planes(planes, KS, T_true, W, H, gain=np.exp(a_true), bias=b_true)
    kf = kf + rng.normal(0, 1.0, kf.shape)
    new = new + rng.normal(0, 1.0, kf.shape)
    return kf, new, idepth, T_true, a_true, b_true


def test_trackframe_recovers_synthetic_motion(tracking_scene):
    kf, new, idepth, T_true, a_true, b_true = tracking_scene
    angle = np.rad2deg(np.linalg.norm(gtsam.Rot3.Logmap(T_true.rotation())))
    assert 0.9 < angle < 1.1 and 0.015 < np.linalg.norm(T_true.translation()) < 0.025
    sel = select_points(kf, SelectConfig(n_points=500))
    rho = idepth[sel.uv[:, 1].astype(int), sel.uv[:, 0].astype(int)]
    cfg = TrackConfig()
    ref = make_reference(kf, sel.uv, rho, KS, idepth_var=np.full(len(rho), 1e-4), config=cfg)
    out = track_frame(ref, new, config=cfg)
    err = T_true.between(out.T_kf_new)
    assert out.ok and len(out.levels) == 4
    assert np.rad2deg(np.linalg.norm(gtsam.Rot3.Logmap(err.rotation()))) < 0.03
    assert np.linalg.norm(err.translation()) < 1.5e-3
    assert abs(out.a - a_true) < 0.02 and abs(out.b - b_true) < 2.5
    start = track_frame(ref, new, config=TrackConfig(iters=(0, 0, 0, 0)))   # no iterations
    assert out.rmse < 0.25 * start.rmse and out.rmse < 6.0
    assert out.levels[-1].level == 0 and out.levels[0].cost < out.levels[0].initial_cost


def test_trackframe_flags_lost_frame(tracking_scene):
    kf, _, idepth, *_ = tracking_scene
    sel = select_points(kf, SelectConfig(n_points=200))
    rho = idepth[sel.uv[:, 1].astype(int), sel.uv[:, 0].astype(int)]
    ref = make_reference(kf, sel.uv, rho, KS)
    far = gtsam.Pose3(gtsam.Rot3.Expmap([0.0, 1.2, 0.0]), np.zeros(3))  # looking 70 deg away
    out = track_frame(ref, kf, T_kf_new_init=far)
    assert not out.ok


def test_trackframe_diverged_affine_start_is_a_failure_not_an_exception(tracking_scene):
    """A diverged estimate hands TrackFrame an absurd affine gain (log gain 800: exp
    overflowed, OverflowError, on the real MH_01 set without TrackFrame's pose guess); the
    gain is bounded as in the factors and the result is a flagged failure."""
    kf, new, idepth, *_ = tracking_scene
    sel = select_points(kf, SelectConfig(n_points=200))
    rho = idepth[sel.uv[:, 1].astype(int), sel.uv[:, 0].astype(int)]
    ref = make_reference(kf, sel.uv, rho, KS)
    out = track_frame(ref, new, ab_init=np.array([800.0, 0.0]))
    assert not out.ok


def test_trackframe_without_points_is_a_quiet_failure(tracking_scene):
    """A keyframe with no points (darkness, no texture: 1 s of black frames in a real MH_01
    copy) is a flagged failure with no NumPy warning on the way (the mean of an empty mask)."""
    import warnings
    kf, new, *_ = tracking_scene
    ref = make_reference(kf, np.zeros((0, 2)), np.zeros(0), KS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = track_frame(ref, new)
    assert not out.ok and out.rmse == float("inf")


def test_direct_config_strict_yaml():
    cfg = from_dict(DirectConfig, {"track": {"levels": 3, "iters": [5, 5, 5]},
                                   "epipolar": {"zero_mean": False}})
    assert cfg.track.levels == 3 and cfg.epipolar.zero_mean is False
    with pytest.raises(ConfigError):
        from_dict(DirectConfig, {"track": {"levls": 3}})
    with pytest.raises(ConfigError):
        from_dict(DirectConfig, {"track": {"levels": 3}})       # iters length mismatch
