"""The backend's fast paths give the same numbers as the reference code they replace."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors import landmark, stereo
from factors.bearing_model import tangent_basis
from factors.projection import anchor_jacobian_batch, project_batch
from vio.backend import graph
from vio.backend.config import BackendConfig
from vio.backend.landmarks import Obs, Track


def _pose(rng: np.random.Generator, scale: float = 0.2) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, scale, 3)), rng.normal(0, scale, 3))


@pytest.mark.parametrize("model", ["pinhole", "sphere"])
def test_anchor_jacobian_batch_is_project_batch_uvi(model):
    rng = np.random.default_rng(3)
    Ti, Tc = _pose(rng).matrix(), _pose(rng, 0.05).matrix()
    Tjs = np.array([_pose(rng).matrix() for _ in range(6)])
    flip = gtsam.Pose3(gtsam.Rot3.Ry(np.pi), np.zeros(3))     # camera j: camera i turned round
    Tjs[2] = (gtsam.Pose3(Ti) * gtsam.Pose3(Tc) * flip * gtsam.Pose3(Tc).inverse()).matrix()
    uv_i, uv_j = rng.normal(0, 0.3, 2), rng.normal(0, 0.3, (6, 2))
    B = tangent_basis(uv_j)
    ref = project_batch(Ti, Tjs, Tc, 0.4, uv_i, uv_j, model, B)
    got = anchor_jacobian_batch(Ti, Tjs, Tc, 0.4, uv_i, uv_j, model, B)
    assert np.array_equal(got, ref.uvi)
    if model == "pinhole":
        assert not ref.valid.all() and not got[~ref.valid].any()


@pytest.mark.parametrize("use_td", [False, True])
def test_anchor_jacobians_of_the_factors_match_their_projection(use_td):
    rng = np.random.default_rng(5)
    poses = [_pose(rng) for _ in range(4)]
    keys = [gtsam.symbol("x", i) for i in range(4)]
    lm = landmark.make_track(keys[0], rng.normal(0, 0.2, 2), keys[1:], rng.normal(0, 0.2, (3, 2)),
                             anchor_vel=rng.normal(0, 1, 2), vel=rng.normal(0, 1, (3, 2)),
                             anchor_offset=0.001, offset=rng.normal(0, 0.002, 3))
    args = [np.array([0.3]), _pose(rng, 0.05), *poses] + ([np.array([0.004])] if use_td else [])
    ref = landmark._project(args, lm, "pinhole", use_td).uvi.reshape(-1, 2)
    assert np.array_equal(landmark.landmark_anchor_jacobian(args, lm, "pinhole", use_td), ref)
    C = gtsam.Pose3(gtsam.Rot3(), np.array([0.11, 0.0, 0.0]))
    st = stereo.make_stereo_track(keys[0], rng.normal(0, 0.2, 2), [keys[1], keys[2], keys[0], keys[2]],
                                  rng.normal(0, 0.2, (4, 2)), stereo.stereo_rig(C),
                                  anchor_vel=rng.normal(0, 1, 2), vel=rng.normal(0, 1, (4, 2)),
                                  right=[False, False, True, True])
    args = [np.array([0.3]), _pose(rng, 0.05), *poses[:3]] + ([np.array([0.004])] if use_td else [])
    ref = stereo._project(args, st, "sphere", use_td).uvi.reshape(-1, 2)
    assert np.array_equal(stereo.stereo_anchor_jacobian(args, st, "sphere", use_td), ref)


def test_stereo_rig_equals_the_pose():
    C = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.01, 0.02, -0.01])), np.array([0.11, 0.001, 0.0]))
    a = stereo.make_stereo_track(1, np.zeros(2), [1, 2], np.full((2, 2), 0.1), C)
    b = stereo.make_stereo_track(1, np.zeros(2), [1, 2], np.full((2, 2), 0.1), stereo.stereo_rig(C))
    assert np.array_equal(a.C, b.C) and np.array_equal(a.ad_inv, b.ad_inv)


def test_worst_reprojection_errors_match_the_per_track_check():
    rng = np.random.default_rng(11)
    vals = gtsam.Values()
    frames = list(range(5))
    for f in frames:
        vals.insert(graph.X(f), gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.05, 3)),
                                            np.array([0.1 * f, 0.0, 0.0])))
    vals.insert(graph.EXTRINSIC, _pose(rng, 0.02))
    vals.insert(graph.TD, np.array([0.003]))
    tracks = []
    for i, fs in enumerate([[0, 1, 2], [1, 3, 4], [2], [0, 1, 2, 3, 4], [3, 4]]):
        tr = Track(i, {f: Obs(rng.normal(0, 0.2, 2), rng.normal(0, 1, 2), 100.0 * f) for f in fs},
                   graph.L(i), fs[0])
        vals.insert(tr.key, np.array([0.2 + 0.1 * i]))
        if i % 2 == 0 and len(fs) > 1:   # a factor has set the td shifts (and shift_rows) of these
            graph.build_landmark_factor(tr, fs, BackendConfig(), 1e-3, 1e-5)
            assert tr.shift_rows is not None and tr.shift_rows[0] == tuple(fs)
        tracks.append(tr)
    tracks[3].obs[5] = Obs(rng.normal(0, 0.2, 2), rng.normal(0, 1, 2), 500.0)   # observed since its factor:
    vals.insert(graph.X(5), gtsam.Pose3(gtsam.Rot3(), np.array([0.5, 0.1, 0.0])))   # shift_rows stale
    frames.append(5)
    table = graph.camera_table(vals, frames)
    got = graph.worst_reprojection_errors(tracks, vals, table)
    for tr, g in zip(tracks, got):
        e = graph.reprojection_errors(tr, tr.frames(), vals, table)
        assert g == (e.max() if e.size else 0.0)


def test_image_velocity_rows_match_the_broadcast_formula():
    rng = np.random.default_rng(2)
    uv, z, w, v = rng.normal(size=(7, 2)), rng.uniform(1, 5, 7), rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    rows = graph.image_velocity(uv, z, w, v)            # compiled path
    single = np.array([graph.image_velocity(uv[i], z[i], w[i], v[i]) for i in range(7)])
    assert np.array_equal(rows, single)


def _predicted_reference(idx, uv, meas, has_r, ruv, rmeas, R, t, w, v, lam, R10, t01, zmin, gate):
    """The numpy formulation the compiled vio.backend.td_velocity kernel replaced."""
    def gated(uv, z, w_c, v_c, meas):
        out = np.zeros_like(meas)
        ok = z > zmin
        if ok.any():
            p = graph.image_velocity(uv[ok], z[ok], w_c[ok], v_c[ok])
            good = np.linalg.norm(p - meas[ok], axis=1) < gate
            out[np.flatnonzero(ok)[good]] = p[good]
        return out
    a = np.array([uv[0, 0], uv[0, 1], 1.0]) / lam
    p_w = R[idx[0]] @ a + t[idx[0]]
    p_c = np.einsum("nji,nj->ni", R[idx], p_w - t[idx])
    vel = gated(uv, p_c[:, 2], w[idx], v[idx], meas)
    rvel = np.zeros_like(vel)
    z1 = (p_c[has_r] - t01) @ R10[2]
    w1 = w[idx][has_r] @ R10.T
    v1 = (v[idx][has_r] + np.cross(w[idx][has_r], t01)) @ R10.T
    rvel[has_r] = gated(ruv[has_r], z1, w1, v1, rmeas[has_r])
    return vel, rvel


def test_predicted_velocities_kernel_matches_numpy():
    from vio.backend.td_velocity import predicted_velocities
    rng = np.random.default_rng(2)
    K, n = 6, 5
    R = np.array([gtsam.Rot3.Expmap(rng.normal(0, 0.1, 3)).matrix() for _ in range(K)])
    t = rng.normal(0, 0.2, (K, 3))
    w, v = rng.normal(0, 0.5, (K, 3)), rng.normal(0, 0.5, (K, 3))
    idx = np.array([1, 2, 3, 4, 5], np.int64)
    uv, ruv = rng.normal(0, 0.2, (n, 2)), rng.normal(0, 0.2, (n, 2))
    C = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.01, 0.0, 0.02])), np.array([0.11, 0.0, 0.0]))
    R10, t01 = C.rotation().matrix().T.copy(), C.translation()
    for lam, gate in [(0.5, 5.0), (0.5, 0.3), (-0.5, 5.0), (20.0, 5.0)]:
        meas = rng.normal(0, 0.3, (n, 2))
        rmeas = rng.normal(0, 0.3, (n, 2))
        has_r = np.array([True, False, True, True, False])
        ref = _predicted_reference(idx, uv, meas, has_r, ruv, rmeas, R, t, w, v, lam, R10, t01, 0.1, gate)
        vel, rvel = np.empty((n, 2)), np.empty((n, 2))
        predicted_velocities(idx, uv, meas, has_r, ruv, rmeas, R, t, w, v, lam, R10, t01, 0.1, gate,
                             vel, rvel)
        assert np.allclose(vel, ref[0], rtol=1e-12, atol=1e-14)
        assert np.allclose(rvel, ref[1], rtol=1e-12, atol=1e-14)


def _stereo_case(rng, frames, stereo_track, key=9):
    """A track over ``frames`` (cam1 matches except in frame 6 when ``stereo_track``)."""
    obs = {}
    for f in frames:
        right = stereo_track and f != 6
        obs[f] = Obs(rng.normal(0, 0.2, 2), rng.normal(0, 0.3, 2), 50.0 * f,
                     rng.normal(0, 0.2, 2) if right else None, rng.normal(0, 0.3, 2) if right else None,
                     float(rng.normal(0, 0.001)), 50.0 * f + 7.0 if right else float("nan"))
    return Track(key, obs, graph.L(key), frames[0])


def _state(rng, frames, keys):
    C = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.01, 0.0, -0.02])), np.array([0.11, 0.0, 0.0]))
    poses = {f: _pose(rng) for f in frames}
    vals = gtsam.Values()
    for f, P in poses.items():
        vals.insert(graph.X(f), P)
    vals.insert(graph.EXTRINSIC, _pose(rng, 0.05))
    vals.insert(graph.TD, np.array([0.003]))
    for key in keys:
        vals.insert(key, np.array([0.35]))
    return C, poses, vals


def _same_linearization(ref, got, vals):
    assert list(got.keys()) == list(ref.keys())
    a, b = ref.linearize(vals), got.linearize(vals)
    assert np.array_equal(a.jacobian()[0], b.jacobian()[0]) and np.array_equal(a.jacobian()[1], b.jacobian()[1])
    assert ref.error(vals) == got.error(vals)


@pytest.mark.parametrize("stereo_track,frames", [(False, [3, 4, 6, 7]), (True, [3, 4, 6, 7]), (True, [3])])
def test_track_factor_equals_the_stereo_and_landmark_builders(stereo_track, frames):
    """vio.backend.track_factor on track_arrays rows (measured velocities) linearizes
    exactly as graph.build_stereo_factor / build_landmark_factor (td, Huber, anchor
    whitening on); also a stereo track seen only in its anchor keyframe."""
    from vio.backend.track_arrays import track_rows
    from vio.backend.track_factor import member_factor, track_member
    rng = np.random.default_rng(4)
    tr = _stereo_case(rng, frames, stereo_track)
    C, poses, vals = _state(rng, frames, [tr.key])
    rig = graph.stereo_rig(C)
    at = graph.LinPoint(0.4, _pose(rng, 0.05), poses, 0.002)
    cfg = BackendConfig()
    ref = (graph.build_stereo_factor(tr, rig, cfg, 1e-3, 1e-5, None, None, at, frames) if stereo_track
           else graph.build_landmark_factor(tr, frames, cfg, 1e-3, 1e-5, None, at))
    shift_ref = {f: (v.copy(), o) for f, (v, o) in tr.td_shift.items()}
    vmax = cfg.vision.td_velocity_max
    rows = track_rows([(tr, frames, 0.4)], True, False, None, None, 0.1, 1.0, vmax, 1e-5)[0]
    got = member_factor(track_member(tr, frames, rows, rig, cfg, 1e-3, at))
    _same_linearization(ref, got, vals)
    # a cam1 observation is timed by cam1's own row (rolling shutter), not cam0's
    want = [(tr.obs[f].right_row * 1e-5 - tr.obs[f].td_obs) for f in frames if tr.obs[f].right_uv is not None]
    np.testing.assert_allclose(rows.offset[rows.right], want, rtol=0, atol=1e-15)
    assert all(np.array_equal(shift_ref[f][0], tr.td_shift[f][0]) and shift_ref[f][1] == tr.td_shift[f][1]
               for f in frames)


def test_track_rows_of_many_tracks_equal_the_per_track_predicted_factors():
    """track_rows over several tracks at once, td velocities predicted from a motion
    table (a track at lam <= 0 falls back to the measured ones; fast ones are capped),
    gives each track the factor graph.build_stereo_factor builds from that track's own
    td_velocity.predicted_velocities."""
    from vio.backend.td_velocity import predicted_velocities, rig_c1
    from vio.backend.track_arrays import track_rows
    from vio.backend.track_factor import member_factor, track_member
    rng = np.random.default_rng(8)
    frames = [2, 3, 4, 6, 7]
    cases = [([3, 4, 6], True, 0.4), ([2, 3], False, 0.8), ([4, 6, 7], True, -0.2), ([6, 7, 2], True, 0.3)]
    tracks = [_stereo_case(rng, fr, st, key=20 + i) for i, (fr, st, _) in enumerate(cases)]
    tracks[0].obs[4] = Obs(tracks[0].obs[4].uv, np.array([40.0, 0.0]), 10.0)   # gated: far from its prediction
    tracks[2].obs[6] = Obs(tracks[2].obs[6].uv, np.array([40.0, 0.0]), 10.0)   # measured beyond the cap
    C, poses, vals = _state(rng, frames, [tr.key for tr in tracks])
    rig, R10_t01 = graph.stereo_rig(C), rig_c1(C)
    K = len(frames)
    table = ({f: i for i, f in enumerate(frames)}, np.array([_pose(rng).rotation().matrix() for _ in range(K)]),
             rng.normal(0, 0.5, (K, 3)), rng.normal(0, 0.5, (K, 3)), rng.normal(0, 0.5, (K, 3)))
    cfg = BackendConfig()
    vmax, gate = cfg.vision.td_velocity_max, 3.0
    items = [(tr, fr, lam) for tr, (fr, _, lam) in zip(tracks, cases)]
    rows = track_rows(items, True, True, table, R10_t01, 0.1, gate, vmax, 1e-5)
    for (tr, fr, lam), r in zip(items, rows):
        got = member_factor(track_member(tr, fr, r, rig, cfg, 1e-3))
        shift = dict(tr.td_shift)
        vel = rvel = None
        if lam > 0:
            obs = [tr.obs[f] for f in fr]
            has_r = np.array([o.right_uv is not None for o in obs])
            pick = [lambda o: o.right_uv, lambda o: o.right_velocity]
            ruv, rmeas = (np.array([p(o) if o.right_uv is not None else np.zeros(2) for o in obs]) for p in pick)
            vel, rvel = np.empty((len(fr), 2)), np.empty((len(fr), 2))
            predicted_velocities(np.array([table[0][f] for f in fr], np.int64), np.array([o.uv for o in obs]),
                                 np.array([o.velocity for o in obs]), has_r, ruv, rmeas, *table[1:], lam,
                                 *R10_t01, 0.1, gate, vel, rvel)
        ref = graph.build_stereo_factor(tr, rig, cfg, 1e-3, 1e-5, vel, rvel, None, fr)
        _same_linearization(ref, got, vals)
        assert all(np.array_equal(shift[f][0], tr.td_shift[f][0]) and shift[f][1] == tr.td_shift[f][1] for f in fr)
    assert not rows[0].vel[0].any() and not rows[2].vel[0].any()   # no td term from either
    assert rows[1].vel.any() and rows[3].vel.any()
