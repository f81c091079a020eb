"""Visual-inertial BA over the keyframe history (vio.backend.viba): a smoother history with a
wrong scale and tilt is corrected to the truth (a swaying flight with exact IMU, landmark
observations with 0.5-px noise), and a history without acceleration (no scale information)
is refused."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from factors.robust import RobustKernel
from vio.backend import viba
from vio.backend.regauge import Similarity
from vio.backend.scale_refine import RefineConfig
from vio.imu import ImuNoiseConfig, combined_params

FX = 458.0
T_B_C = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2), np.array([-0.02, -0.06, 0.01]))


def _observations(poses: list, rng: np.random.Generator, noise_px: float = 0.5) -> list:
    """Per keyframe ``(ids, uv)``: points spawned every 3rd keyframe 3-8 m ahead of its camera,
    seen by the following keyframes within the field of view."""
    cams = [T.compose(T_B_C) for T in poses]
    pts = []
    for k in range(0, len(poses), 3):
        uv = rng.uniform(-0.5, 0.5, (30, 2))
        d = rng.uniform(3.0, 8.0, 30)
        pts += [cams[k].transformFrom(np.r_[u, 1.0] * z) for u, z in zip(uv, d)]
    out = []
    for c in cams:
        ids, uvs = [], []
        for i, p in enumerate(pts):
            q = c.transformTo(p)
            if q[2] > 0.5 and np.all(np.abs(q[:2] / q[2]) < 0.6):
                ids.append(i)
                uvs.append(q[:2] / q[2] + rng.normal(0.0, noise_px / FX, 2))
        out.append((np.array(ids, np.int64), np.array(uvs).reshape(-1, 2)))
    return out


def _history(poses, vel, pims, bias, rng) -> viba.History:
    n = len(poses)
    return viba.History(list(range(n)), list(poses), np.asarray(vel), [bias] * n, list(pims),
                        _observations(poses, rng), np.arange(n) >= n - 12)


def _solve(h: viba.History, cfg: RefineConfig = RefineConfig(enabled=True)) -> viba.VibaResult:
    return viba.solve(h, T_B_C, 1.0 / FX, RobustKernel("huber", 3.0), 6.0 / FX,
                      np.r_[np.full(3, 0.2), np.full(3, 0.01)], cfg)


def _params():
    calib = type("C", (), dict(gyro_noise_density=1.7e-4, accel_noise_density=2e-3,
                               gyro_random_walk=1.9e-5, accel_random_walk=3e-3))()
    return combined_params(calib, ImuNoiseConfig())


def _motion(t: float):
    """A swaying flight: body position (m), velocity, acceleration (world), yaw (rad) and
    yaw rate (rad/s); roll and pitch zero."""
    A, w, ph = np.array([1.0, 0.8, 0.3]), np.array([0.9, 1.3, 1.7]), np.array([0.0, 0.5, 0.0])
    p, v, a = A * np.sin(w * t + ph), A * w * np.cos(w * t + ph), -A * w * w * np.sin(w * t + ph)
    return p, v, a, 0.4 * np.sin(0.7 * t), 0.28 * np.cos(0.7 * t)


def _swaying_history(seconds: float = 8.0, step: float = 0.2, dt: float = 0.005):
    """Keyframe poses, velocities and exact (noise-free) preintegrated IMU of :func:`_motion`."""
    params, bias = _params(), gtsam.imuBias.ConstantBias()
    n = int(round(seconds / step))
    poses, vel, pims = [], [], []
    for k in range(n + 1):
        p, v, _, yaw, _ = _motion(k * step)
        poses.append(gtsam.Pose3(gtsam.Rot3.Rz(yaw), p))
        vel.append(v)
        if k == n:
            break
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        for m in range(int(round(step / dt))):
            tm = k * step + (m + 0.5) * dt
            _, _, a, yaw_m, rate = _motion(tm)
            pim.integrateMeasurement(gtsam.Rot3.Rz(yaw_m).unrotate(a + np.array([0.0, 0.0, 9.81])),
                                     np.array([0.0, 0.0, rate]), dt)
        pims.append(pim)
    return poses, np.array(vel), pims, bias


def test_corrects_scale_and_tilt():
    poses, vel, pims, bias = _swaying_history()
    # the smoother's history: 5% short and tilted by 1 degree about the first camera
    sim = Similarity(0.95, gtsam.Rot3.Rx(np.radians(1.0)), poses[0].compose(T_B_C).translation(),
                     T_B_C.translation())
    bad = [sim.pose(T) for T in poses]
    h = _history(bad, [sim.velocity(v) for v in vel], pims, bias, np.random.default_rng(3))
    res = _solve(h)
    assert res.ok, res.reason
    assert res.scale == pytest.approx(1 / 0.95, rel=0.005)
    assert res.gravity_change_deg == pytest.approx(1.0, abs=0.2)
    assert np.allclose(res.pivot, bad[-1].compose(T_B_C).translation())   # no jump at the newest
    fix = Similarity(res.scale, res.R_corr, res.pivot, T_B_C.translation())
    rel = [fix.pose(b).translation() - fix.pose(bad[-1]).translation() for b in bad]
    err = [np.linalg.norm(r - (T.translation() - poses[-1].translation())) for r, T in zip(rel, poses)]
    assert max(err) < 0.03           # the corrected history has the truth's shape and size
    tilt = [np.degrees(np.linalg.norm(fix.pose(b).rotation().between(T.rotation()).ypr()[1:]))
            for b, T in zip(bad, poses)]
    assert max(tilt) < 0.2


def test_refuses_a_history_without_acceleration():
    """Constant velocity and attitude: the IMU says nothing about the scale."""
    params = _params()
    v = np.array([0.8, 0.3, 0.0])
    R = gtsam.Rot3.Ypr(0.3, 0.0, 0.0)
    poses = [gtsam.Pose3(R, v * 0.2 * k) for k in range(31)]
    bias = gtsam.imuBias.ConstantBias()
    f_b = R.unrotate(np.array([0.0, 0.0, 9.81]))
    pims = []
    for _ in range(30):
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        for _ in range(40):
            pim.integrateMeasurement(f_b, np.zeros(3), 0.005)
        pims.append(pim)
    res = _solve(_history(poses, [v] * 31, pims, bias, np.random.default_rng(4)))
    assert not res.ok
    assert "poorly determined" in res.reason


def _v101_refined(**refine):
    """The pipeline on the first 180 real V1_01 frames with the refinement enabled (first at
    3 s, every 2 s, a permissive sigma bound) and ``refine`` overrides; returns its estimator."""
    from tests.conftest import shared
    from vio.io.euroc import load_euroc
    from vio.pipeline import Pipeline
    from vio.run import default_config
    from vio.sync import packets
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    cfg = default_config("features")
    ref = dataclasses.replace(cfg.backend.refine, enabled=True, first_s=3.0, every_s=2.0,
                              ba_max_scale_sigma=0.5, **refine)
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, refine=ref))
    pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg)
    it = packets(data.imu, data.cam0.t_ns, cfg.td_s, data.features)
    for _ in range(180):
        pipe.process(next(it))
    return pipe.est


def test_pipeline_applies_the_batch_scale_on_real_v101():
    """Enabled on the real V1_01 tracks: the refiner runs the batch from ``first_s`` on and
    puts its scale on the newest velocity without a recovery or an implausible state."""
    est = _v101_refined()
    log = est.refiner.log
    assert log and log[0][0] >= 3.0
    assert est.refiner.applied >= 1
    assert all(0.8 < r.scale < 1.25 for _, r in log if r.ok)
    assert est.recoveries == 0 and est.divergences == 0
    assert np.linalg.norm(est.latest()[1]) < 2.0      # V1_01 flies below 0.7 m/s


def test_significance_gate_applies_only_distinct_scales():
    """``ba_min_significance``: accepted batches whose scale is within that many sigmas of the
    smoother's are not applied; a batch beyond it still is."""
    est = _v101_refined(ba_min_significance=1e6)
    ok = [r for _, r in est.refiner.log if r.ok]
    assert ok and est.refiner.applied == 0
    k = min(abs(np.log(r.scale)) / r.scale_sigma for r in ok)
    est = _v101_refined(ba_min_significance=0.5 * k)
    assert est.refiner.applied >= 1


def _bad_history():
    poses, vel, pims, bias = _swaying_history()
    sim = Similarity(0.95, gtsam.Rot3.Rx(np.radians(1.0)), poses[0].compose(T_B_C).translation(),
                     T_B_C.translation())
    return _history([sim.pose(T) for T in poses], [sim.velocity(v) for v in vel], pims, bias,
                    np.random.default_rng(3))


def _args(h: viba.History) -> tuple:
    return (h, T_B_C, 1.0 / FX, RobustKernel("huber", 3.0), 6.0 / FX, np.r_[np.full(3, 0.2), np.full(3, 0.01)],
            RefineConfig(enabled=True))


def test_worker_gives_the_in_process_result_when_due():
    """The BA in the worker process: nothing before its due time, then exactly the result of
    ``viba.solve`` in this process (pickled history and preintegrations)."""
    from vio.backend.viba_worker import BatchWorker
    h = _bad_history()
    w = BatchWorker()
    try:
        assert w.submit(1_000, _args(h), "a")
        assert w.due(999) == [] and w.pending()
        [(tag, (res, dt))] = w.due(1_000)
    finally:
        w.close()
    ref = viba.solve(*_args(h))
    assert tag == "a" and res.ok and dt > 0 and not w.pending()
    assert res.scale == ref.scale and res.scale_sigma == ref.scale_sigma


def test_dead_worker_is_a_refusal_not_an_error(caplog):
    from vio.backend.viba_worker import BatchWorker
    w = BatchWorker()
    w.start()
    w._proc.kill()
    w._proc.wait()
    w.submit(0, _args(_bad_history()), "a")
    out = w.due(0)
    assert w.failed and all(not r.ok for _, (r, _) in out)
    assert "worker stopped" in caplog.text
    assert not w.submit(0, (), "b")        # the caller falls back to solving in process
