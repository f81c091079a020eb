"""Live operation (``PipelineConfig.live``): the backend in its own process computes the
same keyframe states as the deterministic in-process run; the frame path only predicts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import shared
from vio.io.euroc import load_euroc
from vio.run import default_config, run_dataset

FRAMES = 70   # 3.5 s of V1_01 at 20 Hz: initialization and a dozen keyframes


def test_live_backend_reaches_the_deterministic_keyframe_state(monkeypatch):
    data = load_euroc(shared("euroc_V1_01_30s_features"))
    cfg = default_config("features")
    ref = run_dataset(data, cfg, FRAMES, mode="features")
    from vio.live import LivePipeline
    seen: list = []
    orig_close = LivePipeline.close

    def close(self, wait=True):   # keep the pipeline: its final state and prediction
        orig_close(self, wait)
        seen.append(self)

    monkeypatch.setattr(LivePipeline, "close", close)
    live = run_dataset(data, dataclasses.replace(cfg, live=True), FRAMES, mode="features")
    assert live.keyframes == ref.keyframes > 3
    last_kf = [o for o in ref.outputs if o.keyframe][-1]
    pipe = seen[0]
    assert pipe.state.t_ns == last_kf.t_ns
    assert np.array_equal(pipe.state.T_w_b, last_kf.T_w_b.matrix())      # same input, same update
    # the frame path's prediction from that state equals the in-process estimator's
    last = ref.outputs[-1]
    assert not last.keyframe
    assert np.array_equal(pipe.predict().pose().matrix(), last.T_w_b.matrix())
    # how many frames got a live output, and from which state, depends on the load
    t = [o.t_ns for o in live.outputs]
    assert t == sorted(t) and not any(o.keyframe for o in live.outputs)
    assert all(np.isfinite(o.T_w_b.matrix()).all() for o in live.outputs)
    # the backend's fault counters stayed in its process: the summary says so, not "0 gaps"
    from vio.run_summary import summary
    assert live.live and not ref.live
    faults = [ln for ln in summary(live, data) if ln.startswith("faults")]
    assert faults == ["faults          in the live backend process (not reported here; its warnings name each)"]
    assert [ln for ln in summary(ref, data) if ln.startswith("faults")][0].startswith("faults          0 IMU gap(s)")


def test_live_is_refused_for_the_photometric_modes():
    data = load_euroc(shared("euroc_V1_01_static_stereo"))
    cfg = dataclasses.replace(default_config("direct"), live=True)
    with pytest.raises(ValueError, match="live operation"):
        run_dataset(data, cfg, 5, mode="direct")
