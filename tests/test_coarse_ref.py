"""TrackFrame's reference from the whole window (``vio.direct.coarse_ref``)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_photometric import box_scene, render_planes
from factors.photometric import Pinhole
from vio.direct import SelectConfig, TrackConfig
from vio.direct.coarse_ref import host_in_camera, moved_points, one_per_cell, window_reference
from vio.direct.select import select_points
from vio.direct.trackframe import make_reference, track_frame

KS = Pinhole(450.0, 450.0, 319.5, 239.5)
W, H = 640, 480


def test_moved_points_match_a_pinhole_projection():
    rng = np.random.default_rng(0)
    uv_h = rng.uniform([0, 0], [W, H], (200, 2))
    rho_h = rng.uniform(0.1, 3.0, 200)
    T_c_h = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.1, 3)), rng.normal(0, 0.3, 3))
    uv, rho = moved_points(KS, T_c_h, uv_h, rho_h, (H, W))
    cam = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(), gtsam.Cal3_S2(KS.fx, KS.fy, 0.0, KS.cx, KS.cy))
    want_uv, want_rho = [], []
    for (u, v), r in zip(uv_h, rho_h):
        p = T_c_h.transformFrom(np.array([(u - KS.cx) / KS.fx, (v - KS.cy) / KS.fy, 1.0]) / r)
        if p[2] <= 0:
            continue
        q = cam.project(p)
        if 4 <= q[0] <= W - 5 and 4 <= q[1] <= H - 5:
            want_uv.append(q)
            want_rho.append(1.0 / p[2])
    assert 50 < len(uv) < 200                      # some leave the image or go behind it
    np.testing.assert_allclose(uv, np.array(want_uv), atol=1e-9)
    np.testing.assert_allclose(rho, np.array(want_rho), rtol=1e-12)


def test_moved_points_with_a_rolling_shutter_are_the_warp_of_the_factors():
    """With a ``Shutter`` (host = h's camera twist, target = c's) a moved point is where
    the photometric factors' warp (``factors.photometric._warp``) samples camera c, and its
    inverse depth is c's at that row's time; the shutter moves it by pixels."""
    from factors.photometric import HostPatch, _warp
    from factors.photometric_shutter import Shutter
    rng = np.random.default_rng(1)
    uv_h = rng.uniform([40, 40], [W - 40, H - 40], (100, 2))
    rho_h = rng.uniform(0.2, 1.5, 100)
    T_c_h = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.03, 3)), rng.normal(0, 0.05, 3))
    sh = Shutter(1e-4, rng.normal(0, 0.8, 6), rng.normal(0, 0.8, 6))
    uv, rho, ok = host_in_camera(KS, T_c_h, uv_h, rho_h, sh)
    uv0, _, _ = host_in_camera(KS, T_c_h, uv_h, rho_h)

    class Flat:
        def sample(self, u, v):
            z = np.zeros_like(u)
            return z, z, z, np.ones_like(u, bool)

    patch = HostPatch(uv_h, KS.unproject(uv_h)[:, None, :], np.zeros((100, 1)), np.zeros((100, 1)),
                      np.ones((100, 1), bool))
    q, uv_w, *_ = _warp(patch, rho_h, T_c_h.rotation().matrix(), T_c_h.translation(), KS, Flat(), sh)
    assert ok.all()
    np.testing.assert_allclose(uv, uv_w[:, 0], atol=1e-9)
    assert np.median(np.linalg.norm(uv - uv0, axis=1)) > 1.0
    # rho = rho_h / z of the point in c at its row's time (q_s = q - s (w x q + rho v))
    q = q[:, 0]
    s = sh.line_time_s * (KS.fy * q[:, 1] / q[:, 2] + KS.cy)
    q_s = q - s[:, None] * (np.cross(sh.target[:3], q) + rho_h[:, None] * sh.target[3:])
    np.testing.assert_allclose(rho, rho_h / q_s[:, 2], rtol=1e-12)


def test_one_per_cell_keeps_the_first_point_of_each_cell():
    uv = np.array([[5.0, 5.0], [40.0, 5.0], [6.0, 7.0], [39.0, 31.0], [1.0, 40.0]])
    assert one_per_cell(uv, 32.0).tolist() == [0, 1, 4]
    assert one_per_cell(np.zeros((0, 2)), 32.0).size == 0


@pytest.fixture(scope="module")
def window_scene():
    """A keyframe c (world origin), a new frame 2 cm / 1 degree away, and an older host
    h 3 cm behind with the points it selected at their true depths."""
    rng = np.random.default_rng(2)
    planes = box_scene(rng, scales_m=(0.025, 0.08))
    T_true = gtsam.Pose3(gtsam.Rot3.Expmap(np.deg2rad([0.6, -0.7, 0.3])), [0.012, -0.01, 0.012])
    T_w_h = gtsam.Pose3(gtsam.Rot3.Expmap(np.deg2rad([-0.4, 0.5, 0.0])), [-0.02, 0.01, -0.03])
    kf, idepth = render_planes(planes, KS, gtsam.Pose3(), W, H)
    new, _ = render_planes(planes, KS, T_true, W, H)
    host, idepth_h = render_planes(planes, KS, T_w_h, W, H)
    kf, new = kf + rng.normal(0, 1.0, kf.shape), new + rng.normal(0, 1.0, kf.shape)
    sel = select_points(kf, SelectConfig(n_points=400)).uv
    sel_h = select_points(host, SelectConfig(n_points=400)).uv
    rho = idepth[sel[:, 1].astype(int), sel[:, 0].astype(int)]
    rho_h = idepth_h[sel_h[:, 1].astype(int), sel_h[:, 0].astype(int)]
    return kf, new, T_true, T_w_h, (sel, rho), (sel_h, rho_h)


def test_window_points_outweigh_wrong_own_depths(window_scene):
    """The keyframe's own points in its lower half carry depths 25 % short (as the stereo
    depths of the real MH_01 planks pulled TrackFrame 8-11 mm off): alone they bias the
    alignment; with the older host's points at their true depths first in every 32-px
    cell, only the cells they leave to the wrong points keep a little of the bias."""
    kf, new, T_true, T_w_h, (uv, rho), (uv_h, rho_h) = window_scene
    wrong = np.where(uv[:, 1] > H / 2, rho / 0.75, rho)
    var = np.full(len(rho), 1e-4)
    cfg = TrackConfig()

    def error_mm(ref) -> float:
        out = track_frame(ref, new, config=cfg)
        assert out.ok
        return 1e3 * float(np.linalg.norm(T_true.between(out.T_kf_new).translation()))

    own = error_mm(make_reference(kf, uv, wrong, KS, var, config=cfg))
    win = error_mm(window_reference(kf, KS, gtsam.Pose3(), (uv, wrong, var), [(T_w_h, uv_h, rho_h)],
                                    np.zeros(2), 32.0, cfg))
    right = error_mm(make_reference(kf, uv, rho, KS, var, config=cfg))
    print(f"own points, wrong depths {own:.2f} mm; with the window's {win:.2f} mm; right depths {right:.2f} mm")
    assert own > 3.0
    assert win < 2.5 and win < own / 3      # measured 7.04 -> 1.68 mm (right depths 0.59)
