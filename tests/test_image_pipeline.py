"""Images -> KLT front end -> backend, on a short rendered stereo sequence."""

from __future__ import annotations

import numpy as np
import pytest

from vio.evaluation import evaluate
from vio.io.euroc import load_euroc
from vio.pipeline import PipelineConfig
from vio.run import resolve_mode, run_dataset


@pytest.fixture(scope="module")
def sim_stereo(tmp_path_factory):
    from vio.sim import simulate
    from vio.sim.config import SimConfig
    root = tmp_path_factory.mktemp("sim_stereo")
    simulate(root, SimConfig(seconds=5.0, seed=2, image_scale=0.5, td_s=0.0))
    return load_euroc(root)


@pytest.mark.slow
def test_stereo_images_end_to_end(sim_stereo):
    """5 s of rendered stereo (starts moving): 1.1 cm ATE measured; bound 3 cm."""
    res = run_dataset(sim_stereo, PipelineConfig(), mode="stereo")
    assert res.recoveries == 0 and len(res.outputs) > 60
    e = evaluate(*res.arrays(), sim_stereo.groundtruth)
    assert e.ate_rmse < 0.03
    # stereo depth puts landmarks in the graph at the first keyframe updates
    kfs = [o for o in res.outputs if o.keyframe]
    assert kfs[1].n_landmarks > 0 or kfs[2].n_landmarks > 0


@pytest.mark.slow
def test_mono_images_end_to_end(sim_stereo):
    """Same sequence, cam0 only: 3.4 cm ATE measured; bound 6 cm."""
    res = run_dataset(sim_stereo, PipelineConfig(), mode="mono")
    e = evaluate(*res.arrays(), sim_stereo.groundtruth)
    assert res.recoveries == 0 and e.ate_rmse < 0.06


def test_mode_resolution_errors(sim_stereo, tmp_path):
    assert resolve_mode(sim_stereo, "auto") == "stereo"
    with pytest.raises(ValueError, match="no cam0/features.csv"):
        resolve_mode(sim_stereo, "features")
    with pytest.raises(ValueError, match="not available"):
        resolve_mode(sim_stereo, "lidar")


def test_image_stage_on_real_static_stereo():
    """Real EuRoC images while the vehicle is still: stereo matches exist and the
    attached right observations lie near the same epipolar geometry."""
    from conftest import shared
    from vio.sync import packets
    from vio.tracking import ImageStage
    d = load_euroc(shared("euroc_V1_01_static_stereo"))
    stage = ImageStage(d.cam0.calib, d.cam1.calib)
    files = list(zip(d.cam0.files[:5], d.cam1.files[:5]))
    n_right = []
    for pkt in packets(d.imu, d.cam0.t_ns[:5], image_files=files):
        fr = stage(pkt).features
        ok = np.isfinite(fr.right_uv).all(axis=1)
        n_right.append(int(ok.sum()))
        # rectification-free sanity: right points are shifted left (positive depth)
        assert np.median(fr.uv[ok, 0] - fr.right_uv[ok, 0]) > 0
    assert min(n_right) > 30


def test_worker_process_front_end_is_identical(sim_stereo):
    """The KLT stage in a worker process (``vio.overlap``) hands the backend exactly
    the packets the in-process stage gives: same ids, same coordinates, bit for bit."""
    from vio.overlap import overlapped
    from vio.io.euroc import image_files
    from vio.sync import packets
    from vio.tracking import ImageStage
    d = sim_stereo
    args = (d.cam0.calib, d.cam1.calib, PipelineConfig().frontend)
    stamps = d.cam0.t_ns[:25]
    files = image_files(d, True, stamps)
    local = ImageStage(*args)
    expected = [local(p) for p in packets(d.imu, stamps, 0.0, image_files=files)]
    got = list(overlapped(ImageStage, args, packets(d.imu, stamps, 0.0, image_files=files), depth=3,
                          nice=19))   # the worker matches stereo in a thread (ImageStage.submit)
    assert [p.index for p in got] == [p.index for p in expected]
    for a, b in zip(got, expected):
        for name in ("ids", "uv", "velocity", "row", "right_uv", "right_velocity"):
            np.testing.assert_array_equal(getattr(a.features, name), getattr(b.features, name))
        assert a.images == ()   # the images stay in the worker


def test_worker_process_drops_unreadable_images_and_reports_bad_ones(sim_stereo, tmp_path):
    """Inside the worker, an image that does not decode marks its packet ``dropped`` (the
    pipeline carries its IMU over, ``Pipeline.process``) and the next frame is tracked
    from the last good one; an image of the wrong size is bad input: the same one-line
    error, after the results of the packets before it (the stereo thread's included)."""
    import cv2
    from vio.overlap import overlapped
    from vio.io.euroc import image_files
    from vio.sync import packets
    from vio.tracking import ImageStage
    d = sim_stereo
    stamps = d.cam0.t_ns[:7]
    files = image_files(d, True, stamps)
    (tmp_path / "gone.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((48, 64), np.uint8))
    files[3] = (tmp_path / "gone.png", files[3][1])
    files[5] = (small, files[5][1])
    it = overlapped(ImageStage, (d.cam0.calib, d.cam1.calib, None),
                    packets(d.imu, stamps, 0.0, image_files=files))
    got = []
    with pytest.raises(ValueError, match=r"small\.png: image is 64x48 but camera \S+ is calibrated for \d+x\d+"):
        for pkt in it:
            got.append(pkt)
    assert [p.index for p in got] == [0, 1, 2, 3, 4]
    assert "gone.png: image missing or unreadable" in got[3].dropped and got[3].features is None
    assert all(len(p.features.ids) and not p.dropped for p in got[:3] + got[4:])
    kept = set(got[2].features.ids.tolist())      # frame 4 tracked on from frame 2
    assert len(kept & set(got[4].features.ids.tolist())) > 0.5 * len(kept)


def test_blank_images_drop_their_frames_and_tracking_goes_on(sim_stereo, tmp_path, caplog):
    """A cam0 image that shows nothing (black, saturated, a covered lens: every pixel
    alike, ``vio.tracking.blank_image``) marks its frame ``dropped`` with the file named,
    as an undecodable one; the frame after is tracked from the last good one (gyro
    prediction), keeping most tracks. A dark but textured image is kept; in the pipeline
    a run of dropped frames gives one warning at its start and one with its length."""
    import cv2
    from vio.io.euroc import image_files, read_image
    from vio.sync import packets
    from vio.tracking import ImageStage, blank_image
    d = sim_stereo
    img = read_image(image_files(d, True, d.cam0.t_ns[:1])[0][0])
    assert not blank_image(img, 4.0) and not blank_image((img // 12).astype(np.uint8), 4.0)
    assert blank_image(np.zeros_like(img), 4.0) and blank_image(np.full_like(img, 255), 4.0)
    assert not blank_image(np.zeros_like(img), 0.0)
    stamps = d.cam0.t_ns[:8]
    files = image_files(d, True, stamps)
    for i, value in ((3, 0), (4, 12), (5, 255)):
        path = tmp_path / f"blank{i}.png"
        cv2.imwrite(str(path), np.full(img.shape, value, np.uint8))
        files[i] = (path, files[i][1])
    stage = ImageStage(d.cam0.calib, d.cam1.calib, None)
    got = [stage(p) for p in packets(d.imu, stamps, 0.0, image_files=files)]
    assert [bool(p.dropped) for p in got] == [False] * 3 + [True] * 3 + [False] * 2
    assert "blank3.png: the image shows nothing" in got[3].dropped and got[3].features is None
    kept = set(got[2].features.ids.tolist())      # frame 6 tracked on from frame 2
    assert len(kept & set(got[6].features.ids.tolist())) > 0.5 * len(kept)
    from vio.pipeline import Pipeline
    from vio.run import default_config
    pipe = Pipeline(d.imu_calib, d.cam0.calib, default_config("stereo"), d.cam1.calib)
    with caplog.at_level("WARNING", logger="vio.pipeline"):
        for p in got:
            pipe.process(p)
    assert pipe.frames_dropped == 3
    msgs = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    assert len(msgs) == 2 and "blank3.png" in msgs[0] and "3 frames in a row dropped" in msgs[1], msgs


def _policy_flags(frames, cfg, fx):
    """``KeyframeConfig``'s decisions over (t_ns, FeatureFrame) pairs, as the pipeline
    makes them (every decision made on its own features)."""
    from vio.keyframes import KeyframePolicy
    pol, out = KeyframePolicy(cfg, fx), []
    for t, fr in frames:
        kf = pol.due(t, fr.ids, fr.uv)
        if kf:
            pol.reset(t, fr.ids, fr.uv)
        out.append(kf)
    return out


def test_keyframe_policy():
    """``vio.keyframes.KeyframePolicy``: the first frame, the parallax, the track count,
    and the interval limits of ``KeyframeConfig``."""
    from vio.backend.config import KeyframeConfig
    from vio.keyframes import KeyframePolicy
    ids = np.arange(20)
    uv = np.zeros((20, 2))
    pol = KeyframePolicy(KeyframeConfig(min_parallax_px=10.0, max_interval_s=0.3, min_interval_s=0.1,
                                        min_tracked=12), fx=100.0)
    assert pol.due(0, ids, uv)                            # nothing to compare with
    pol.reset(0, ids, uv)
    ms = 1_000_000
    x = np.array([1.0, 0.0])
    assert not pol.due(50 * ms, ids, uv + 0.5 * x)        # 50 px, but sooner than 0.1 s
    assert not pol.due(150 * ms, ids, uv + 0.09 * x)      # 9 px
    assert pol.due(150 * ms, ids, uv + 0.1 * x)           # 10 px
    assert pol.due(150 * ms, ids[:11], uv[:11])           # 11 tracks left
    assert not pol.due(150 * ms, ids + 5, uv + 0.09 * x)  # 15 common tracks, 9 px
    assert pol.due(300 * ms, ids, uv)                     # 0.3 s
    pol.reset(300 * ms, ids, uv + x)
    assert not pol.due(350 * ms, ids, uv)                 # 100 px, 0.05 s after the new one


def test_stage_matches_cam1_at_its_keyframes_only(sim_stereo):
    """``FrontendConfig.stereo_at = "keyframe"``: the image stage marks exactly the
    keyframes the pipeline's policy picks on the same tracks, has cam1 matches at those
    and through ``every_frame_s`` only, and at the keyframes matches about as many
    features as matching every frame does; in a worker process it gives the same packets."""
    import dataclasses
    from vio.io.euroc import image_files
    from vio.overlap import overlapped
    from vio.sync import packets
    from vio.tracking import ImageStage
    d, cfg = sim_stereo, PipelineConfig()
    stamps = d.cam0.t_ns[:60]
    files = image_files(d, True, stamps)
    every = ImageStage(d.cam0.calib, d.cam1.calib, cfg.frontend)
    ref = [every(p) for p in packets(d.imu, stamps, 0.0, image_files=files)]
    args = (d.cam0.calib, d.cam1.calib, dataclasses.replace(cfg.frontend, stereo_at="keyframe"),
            cfg.backend.keyframe, 0.5)
    stage = ImageStage(*args)
    got = [stage(p) for p in packets(d.imu, stamps, 0.0, image_files=files)]
    flags = [p.keyframe for p in got]
    assert flags == _policy_flags([(p.t_ns, p.features) for p in ref], cfg.backend.keyframe,
                                  d.cam0.calib.intrinsics[0])
    assert 8 < sum(flags) < 40
    n_kf = n_ref = 0
    for p, r in zip(got, ref):
        np.testing.assert_array_equal(p.features.uv, r.features.uv)     # cam0 is untouched
        matched = np.isfinite(p.features.right_uv).all(axis=1)
        if p.keyframe or p.t_ns - stamps[0] < 0.5e9:
            assert matched.sum() > 20
        else:
            assert not matched.any() and not p.features.right_velocity.any()
        if p.keyframe:
            n_kf += matched.sum()
            n_ref += np.isfinite(r.features.right_uv).all(axis=1).sum()
    assert n_kf >= 0.95 * n_ref
    remote = list(overlapped(ImageStage, args, packets(d.imu, stamps, 0.0, image_files=files), depth=3))
    for a, b in zip(remote, got):
        assert a.keyframe == b.keyframe
        np.testing.assert_array_equal(a.features.right_uv, b.features.right_uv)


def test_stage_decodes_cam1_at_its_keyframes_only(sim_stereo, tmp_path):
    """With cam1 matched at keyframes, an undecodable cam1 image is not read at a frame
    that is no keyframe, and drops the frame where it is one (as a bad cam0 image does);
    a missing cam1 file drops its frame wherever it is."""
    import dataclasses
    from vio.io.euroc import image_files
    from vio.sync import packets
    from vio.tracking import ImageStage
    d, cfg = sim_stereo, PipelineConfig()
    stamps = d.cam0.t_ns[:40]
    files = image_files(d, True, stamps)
    args = (d.cam0.calib, d.cam1.calib, dataclasses.replace(cfg.frontend, stereo_at="keyframe"),
            cfg.backend.keyframe, 0.0)
    flags = [p.keyframe for p in map(ImageStage(*args), packets(d.imu, stamps, 0.0, image_files=files))]
    plain, kf = flags.index(False, 1), flags.index(True, flags.index(False, 1))
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    files[plain] = (files[plain][0], bad)
    files[kf] = (files[kf][0], bad)
    files[-1] = (files[-1][0], tmp_path / "missing.png")
    got = list(map(ImageStage(*args), packets(d.imu, stamps, 0.0, image_files=files)))
    assert not got[plain].dropped and got[plain].features is not None
    assert "bad.png: image missing or unreadable" in got[kf].dropped and got[kf].features is None
    assert "missing.png" in got[-1].dropped
    assert sum(bool(p.dropped) for p in got) == 2


@pytest.mark.slow
def test_stereo_mode_keyframes_are_the_stages(sim_stereo):
    """Stereo mode (cam1 at keyframes, ``vio.modes``) keyframes where the stage matched
    cam1: every keyframe after initialization has stereo observations, and the estimate
    matches the every-frame run's to a few millimetres."""
    import dataclasses
    from vio.run import default_config
    cfg = default_config("stereo")
    assert cfg.frontend.stereo_at == "keyframe"
    res = run_dataset(sim_stereo, cfg, mode="stereo")
    ref = run_dataset(sim_stereo, dataclasses.replace(
        cfg, frontend=dataclasses.replace(cfg.frontend, stereo_at="frame")), mode="stereo")
    assert [o.keyframe for o in res.outputs] == [o.keyframe for o in ref.outputs]
    kfs = [o for o in res.outputs if o.keyframe]
    assert all(o.packet.keyframe and np.isfinite(o.features.right_uv).any() for o in kfs[1:])
    ate = [evaluate(*r.arrays(), sim_stereo.groundtruth).ate_rmse for r in (res, ref)]
    assert ate[0] < 0.03 and abs(ate[0] - ate[1]) < 0.005


def test_stereo_initialization_starts_at_a_matched_frame(sim_stereo):
    """A stereo initialization window whose first frames the stage did not match in cam1
    (``stereo_at = "keyframe"`` after ``every_frame_s``) starts at the first keyframe: the
    first pose is that frame's, not an unmatched one's (which cannot give the structure)."""
    from vio.io.euroc import image_files
    from vio.pipeline import Pipeline
    from vio.run import default_config
    from vio.sync import packets
    from vio.tracking import ImageStage
    d, cfg = sim_stereo, default_config("stereo")
    stamps = d.cam0.t_ns[:30]
    stage = ImageStage(d.cam0.calib, d.cam1.calib, cfg.frontend, cfg.backend.keyframe, 0.0)
    got = [stage(p) for p in packets(d.imu, stamps, 0.0, image_files=image_files(d, True, stamps))]
    first_kf = next(k for k in range(1, len(got)) if got[k].keyframe)
    assert first_kf > 1 and not np.isfinite(got[1].features.right_uv).any()
    pipe = Pipeline(d.imu_calib, d.cam0.calib, cfg, d.cam1.calib)
    outs = [o for p in got[1:] for o in pipe.process(p)]
    assert pipe.init_info is not None and pipe.init_info.method == "stereo"
    assert outs[0].t_ns == got[first_kf].t_ns
