"""vio.sim.flight: images rendered along a real flight next to its real IMU.

The written IMU rows are the source's verbatim; the written ground truth is the
IMU-consistent trajectory moved into the room; and the rendered images move as that
ground truth says: KLT correspondences between two frames satisfy the epipolar
constraint of the written poses and the written camera extrinsics to a fraction of a
pixel (a wrong offset sign, extrinsic or exposure time would put them pixels off).
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest
import yaml

from conftest import shared
from vio.io.euroc import load_euroc
from vio.sim.config import SimConfig
from vio.frontend.camera import Camera
from vio.sim.flight import flight_room, render_flight
from vio.sim.optics import FlightOptics
from vio.sim.tracks_config import TrackGenConfig
from vio.trajectory import interpolate_poses


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    src = shared("euroc_imu_gt", "V1_02_medium")
    out = tmp_path_factory.mktemp("flight")
    tcfg = TrackGenConfig(start_s=20.0, duration_s=2.0, td_s=0.01)
    scfg = SimConfig(stereo=True, texels_per_m=64.0, image_noise_sigma=0.5)
    res = render_flight(src, out, tcfg, scfg)
    return src, res, tcfg


@pytest.fixture(scope="module")
def lens_flight(tmp_path_factory):
    """The source's own (distorted, k1 = -0.28) cameras, 2-ms motion blur."""
    src = shared("euroc_imu_gt", "V1_02_medium")
    out = tmp_path_factory.mktemp("lens_flight")
    tcfg = TrackGenConfig(start_s=20.0, duration_s=0.5, td_s=-0.005)
    scfg = SimConfig(stereo=True, texels_per_m=64.0, image_noise_sigma=0.5)
    res = render_flight(src, out, tcfg, scfg, FlightOptics(distortion=True, blur_s=0.002, blur_samples=3))
    return src, res, tcfg


def _rows(path):
    return [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def test_imu_rows_are_the_source_rows(flight):
    src, res, _ = flight
    written = _rows(res.mav0 / "imu0" / "data.csv")
    source = _rows(src / "mav0" / "imu0" / "data.csv")
    i = source.index(written[0])
    assert written == source[i:i + len(written)]
    assert len(written) == res.n_imu and len(written) > 200


def test_room_holds_the_flight_and_the_truth_is_shifted_into_it(flight):
    _, res, _ = flight
    truth = yaml.safe_load(res.truth_path.read_text())
    data = load_euroc(res.out_dir)
    p = data.groundtruth.p_w
    L = np.asarray(truth["scene"]["room_size"])
    assert np.all(p.min(axis=0) > 0.5) and np.all(p.max(axis=0) < L - 0.5)
    size, offset = flight_room(p - np.asarray(truth["offset_w"]))
    np.testing.assert_allclose(size, L, atol=1e-9)
    np.testing.assert_allclose(offset, truth["offset_w"], atol=1e-9)


def _sampson_px(x0: np.ndarray, x1: np.ndarray, T_c0_c1: gtsam.Pose3, f: float) -> np.ndarray:
    """Sampson distances (pixels at focal ``f``) of normalized matches ``x0``, ``x1`` (N, 2)
    under the relative pose ``T_c0_c1`` (camera 1 in camera 0)."""
    T = T_c0_c1.inverse()                           # c0 -> c1
    R, t = T.rotation().matrix(), T.translation()
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    a = np.column_stack([x0, np.ones(len(x0))])
    b = np.column_stack([x1, np.ones(len(x1))])
    Ea, Etb = a @ E.T, b @ E
    num = np.einsum("ij,ij->i", b, Ea)
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return f * np.abs(num) / np.sqrt(den)


@pytest.mark.parametrize("which", ["flight", "lens_flight"])
@pytest.mark.parametrize("pair", [("cam0", 0, "cam0", 3), ("cam0", 5, "cam1", 5)])
def test_images_move_as_the_written_poses_say(which, pair, request):
    _, res, tcfg = request.getfixturevalue(which)
    data = load_euroc(res.out_dir)
    (ca, ja, cb, jb) = pair
    cams = {"cam0": data.cam0.calib, "cam1": data.cam1.calib}
    stamps = data.cam0.t_ns
    ta, tb = int(stamps[ja]), int(stamps[jb])
    ima = cv2.imread(str(res.mav0 / ca / "data" / f"{ta}.png"), 0)
    imb = cv2.imread(str(res.mav0 / cb / "data" / f"{tb}.png"), 0)
    pa = cv2.goodFeaturesToTrack(ima, 300, 0.01, 12)
    pb, st, _ = cv2.calcOpticalFlowPyrLK(ima, imb, pa, None, winSize=(21, 21), maxLevel=3)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(imb, ima, pb, None, winSize=(21, 21), maxLevel=3)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - pa, axis=2).ravel() < 0.3)
    assert ok.sum() > 80
    gt = data.groundtruth
    td = int(round(tcfg.td_s * 1e9))
    T_w_b = [interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, np.array([t + td])) for t in (ta, tb)]
    T_w_c = [gtsam.Pose3(gtsam.Rot3(R[0]), p[0]).compose(cams[c].T_b_c) for (p, R), c in zip(T_w_b, (ca, cb))]
    K = [cams[c].intrinsics for c in (ca, cb)]
    x = [Camera(cams[c]).undistort_px(q.reshape(-1, 2)[ok]) for q, c in zip((pa, pb), (ca, cb))]
    err = _sampson_px(x[0], x[1], T_w_c[0].between(T_w_c[1]), K[0][0])
    assert np.median(err) < 0.15, np.median(err)
    # the same matches against the poses 20 ms later: the check can tell the timing
    late = [interpolate_poses(gt.t_ns, gt.p_w, gt.q_wxyz, np.array([t + td + 20_000_000])) for t in (ta, tb)]
    T_late = [gtsam.Pose3(gtsam.Rot3(R[0]), p[0]).compose(cams[c].T_b_c) for (p, R), c in zip(late, (ca, cb))]
    if ca == cb:
        assert np.median(_sampson_px(x[0], x[1], T_late[0].between(T_late[1]), K[0][0])) > 3 * np.median(err)


@pytest.mark.slow
def test_stereo_runs_on_the_rendered_flight_from_its_first_frame(flight):
    """The pipeline on the real IMU with the rendered pair (td 10 ms found online): a pose
    for every frame from the first, centimetre-level ATE over the 2 s."""
    from vio.evaluation import evaluate
    from vio.run import load_config, run_dataset
    _, res, _ = flight
    data = load_euroc(res.out_dir)
    run = run_dataset(data, load_config(None, mode="stereo"), mode="stereo")
    assert len(run.outputs) == run.frames_in == len(data.cam0.t_ns) and run.restarts == 0
    e = evaluate(*run.arrays(), data.groundtruth)
    assert e.ate_rmse < 0.01, e.ate_rmse


def test_lens_flight_writes_the_source_calibration(lens_flight):
    src, res, _ = lens_flight
    data = load_euroc(res.out_dir)
    from vio.io.calib import load_camera
    for name, calib in (("cam0", data.cam0.calib), ("cam1", data.cam1.calib)):
        own = load_camera(src / "mav0" / name / "sensor.yaml", name)
        assert calib.distortion_model == own.distortion_model == "radial-tangential"
        np.testing.assert_allclose(calib.distortion, own.distortion, rtol=1e-9)
        np.testing.assert_allclose(calib.intrinsics, own.intrinsics, rtol=1e-9)


def test_rolling_shutter_flight_through_the_lens(tmp_path):
    """``--line-time`` with ``--distort``: the cameras are written with their line time,
    the truth names it, sensor row 0 is the global-shutter image's row 0 (both exposed at
    stamp + td) while the last rows, exposed 14 ms later, are not."""
    src = shared("euroc_imu_gt", "V1_02_medium")
    tcfg = TrackGenConfig(start_s=25.0, duration_s=0.1, td_s=0.004)
    optics = FlightOptics(distortion=True)
    imgs = {}
    for lt in (0.0, 3e-5):
        scfg = SimConfig(stereo=False, texels_per_m=64.0, image_noise_sigma=0.0, line_time_s=lt)
        res = render_flight(src, tmp_path / f"lt{lt}", tcfg, scfg, optics)
        data = load_euroc(res.out_dir)
        assert data.cam0.calib.line_time_s == lt
        assert yaml.safe_load(res.truth_path.read_text())["line_time_s"] == lt
        t = int(data.cam0.t_ns[1])
        imgs[lt] = cv2.imread(str(res.mav0 / "cam0" / "data" / f"{t}.png"), 0).astype(float)
    gs, rs = imgs[0.0], imgs[3e-5]
    top, bottom = np.abs(rs[0] - gs[0]).mean(), np.abs(rs[-40:] - gs[-40:]).mean()   # measured 0.08, 6.9
    assert top < 0.5 and bottom > 3.0, (top, bottom)
