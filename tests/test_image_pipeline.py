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
