"""The rolling-shutter warp of the photometric factors (``factors.photometric_shutter.Shutter``)
against the simulator's exact row geometry (``vio.sim``: row r of an image exposed at
stamp + td + r * line_time, the camera at its trajectory pose of that instant): the
Jacobian suite checks the warp's derivatives, this checks that the warp is the camera."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from factors.photometric import HostPatch, Pinhole, temporal_eval
from factors.photometric_shutter import Shutter
from factors.photometric_warp import row_model
from vio.frontend.camera import Camera
from vio.sim.config import SimConfig
from vio.sim.render import sim_camera
from vio.sim.trajectory import make_trajectory

from cases_photometric import LENS

LINE_S = 30e-6


class _Flat:
    """A target image that is everywhere valid (only the warp's pixels are compared)."""

    def sample(self, u, v):
        z = np.zeros_like(u)
        return z, z, z, np.ones_like(u, bool)


@pytest.mark.parametrize("lens", ["none", "radial-tangential", "equidistant"])
def test_shutter_warp_is_the_simulated_rolling_shutter_camera(lens):
    """Random points seen by the rolling-shutter camera of a rendered loop (seed 12's
    trajectory, 30 us a row: 14.4 ms readout) in two frames 50-400 ms apart: the warp from
    the host pixel and its depth at the host row's time, with the cameras' row-0 poses
    and twists, lands within 0.1 px of where the simulator's camera sees the point
    (measured: median 0.004 px, max 0.06 px); the global-shutter warp is off by 0.3 px
    median, 2 px at worst. Through a lens (``lens``: EuRoC's / TUM-VI's coefficients, the
    pixels those of the undistorted image) the row that sees the point is its *sensor*
    row, and the warp with the lens's row model lands as close (radial-tangential: median
    0.004, max 0.04 px; the pinhole rows' warp is off by up to 0.4 px there)."""
    cfg = SimConfig(seconds=20.0, seed=12, line_time_s=LINE_S)
    traj = make_trajectory(cfg)
    cam = sim_camera("cam0", 1.0, 20.0, LINE_S)
    K = Pinhole(*cam.intrinsics)
    w, h = cam.resolution
    rows = None if lens == "none" else row_model(cam.intrinsics, lens, LENS[lens])
    lens_row = None if lens == "none" else Camera(replace(cam, distortion_model=lens, distortion=LENS[lens]))

    def T_w_c(t: float) -> gtsam.Pose3:
        s = traj.sample(np.array([t]))
        return gtsam.Pose3(gtsam.Rot3(s.R_w_b[0]), s.p_w[0]).compose(cam.T_b_c)

    def twist(t: float, dt: float = 1e-5) -> np.ndarray:
        return gtsam.Pose3.Logmap(T_w_c(t).between(T_w_c(t + dt))) / dt

    def seen(p_w: np.ndarray, t0: float) -> tuple[np.ndarray, float, float]:
        """(Undistorted) pixel, z-depth and sensor row where the camera of the frame whose
        row 0 is at t0 sees p_w."""
        r = h / 2.0
        for _ in range(30):             # the row that sees the point, at that row's pose
            p = T_w_c(t0 + r * LINE_S).transformTo(p_w)
            u, v = K.fx * p[0] / p[2] + K.cx, K.fy * p[1] / p[2] + K.cy
            r = v if lens_row is None else lens_row.project_normalized((p[:2] / p[2])[None])[0, 1]
        return np.array([u, v]), float(p[2]), r

    rng = np.random.default_rng(0)
    err, err_gs = [], []
    while len(err) < 150:
        t_h = rng.uniform(1.0, 18.0)
        t_j = t_h + rng.choice([0.05, 0.1, 0.2, 0.4])
        uv0, z0 = rng.uniform([50, 20], [w - 50, h - 20]), rng.uniform(1.5, 6.0)
        p_w = T_w_c(t_h + uv0[1] * LINE_S).transformFrom(np.append(K.unproject(uv0)[:2], 1.0) * z0)
        uv_h, z_h, r_h = seen(p_w, t_h)
        uv_j, _, r_j = seen(p_w, t_j)
        if not (0 < uv_j[0] < w and 0 < uv_j[1] < h and 0 <= r_h < h and 0 <= r_j < h):
            continue
        host = HostPatch(uv_h[None], K.unproject(uv_h[None, None]), np.zeros((1, 1)), np.zeros((1, 1)),
                         np.ones((1, 1), bool))
        for sh, out in ((Shutter(LINE_S, twist(t_h), twist(t_j), rows, rows), err), (None, err_gs)):
            ev = temporal_eval(T_w_c(t_h), T_w_c(t_j), np.array([1.0 / z_h]), np.zeros(2), np.zeros(2),
                               host, _Flat(), K, gtsam.Pose3(), shutter=sh)
            out.append(np.linalg.norm(ev.uv[0, 0] - uv_j))
    assert np.median(err) < 0.01 and np.max(err) < 0.1, (np.median(err), np.max(err))
    assert np.median(err_gs) > 0.1


def test_sensor_row_is_the_lens_projection_row():
    """``factors.photometric_warp.sensor_row`` (the row a rolling shutter times, for an
    undistorted point) is the row of the camera's own distorted projection
    (``vio.frontend.camera.Camera``) for EuRoC's radial-tangential and TUM-VI's equidistant
    lenses, up to the image corners and beyond; its derivatives match central
    differences; without a lens it is the pinhole row."""
    from factors.photometric_warp import sensor_row, sensor_rows
    base = sim_camera("cam0", 1.0, 20.0, LINE_S)
    lenses = {**LENS, "none": (0.0, 0.0, 0.0, 0.0)}
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-0.9, 0.9, 200), rng.uniform(-0.6, 0.6, 200)
    x[:2], y[:2] = 0.0, (0.0, 1e-12)                      # the optical axis
    for model, D in lenses.items():
        calib = replace(base, distortion_model=model, distortion=D if model != "none" else ())
        m = row_model(calib.intrinsics, model, D)
        row, gx, gy = sensor_rows(x, y, m)
        np.testing.assert_allclose(row, Camera(calib).project_normalized(np.column_stack([x, y]))[:, 1],
                                   atol=1e-9)
        e = 1e-6
        for i in range(0, 200, 7):
            fdx = (sensor_row(x[i] + e, y[i], m)[0] - sensor_row(x[i] - e, y[i], m)[0]) / (2 * e)
            fdy = (sensor_row(x[i], y[i] + e, m)[0] - sensor_row(x[i], y[i] - e, m)[0]) / (2 * e)
            assert abs(fdx - gx[i]) < 1e-4 * base.intrinsics[1] and abs(fdy - gy[i]) < 1e-4 * base.intrinsics[1]
        if model == "none":
            np.testing.assert_allclose(row, base.intrinsics[1] * y + base.intrinsics[3], atol=1e-9)
        else:   # a lens bends the rows: tens of rows off the pinhole row near the corners
            assert np.abs(row - (base.intrinsics[1] * y + base.intrinsics[3])).max() > 10.0
