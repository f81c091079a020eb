"""Scale and gravity refinement (vio.backend.scale_refine) and its application to the
estimator state (vio.backend.regauge)."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from tests.conftest import shared
from vio.backend import graph
from vio.backend.regauge import Similarity, apply_similarity
from vio.backend.scale_refine import RefineConfig, interval, solve
from vio.imu import ImuNoiseConfig, combined_params, integrate


def _gt_history(seconds: float, start_s: float = 20.0, step_s: float = 0.2):
    """Real MH_05 IMU and ground truth: keyframe poses every ``step_s`` over ``seconds``
    and the intervals' preintegrations at the ground-truth biases."""
    from vio.io.euroc import load_euroc
    data = load_euroc(shared("euroc_imu_gt", "MH_05_difficult"))
    gt, imu = data.groundtruth, data.imu
    params = combined_params(data.imu_calib, ImuNoiseConfig())
    t0 = gt.t_ns[0] + int(start_s * 1e9)
    ts = t0 + np.arange(int(round(seconds / step_s)) + 1) * int(step_s * 1e9)
    rows = np.searchsorted(gt.t_ns, ts)
    ts = gt.t_ns[rows]
    poses = [gt.pose(int(r)) for r in rows]
    vel = gt.v_w[rows]
    gravity = np.asarray(params.n_gravity, float)
    ivs = []
    for n in range(len(ts) - 1):
        r = int(rows[n])
        pim = gtsam.PreintegratedCombinedMeasurements(
            params, gtsam.imuBias.ConstantBias(gt.ba[r], gt.bg[r]))
        m = (imu.t_ns >= ts[n]) & (imu.t_ns <= ts[n + 1])
        integrate(pim, dataclasses.replace(imu, t_ns=imu.t_ns[m], gyro=imu.gyro[m], accel=imu.accel[m]))
        ivs.append(interval(n, n + 1, pim, gravity))
    return poses, vel, ivs, gravity, data.cam0.calib.T_b_c


def _similar(poses, s: float, R: gtsam.Rot3, t_bc: np.ndarray):
    """Poses of a world scaled by ``s`` and rotated by ``R`` (a wrong scale and tilt)."""
    sim = Similarity(s, R, poses[0].translation(), t_bc)
    return [sim.pose(T) for T in poses]


def test_recovers_scale_and_gravity_from_real_imu():
    poses, vel, ivs, gravity, T_b_c = _gt_history(15.0)
    t_bc = T_b_c.translation()
    tilt = gtsam.Rot3.Rx(np.radians(1.5))
    bad = _similar(poses, 0.95, tilt, t_bc)
    res = solve(bad, vel * 0.95, ivs, T_b_c, gravity, RefineConfig())
    assert res.ok, res.reason
    assert res.scale == pytest.approx(1 / 0.95, rel=0.01)
    assert res.scale_sigma < 0.01
    assert res.gravity_change_deg == pytest.approx(1.5, abs=0.3)
    fixed = _similar(bad, res.scale, res.R_corr, t_bc)
    err = [np.linalg.norm(a.translation() - b.translation()) for a, b in zip(fixed, poses)]
    assert max(err) < 0.02 * max(np.linalg.norm(p.translation() - poses[0].translation()) for p in poses)


def test_refuses_a_poorly_determined_scale():
    """Two seconds of history: the scale's sigma exceeds the bound and nothing is applied."""
    poses, vel, ivs, gravity, T_b_c = _gt_history(2.0, step_s=0.1)
    res = solve(_similar(poses, 0.9, gtsam.Rot3(), T_b_c.translation()), vel, ivs, T_b_c, gravity,
                RefineConfig())
    assert not res.ok
    assert "poorly determined" in res.reason
    assert res.scale_sigma > RefineConfig().max_scale_sigma


def test_refuses_too_few_intervals():
    poses, vel, ivs, gravity, T_b_c = _gt_history(1.0)
    res = solve(poses, vel, ivs, T_b_c, gravity, RefineConfig())
    assert not res.ok and "intervals" in res.reason


def _pipeline(n_frames: int, cfg=None):
    from vio.io.euroc import load_euroc
    from vio.pipeline import Pipeline
    from vio.run import default_config
    from vio.sync import packets
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    cfg = cfg or default_config("features")
    pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg)
    it = packets(data.imu, data.cam0.t_ns, cfg.td_s, data.features)
    for _ in range(n_frames):
        pipe.process(next(it))
    return pipe, it


def _n_marginal(est) -> int:
    fg = est.smoother.getFactors()
    return sum(isinstance(fg.at(i), gtsam.LinearContainerFactor) for i in range(fg.size()))


def _converged(est) -> gtsam.Values:
    for _ in range(5):
        est.smoother.update()
    return est.smoother.calculateEstimate()


def test_identity_rebuild_keeps_the_state():
    """Rebuilding the smoother from its own factors (marginal factors re-anchored at its
    linearization point, the keys iSAM2 held fixed kept fixed: ``vio.backend.smoother``)
    and iterating both to convergence: the keyframes agree to rounding. (Before the fixed
    keys were carried over, 3 mm apart, 3.4 mm at the world points' own relinearization
    threshold.)"""
    ref = _converged(_pipeline(160)[0].est)   # ~8 s of V1_01: flying, marginal factors present
    pipe, it = _pipeline(160)
    est = pipe.est
    assert _n_marginal(est) > 0
    apply_similarity(est, Similarity(1.0, gtsam.Rot3(), np.zeros(3), est.extrinsic().translation()))
    got = _converged(est)
    for k in est.kf_t:
        d = ref.atPose3(graph.X(k)).translation() - got.atPose3(graph.X(k)).translation()
        assert np.linalg.norm(d) < 1e-9
    for tr in est.lm.tracks.values():       # remapped factor indices point at live factors
        for i in tr.factor_indices:
            assert est.smoother.getFactors().at(i) is not None
    for _ in range(40):                     # two more seconds: no failure, no restart
        pipe.process(next(it))
    assert est.recoveries == 0 and est.divergences == 0


@pytest.mark.parametrize("reanchor", ["anchor", "point"])
def test_apply_similarity_moves_the_whole_state(reanchor):
    """A 10% scale and 1-degree tilt: landmarks' inverse depths shrink by the scale (world
    points move away from the pivot by it) and the window's extent about the pivot grows by
    it (the IMU factors then pull a little back)."""
    from vio.run import default_config
    cfg = default_config("features")
    vision = dataclasses.replace(cfg.backend.vision, reanchor=reanchor)
    pipe, it = _pipeline(200, dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, vision=vision)))
    est = pipe.est
    before = gtsam.Values(est.values)
    T0 = est.latest()[0]
    sim = Similarity(1.1, gtsam.Rot3.Ry(np.radians(1.0)), T0.translation(), est.extrinsic().translation())
    apply_similarity(est, sim)
    after = est.values
    ks = sorted(est.kf_t)
    ext = [np.linalg.norm(v.atPose3(graph.X(ks[0])).translation() - v.atPose3(graph.X(ks[-1])).translation())
           for v in (before, after)]
    assert 1.04 < ext[1] / ext[0] < 1.11     # anchor 1.05+, world points 1.046 (their priors and
    # marginals carry the old scale too)
    if reanchor == "anchor":
        ids = [tr.key for tr in est.lm.tracks.values() if tr.key is not None and before.exists(tr.key)]
        assert ids
        ratio = np.median([after.atVector(k)[0] / before.atVector(k)[0] for k in ids])
        assert ratio == pytest.approx(ext[0] / ext[1], rel=0.01)   # the depths follow the window
    else:
        keys = [pt.key for pt in est.lm.points.tracks.values() if before.exists(pt.key)]
        assert keys
        c = T0.translation()
        ratio = np.median([np.linalg.norm(after.atVector(k) - c) / np.linalg.norm(before.atVector(k) - c)
                           for k in keys])
        assert ratio == pytest.approx(ext[1] / ext[0], rel=0.03)    # the points follow the window
    for _ in range(20):
        pipe.process(next(it))
    assert est.recoveries == 0


def test_refinement_is_scheduled_and_logged_on_real_v101():
    """The refiner attempts at ``first_s`` after the start and records each outcome; with
    an impossible bound every attempt is refused and the state is left alone."""
    from vio.run import default_config
    cfg = default_config("features")
    b = cfg.backend
    ref = dataclasses.replace(b.refine, enabled=True, method="inertial", first_s=3.0, every_s=10.0,
                              max_scale_sigma=1e-6)
    cfg = dataclasses.replace(cfg, backend=dataclasses.replace(b, refine=ref))
    pipe, _ = _pipeline(160, cfg)
    log = pipe.est.refiner.log
    assert log and log[0][0] >= 3.0
    assert not any(r.ok for _, r in log)
    assert any("poorly determined" in r.reason for _, r in log)
    assert pipe.est.refiner.applied == 0


def test_scale_held_recovers_a_large_tilt_over_one_second():
    """The gap re-alignment's use (``vio.backend.realign``): one second of real MH_05 IMU,
    the world tilted by 7 degrees, the scale held at 1 by its prior."""
    poses, vel, ivs, gravity, T_b_c = _gt_history(1.0, start_s=25.0, step_s=0.15)
    t_bc = T_b_c.translation()
    bad = _similar(poses, 1.0, gtsam.Rot3.Ry(np.radians(7.0)), t_bc)
    cfg = RefineConfig(min_intervals=2, max_scale_sigma=np.inf, max_gravity_change_deg=90.0,
                       max_gravity_sigma_deg=1.0, accel_bias_sigma=0.05, pos_sigma_m=0.01,
                       scale_prior_sigma=1e-4)
    res = solve(bad, vel, ivs, T_b_c, gravity, cfg)
    assert res.ok, res.reason
    assert abs(res.scale - 1.0) < 1e-3
    assert res.gravity_change_deg == pytest.approx(7.0, abs=3 * res.gravity_sigma_deg)
    fixed = _similar(bad, 1.0, res.R_corr, t_bc)
    err = np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(fixed[-1].rotation().between(poses[-1].rotation()))))
    assert err < 1.0       # yaw is unobservable but the tilt is what was wrong


@pytest.mark.parametrize("s", [1.0, 1.04])
def test_marginal_follows_the_similarity(s):
    """A marginal factor moved into the transformed world (``regauge._marginal``) gives at
    ``sim(x)`` the error the old one gave at ``x``, to first order in the step from its
    linearization point (a pose, a velocity, a world point and an inverse depth; a 9-degree
    tilt, with and without a scale). Left in the old tangents, its change differs by ~10%."""
    from vio.backend.regauge import _marginal
    rng = np.random.default_rng(5)
    keys = [graph.X(3), graph.V(3), gtsam.Symbol("p", 7).key(), gtsam.Symbol("l", 2).key()]
    lin = gtsam.Values()
    lin.insert(keys[0], gtsam.Pose3(gtsam.Rot3.Ypr(0.4, -0.1, 0.2), np.array([1.0, -2.0, 0.5])))
    lin.insert(keys[1], np.array([0.3, 0.1, -0.2]))
    lin.insert(keys[2], np.array([4.0, 1.0, 2.0]))
    lin.insert(keys[3], np.array([0.25]))
    n = 6 + 3 + 3 + 1
    A, b = rng.normal(size=(n + 2, n)), rng.normal(size=n + 2)
    blocks = np.split(A, np.cumsum([6, 3, 3]), axis=1)

    def old_err(_, v, H):
        if H is not None:
            for i, Bk in enumerate(blocks):
                H[i] = Bk
        return -b
    jf = gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n + 2), keys, old_err).linearize(lin)
    old = gtsam.LinearContainerFactor(jf, lin)
    sim = Similarity(s, gtsam.Rot3.Rx(np.radians(9.0)), np.array([0.5, 0.5, 0.0]),
                     np.array([-0.02, 0.06, 0.01]), shift=np.array([0.1, 0.0, -0.2]))
    new = _marginal(old, sim, lin)
    for scale in (1e-3, 1e-4):
        x = gtsam.Values()
        x.insert(keys[0], lin.atPose3(keys[0]).retract(scale * rng.normal(size=6)))
        for k in keys[1:]:
            x.insert(k, lin.atVector(k) + scale * rng.normal(size=lin.atVector(k).size))
        d0 = old.error(x) - old.error(lin)         # first order in the step
        d1 = new.error(sim.values(x)) - new.error(sim.values(lin))
        assert d1 == pytest.approx(d0, rel=30 * scale), (scale, d0, d1)
