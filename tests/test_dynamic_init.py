"""Dynamic initialization (visual-inertial alignment, ``vio.backend.dynamic_init``).

Errors are compared in the first body frame b0 (frame-independent): velocity
``R_w_b0^T v_w`` and gravity direction ``R_w_b0^T e_z``.

* Synthetic windows (no files): exact analytic IMU with biases, noisy tracks with
  outliers; an accelerating window must be aligned accurately (gyro bias included), a
  constant-velocity window (scale unobservable) must be rejected, a hovering one accepted.
* Simulated sequences (``vio sim`` + track generator, as in the memory soak): the
  first window of several seeds. Seeds 7 and 9 are the soak's failure: the old linear
  alignment returned ``|v0 - v_true|`` = 0.77 / 0.93 m/s (at 0.68 / 0.96 m/s).
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from vio.backend.config import BackendConfig
from vio.backend.dynamic_init import align, init_window
from vio.backend.init import InitialState
from vio.io.types import FeatureFrame, ImuCalib, ImuData
from vio.sim.render import sim_camera
from vio.sim.trajectory import R0 as R_W_B0   # body x up, z forward (EuRoC MAV)
from vio.sync import packets

G_W = np.array([0.0, 0.0, -9.81])
IMU_CALIB = ImuCalib(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3, 200.0)


def _b0_errors(state: InitialState, R_true: np.ndarray, v_true: np.ndarray,
               bg_true: np.ndarray) -> tuple[float, float, float]:
    """|v0| error (m/s), gravity direction error (deg), |gyro bias| error (rad/s), in b0."""
    R = state.T_w_b.rotation().matrix()
    dv = np.linalg.norm(R.T @ state.v_w - R_true.T @ v_true)
    cos = (R.T @ [0, 0, 1.0]) @ (R_true.T @ [0, 0, 1.0])
    dbg = np.linalg.norm(state.bias.gyroscope() - bg_true)
    return float(dv), float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), float(dbg)


def _synthetic_window(accel_amp: float, omega_b: np.ndarray, seed: int = 0,
                      outlier_rate: float = 0.02, v0: tuple = (0.5, 0.3, 0.1)):
    """A 1.5-s window: body path ``v0 t + A sin(W t)`` (acceleration ~ ``accel_amp``
    m/s^2), rotation ``R_W_B0 Exp(omega_b t)``; 200 Hz IMU with gyro bias 0.05 rad/s
    (EuRoC's is ~0.08) and accel bias 0.05 m/s^2; 20 Hz tracks of points 2-9 m ahead
    (0.5 px noise, ``outlier_rate`` of them displaced by 20-40 px).
    Returns the window, camera, and the true ``R_w_b0``, ``v_w(0)``, gyro bias."""
    rng = np.random.default_rng(seed)
    cam = sim_camera("cam0")
    v0, W = np.array(v0, float), 3.0
    A = accel_amp / W ** 2 * np.array([1.0, 0.8, 0.4])
    bg, ba = np.array([0.02, -0.03, 0.035]), np.array([0.03, -0.02, 0.03])
    t_imu = np.arange(0, 1.6 + 1e-9, 0.005)
    R = [R_W_B0 @ gtsam.Rot3.Expmap(omega_b * t).matrix() for t in t_imu]
    acc_w = -W ** 2 * np.sin(W * t_imu)[:, None] * A
    accel = np.array([Rk.T @ (a - G_W) for Rk, a in zip(R, acc_w)]) + ba
    gyro = np.tile(omega_b + bg, (len(t_imu), 1))
    t0 = 1_000_000_000
    imu = ImuData(t0 + np.round(t_imu * 1e9).astype(np.int64), gyro, accel)
    pts = np.c_[rng.uniform(2, 9, 300), rng.uniform(-4, 4, 300), rng.uniform(-2, 2, 300)]
    T_b_c = cam.T_b_c.matrix()
    fx = cam.intrinsics[0]
    stamps, frames = t0 + np.arange(0, 31) * 50_000_000, []
    for s in stamps:
        t = (s - t0) * 1e-9
        Rb = R_W_B0 @ gtsam.Rot3.Expmap(omega_b * t).matrix()
        pb = v0 * t + A * np.sin(W * t)
        Rc, pc = Rb @ T_b_c[:3, :3], pb + Rb @ T_b_c[:3, 3]
        p_c = (pts - pc) @ Rc
        uv = p_c[:, :2] / p_c[:, 2:3]
        ok = (p_c[:, 2] > 0.5) & (np.abs(uv[:, 0]) < 0.75) & (np.abs(uv[:, 1]) < 0.5)
        ids = np.flatnonzero(ok)[:60]
        uv = uv[ids] + rng.normal(0, 0.5 / fx, (len(ids), 2))
        bad = rng.random(len(ids)) < outlier_rate
        ang = rng.uniform(0, 2 * np.pi, bad.sum())
        uv[bad] += rng.uniform(20, 40, (bad.sum(), 1)) / fx * np.c_[np.cos(ang), np.sin(ang)]
        frames.append(FeatureFrame(int(s), ids.astype(np.int64), uv, np.zeros_like(uv),
                                   np.zeros(len(ids))))
    win = init_window(list(packets(imu, stamps, 0.0, frames)), 0.1)
    return win, cam, R_W_B0, v0 + A * W, bg


def test_accelerating_window_is_aligned_with_gyro_bias_and_outliers():
    win, cam, R_true, v_true, bg = _synthetic_window(1.0, np.array([0.3, 0.2, -0.1]))
    res = align(win, cam, IMU_CALIB, BackendConfig())
    assert res.ok, res.reason
    dv, dg, dbg = _b0_errors(res.state, R_true, v_true, bg)
    print(f"synthetic: |dv| {dv:.4f} m/s, gravity {dg:.3f} deg, |dbg| {dbg:.4f} rad/s, "
          f"v0 sigma {res.v0_sigma:.4f}, inliers {res.inlier_ratio:.3f}")
    assert dv < 0.05          # measured 0.016
    assert dg < 0.5           # measured 0.26 (accel bias 0.05 m/s^2 ~ 0.3 deg of tilt)
    assert dbg < 0.005        # true gyro bias 0.05 rad/s; measured 0.0012
    assert 0.9 < res.inlier_ratio < 0.995   # the injected outliers were found
    # the window batch's scale uncertainty travels with the state (the run summary prints it)
    assert res.state.scale_sigma == res.scale_sigma and 0.0 < res.scale_sigma < 0.2


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("omega", [(0.3, 0.2, -0.1), (0.0, 0.0, 0.0)])
def test_constant_velocity_window_is_rejected(seed, omega):
    """Without acceleration the IMU carries no scale: any velocity along the true one
    explains the images (the alignment returned 0.03 to 2 m/s for a true 0.6 m/s), so
    the window must be refused rather than guessed."""
    win, cam, *_ = _synthetic_window(0.0, np.array(omega), seed=seed)
    res = align(win, cam, IMU_CALIB, BackendConfig())
    assert not res.ok and res.state is None
    assert res.excitation < 0.02                    # measured < 0.01 m/s^2
    assert "acceleration" in res.reason, res.reason


def test_poorly_scaled_window_is_rejected():
    """Little acceleration (0.16 m/s^2 of excitation, above ``min_excitation``): the batch
    pins the window's metric translation only to ~21% (the same window at 1 m/s^2: ~4%),
    so the initialization is refused instead of starting with a guessed scale."""
    win, cam, *_ = _synthetic_window(0.2, np.array([0.3, 0.2, -0.1]))
    res = align(win, cam, IMU_CALIB, BackendConfig())
    assert not res.ok and res.state is None
    assert res.excitation > BackendConfig().init.dynamic.min_excitation
    assert "scale poorly determined" in res.reason, res.reason
    assert res.scale_sigma > BackendConfig().init.dynamic.max_scale_sigma   # measured 0.21
    good = align(_synthetic_window(1.0, np.array([0.3, 0.2, -0.1]))[0], cam, IMU_CALIB, BackendConfig())
    assert good.ok and good.scale_sigma < 0.08                                # measured 0.043


def test_hovering_window_is_accepted():
    """Rotating in place, no acceleration: no scale either, but no translation parallax
    (rotation alone explains the tracks), so ``v0 ~ 0`` is safe and accepted."""
    win, cam, R_true, v_true, bg = _synthetic_window(0.0, np.array([0.3, 0.2, -0.1]),
                                                     v0=(0.0, 0.0, 0.0))
    res = align(win, cam, IMU_CALIB, BackendConfig())
    assert res.ok, res.reason
    dv, dg, dbg = _b0_errors(res.state, R_true, v_true, bg)
    print(f"hover: |dv| {dv:.4f} m/s, gravity {dg:.3f} deg, |dbg| {dbg:.4f} rad/s")
    assert dv < 0.05 and dg < 0.5 and dbg < 0.005   # measured 0.016, 0.15, 0.0019


@pytest.fixture(scope="module")
def sim_windows(tmp_path_factory):
    """The first 1.5-s window of 4-s simulated sequences (memory-soak recipe), with
    the ground truth at its first keyframe."""
    from vio.io.euroc import load_euroc
    from vio.sim import simulate
    from vio.sim.config import SimConfig
    from vio.sim.tracks import TrackGenConfig, generate_tracks
    out = {}
    for seed in SEEDS:
        root = tmp_path_factory.mktemp(f"dyn{seed}")
        simulate(root / "raw", SimConfig(seconds=4.0, seed=seed, stereo=False, render_images=False))
        generate_tracks(root / "raw", root / "trk", TrackGenConfig(td_s=0.005, seed=seed))
        data = load_euroc(root / "trk")
        pk = []
        for p in packets(data.imu, data.cam0.t_ns, 0.0, data.features):
            pk.append(p)
            if (p.t_ns - pk[0].t_ns) * 1e-9 >= 1.5:
                break
        gt = data.groundtruth
        i = int(np.searchsorted(gt.t_ns, pk[0].t_ns))
        truth = (gt.pose(i).rotation().matrix(), gt.v_w[i], gt.bg[i])
        out[seed] = (init_window(pk, 0.1), data.cam0.calib, data.imu_calib, truth)
    return out


SEEDS = (2, 7, 9, 13)


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS)
def test_simulated_moving_start(sim_windows, seed):
    """|v0| error < 0.15 m/s and gravity < 1.5 deg on the first window. Measured
    (new / old): seed 2 0.022 / 0.055 m/s, 7 0.035 / 0.77, 9 0.059 / 0.93,
    13 0.010 / 0.011; gravity 0.4-0.6 deg (old: up to 3.1)."""
    win, cam, imu_calib, (R, v, bg) = sim_windows[seed]
    res = align(win, cam, imu_calib, BackendConfig())
    assert res.ok, res.reason
    dv, dg, dbg = _b0_errors(res.state, R, v, bg)
    print(f"seed {seed}: |dv| {dv:.3f} m/s (|v| {np.linalg.norm(v):.2f}), gravity {dg:.2f} deg, "
          f"|dbg| {dbg:.4f}, v0 sigma {res.v0_sigma:.3f}, |g| error {100 * res.gravity_error:.2f}%")
    assert dv < 0.15
    assert dg < 1.5
    assert dbg < 0.02
    assert res.v0_disagreement < 0.15 and res.gravity_disagreement_deg < 1.5


def _mh05_window(first: int, n: int = 31, stride: int = 1):
    """The real MH_05 images ``first, first + stride, ...`` (``n`` of them) through mono's
    KLT front end, aligned with mono's defaults: (data, first packet, mono config,
    AlignResult)."""
    from conftest import shared
    from vio.io.euroc import image_files, load_euroc
    from vio.run import default_config
    from vio.tracking import ImageStage
    data = load_euroc(shared("euroc_MH_05_mono_15s"))
    cfg = default_config("mono")
    stage = ImageStage(data.cam0.calib, None, cfg.frontend)
    files = image_files(data, False, data.cam0.t_ns[first:first + n * stride:stride])
    pk = [stage(p) for p in packets(data.imu, data.cam0.t_ns[first:first + n * stride:stride], 0.0,
                                    image_files=files)]
    res = align(init_window(pk, cfg.backend.init.dynamic.step_s), data.cam0.calib, data.imu_calib,
                cfg.backend)
    return data, pk[0], cfg, res


def _mh05_window_errors(first: int, **window) -> tuple[float, float, float]:
    """:func:`_mh05_window` (``window``: its ``n`` and ``stride``), accepted, and its first
    state's errors against the ground truth at the first packet (:func:`_b0_errors`)."""
    data, pk0, _, res = _mh05_window(first, **window)
    assert res.ok, res.reason
    gt = data.groundtruth
    i = np.searchsorted(gt.t_ns, pk0.t_ns)
    R_true = gtsam.Rot3.Quaternion(*gt.q_wxyz[i]).matrix()
    return _b0_errors(res.state, R_true, gt.v_w[i], gt.bg[i])


def test_real_mh05_first_window_from_hover():
    """Real MH_05 images from the first frame, where the MAV hovers (0.005 m/s) before
    climbing (0.35 m/s after 1 s). Started at zero gyro bias (true [-0.002, 0.021, 0.077]
    rad/s) the alignment settled in a local minimum with v0 = 0.40 m/s and the batch
    accepted it; the visual-rotation bias (``gyro_init``) starts it in the right basin."""
    dv, dg, dbg = _mh05_window_errors(0)
    print(f"MH_05 first window: |dv| {dv:.4f} m/s, gravity {dg:.2f} deg, |dbg| {dbg:.4f} rad/s")
    assert dv < 0.05 and dbg < 0.005 and dg < 2.0   # measured 0.010, 0.89, 0.0017 (was |dv| 0.40)


@pytest.mark.parametrize("first", [0, 2])
def test_real_mh05_window_at_a_third_of_the_frame_rate(first):
    """Every third real MH_05 image (6.7 Hz) from the hover: the keyframes' pair rotations
    have 0.5-2 px of translation parallax. A cheirality count on the essential matrix lost
    13 of 15 of them, the alignment started at zero gyro bias and took v0 = 0.35-0.41 m/s
    down for a true 0.003 (gyro bias y off by 0.027 rad/s; the runs ended at 0.158 / 0.208
    m ATE). The essential matrix's candidate next to the rotation-only fit keeps them."""
    dv, dg, dbg = _mh05_window_errors(first, n=11, stride=3)
    print(f"MH_05 from {first} at 6.7 Hz: |dv| {dv:.4f} m/s, gravity {dg:.2f} deg, |dbg| {dbg:.4f} rad/s")
    assert dv < 0.15 and dbg < 0.015 and dg < 2.0   # measured 0.097 / 0.046, 0.0087 / 0.0036


def test_real_mh05_late_window_keeps_its_velocity_uncertainty():
    """Real MH_05 images 5.5 s into the clip: the alignment's own v0 standard deviation
    (0.090 m/s with mono's defaults) is wider than the default velocity prior (0.05 m/s),
    and the first state's prior takes the wider one (``bench_stretches.py``, pixel sigma
    1 px then: start 160 ATE 168 -> 153 mm, start 110 122 -> 118 mm)."""
    _, _, cfg, res = _mh05_window(110)
    assert res.ok, res.reason
    assert res.v0_sigma > cfg.backend.init.prior_vel_sigma      # measured 0.090
    assert res.state.vel_sigma is not None and res.state.vel_sigma >= res.v0_sigma
