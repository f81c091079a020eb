"""Temporal inverse depths of the direct mode's host points (``vio.direct.temporal``): a
keyframe whose right image is covered hosts points placed by an epipolar search in the
previous keyframe, at their true depths, without the static stereo term; a second
keyframe's search rejects a contradicted depth; with the option off nothing is placed."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from cases_photometric import box_scene, render_planes
from factors.photometric import Pinhole
from vio.direct import DirectConfig
from vio.direct.keyframe import StereoRig, build_keyframe
from vio.direct.temporal import agree, host_candidates, widest_baseline
from vio.io.types import CameraCalib

X, A = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.A
W, H = 640, 480
KV = (450.0, 450.0, 319.5, 239.5)
KS = Pinhole(*KV)
# keyframe camera poses in the world (= the host's camera frame; T_b_c = identity)
POSES = {0: gtsam.Pose3(gtsam.Rot3.Expmap([0.01, -0.02, 0.0]), [-0.22, 0.03, -0.02]),
         1: gtsam.Pose3(gtsam.Rot3.Expmap([0.0, -0.01, 0.005]), [-0.11, 0.01, 0.01]),
         2: gtsam.Pose3()}


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(5)
    planes = box_scene(rng)
    T_c1_c0 = gtsam.Pose3(gtsam.Rot3(), [-0.11, 0.0, 0.0])
    cam0 = CameraCalib(gtsam.Pose3(), KV, "radial-tangential", (0.0,) * 4, (W, H))
    cam1 = CameraCalib(T_c1_c0.inverse(), KV, "radial-tangential", (0.0,) * 4, (W, H), name="cam1")
    rig = StereoRig(cam0, cam1)
    imgs, truth = {}, None
    for k, T in POSES.items():
        img, idepth = render_planes(planes, KS, T, W, H)
        imgs[k] = img + rng.normal(0, 1.0, img.shape)
        truth = idepth if k == 2 else truth
    right, _ = render_planes(planes, KS, POSES[2].compose(T_c1_c0.inverse()), W, H)
    covered = np.full((H, W), 12.0)
    values = gtsam.Values()
    for k, T in POSES.items():
        values.insert(X(k), T)
        values.insert(A(k), np.zeros(2))
    return rig, imgs, right + rng.normal(0, 1.0, right.shape), covered, truth, values


def _keyframes(scene, right, cfg):
    rig, imgs, _, covered, _, _ = scene
    return {k: build_keyframe(k, k, imgs[k], right if k == 2 else covered, rig, cfg) for k in imgs}


def test_covered_right_camera_hosts_temporal_points_at_their_depths(scene):
    rig, _, _, covered, truth, values = scene
    cfg = DirectConfig()
    kfs = _keyframes(scene, covered, cfg)
    kd = kfs[2]
    assert len(kd.uv) == 0 and len(kd.points.uv_rest) > 300       # the stereo search placed none
    uv, rho, stereo = host_candidates(kd, kfs, values, rig, cfg)
    assert len(uv) == cfg.points.max_points and not stereo.any()
    true = truth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    rel = np.abs(rho - true) / true
    assert np.median(rel) < 0.01 and np.mean(rel < 0.05) > 0.95
    # every placed candidate joined the keyframe's points (TrackFrame's reference), with a
    # variance that covers its error
    assert len(kd.uv) >= len(uv) and kd.points.ref is None
    t_all = truth[np.round(kd.uv[:, 1]).astype(int), np.round(kd.uv[:, 0]).astype(int)]
    assert np.mean(np.abs(kd.idepth - t_all) <= 3 * np.sqrt(kd.idepth_var)) > 0.9
    # hosted again (after a restart): the same points, still without the stereo term
    uv2, rho2, stereo2 = host_candidates(kd, kfs, values, rig, cfg)
    assert np.array_equal(uv2, uv) and np.array_equal(rho2, rho) and not stereo2.any()
    assert kd.n_stereo == 0 and len(kd.points.uv_rest) == 0
    off = dataclasses.replace(cfg, points=dataclasses.replace(cfg.points, temporal_depth=False))
    kfs = _keyframes(scene, covered, off)
    assert len(host_candidates(kfs[2], kfs, values, rig, off)[0]) == 0


def test_stereo_points_come_first_and_keep_the_stereo_term(scene):
    """With the right image seen, the stereo points fill the host first (flagged for the
    static stereo term); only the remaining slots take temporal ones."""
    rig, _, right, _, truth, values = scene
    cfg = DirectConfig()
    kfs = _keyframes(scene, right, cfg)
    n_stereo = len(kfs[2].uv)
    assert n_stereo > cfg.points.max_points
    uv, _, stereo = host_candidates(kfs[2], kfs, values, rig, cfg)
    assert len(uv) == cfg.points.max_points and stereo.all()
    big = dataclasses.replace(cfg, points=dataclasses.replace(cfg.points, max_points=400))
    uv, rho, stereo = host_candidates(kfs[2], kfs, values, rig, big)
    assert stereo[:n_stereo].all() and not stereo[n_stereo:].any() and len(uv) > n_stereo
    t = uv[n_stereo:]
    true = truth[np.round(t[:, 1]).astype(int), np.round(t[:, 0]).astype(int)]
    assert np.median(np.abs(rho[n_stereo:] - true) / true) < 0.02


def test_a_second_keyframe_rejects_a_contradicted_depth(scene):
    rig, _, _, covered, truth, values = scene
    cfg = DirectConfig()
    kfs = _keyframes(scene, covered, cfg)
    kd = kfs[2]
    uv = kd.points.uv_rest
    true = truth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    var = (0.02 * true) ** 2
    T = POSES[0].between(POSES[2])
    good = agree(kd, kfs[0], uv, true, var, T, 0.0, KS, cfg)
    bad = agree(kd, kfs[0], uv, 1.3 * true, var, T, 0.0, KS, cfg)
    assert good.mean() > 0.9 and bad.mean() < 0.3
    assert widest_baseline(POSES[2], {0: POSES[0], 1: POSES[1]}) == 0
    assert widest_baseline(POSES[2], {}) is None
