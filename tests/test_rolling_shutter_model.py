"""The rolling-shutter warp of the photometric factors (``factors.photometric_shutter.Shutter``)
against the simulator's exact row geometry (``vio.sim``: row r of an image exposed at
stamp + td + r * line_time, the camera at its trajectory pose of that instant): the
Jacobian suite checks the warp's derivatives, this checks that the warp is the camera."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from factors.photometric import HostPatch, Pinhole, stereo_eval, temporal_eval
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


# EuRoC cam1's lens (its sensor.yaml), for the right camera of the stereo case
CAM1_LENS = {"radial-tangential": (-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05)}


class _LoopRig:
    """The rolling-shutter stereo rig of a rendered loop (seed 12's trajectory, 30 us a
    row: 14.4 ms readout), each camera with ``lens`` (None: pinhole) or not."""

    def __init__(self, lens: str) -> None:
        self.traj = make_trajectory(SimConfig(seconds=20.0, seed=12, line_time_s=LINE_S))
        self.cams = [sim_camera(n, 1.0, 20.0, LINE_S) for n in ("cam0", "cam1")]
        self.K = [Pinhole(*c.intrinsics) for c in self.cams]
        self.w, self.h = self.cams[0].resolution
        coeffs = [LENS.get(lens), CAM1_LENS.get(lens, LENS.get(lens))]
        self.rows = [None if lens == "none" else row_model(c.intrinsics, lens, d) for c, d in zip(self.cams, coeffs)]
        self.lens = [None if lens == "none" else Camera(replace(c, distortion_model=lens, distortion=d))
                     for c, d in zip(self.cams, coeffs)]

    def T_w_c(self, t: float, i: int = 0) -> gtsam.Pose3:
        s = self.traj.sample(np.array([t]))
        return gtsam.Pose3(gtsam.Rot3(s.R_w_b[0]), s.p_w[0]).compose(self.cams[i].T_b_c)

    def twist(self, t: float, dt: float = 1e-5) -> np.ndarray:
        """cam0's twist [omega, v] in its own frame at t."""
        return gtsam.Pose3.Logmap(self.T_w_c(t).between(self.T_w_c(t + dt))) / dt

    def seen(self, p_w: np.ndarray, t0: float, i: int = 0) -> tuple[np.ndarray, float, float]:
        """(Undistorted) pixel, z-depth and sensor row where camera i of the frame whose
        row 0 is at t0 sees p_w: the row that sees the point, at that row's pose."""
        K, lens, r = self.K[i], self.lens[i], self.h / 2.0
        for _ in range(30):
            p = self.T_w_c(t0 + r * LINE_S, i).transformTo(p_w)
            u, v = K.fx * p[0] / p[2] + K.cx, K.fy * p[1] / p[2] + K.cy
            r = v if lens is None else lens.project_normalized((p[:2] / p[2])[None])[0, 1]
        return np.array([u, v]), float(p[2]), r

    def point(self, rng: np.random.Generator, t: float) -> tuple[np.ndarray, HostPatch, float, float]:
        """A random world point seen by cam0 at t, its host patch there, inverse depth and
        sensor row."""
        uv0, z0 = rng.uniform([50, 20], [self.w - 50, self.h - 20]), rng.uniform(1.5, 6.0)
        K = self.K[0]
        p_w = self.T_w_c(t + uv0[1] * LINE_S).transformFrom(np.append(K.unproject(uv0)[:2], 1.0) * z0)
        uv_h, z_h, r_h = self.seen(p_w, t)
        return p_w, HostPatch(uv_h[None], K.unproject(uv_h[None, None]), np.zeros((1, 1)), np.zeros((1, 1)),
                              np.ones((1, 1), bool)), 1.0 / z_h, r_h

    def inside(self, uv: np.ndarray, row: float) -> bool:
        return bool(0 < uv[0] < self.w and 0 < uv[1] < self.h and 0 <= row < self.h)


@pytest.mark.parametrize("lens", ["none", "radial-tangential", "equidistant"])
def test_shutter_warp_is_the_simulated_rolling_shutter_camera(lens):
    """Random points seen by the loop's rolling-shutter camera in two frames 50-400 ms
    apart: the warp from the host pixel and its depth at the host row's time, with the
    cameras' row-0 poses and twists, lands within 0.1 px of where the simulator's camera
    sees the point (measured: median 0.004 px, max 0.06 px); the global-shutter warp is
    off by 0.3 px median, 2 px at worst. Through a lens (``lens``: EuRoC's / TUM-VI's
    coefficients, the pixels those of the undistorted image) the row that sees the point
    is its *sensor* row, and the warp with the lens's row model lands as close (radial-
    tangential: median 0.004, max 0.04 px; the pinhole rows' warp is off by up to 0.4 px)."""
    rig = _LoopRig(lens)
    rng = np.random.default_rng(0)
    err, err_gs = [], []
    while len(err) < 150:
        t_h = rng.uniform(1.0, 18.0)
        t_j = t_h + rng.choice([0.05, 0.1, 0.2, 0.4])
        p_w, host, rho, r_h = rig.point(rng, t_h)
        uv_j, _, r_j = rig.seen(p_w, t_j)
        if not (rig.inside(uv_j, r_j) and 0 <= r_h < rig.h):
            continue
        for sh, out in ((Shutter(LINE_S, rig.twist(t_h), rig.twist(t_j), rig.rows[0], rig.rows[0]), err),
                        (None, err_gs)):
            ev = temporal_eval(rig.T_w_c(t_h), rig.T_w_c(t_j), np.array([rho]), np.zeros(2), np.zeros(2),
                               host, _Flat(), rig.K[0], gtsam.Pose3(), shutter=sh)
            out.append(np.linalg.norm(ev.uv[0, 0] - uv_j))
    assert np.median(err) < 0.01 and np.max(err) < 0.1, (np.median(err), np.max(err))
    assert np.median(err_gs) > 0.1


@pytest.mark.parametrize("lens", ["none", "radial-tangential"])
def test_stereo_shutter_warp_is_the_simulated_rolling_shutter_rig(lens):
    """The static stereo warp (left host -> right image of the same frame; both cameras'
    row r exposed at the same time) with the right camera's twist taken as the runtime
    takes it (the left's moved by T_c1_c0, ``factors.photometric_host.shutter_args``) and
    each camera's own lens rows: within 0.1 px of where the simulator's right camera sees
    the point (measured with EuRoC's lenses: median 0.004, max 0.06 px)."""
    rig = _LoopRig(lens)
    T_r_l = rig.cams[1].T_b_c.inverse().compose(rig.cams[0].T_b_c)
    rng = np.random.default_rng(1)
    err = []
    while len(err) < 150:
        t = rng.uniform(1.0, 18.0)
        p_w, host, rho, r_h = rig.point(rng, t)
        uv_r, _, r_r = rig.seen(p_w, t, 1)
        if not (rig.inside(uv_r, r_r) and 0 <= r_h < rig.h):
            continue
        tw = rig.twist(t)
        sh = Shutter(LINE_S, tw, T_r_l.AdjointMap() @ tw, rig.rows[0], rig.rows[1])
        ev = stereo_eval(np.array([rho]), np.zeros(2), host, _Flat(), rig.K[1], T_r_l, shutter=sh)
        err.append(np.linalg.norm(ev.uv[0, 0] - uv_r))
    assert np.median(err) < 0.01 and np.max(err) < 0.1, (np.median(err), np.max(err))


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
