"""The eliminated-depth landmark factors end to end (``VisionConfig.eliminate_depth``,
``vio.backend.bundles``) on a stretch of the real V1_01 tracks: the smoother holds no
landmark variable, landmarks are re-anchored and rejected through the same life cycle,
the trajectory stays accurate and the run is deterministic."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from conftest import shared
from vio.backend.bundles import EliminatedLandmarks
from vio.evaluation import evaluate
from vio.io.euroc import load_euroc
from vio.pipeline import PipelineConfig
from vio.run import run_dataset


@pytest.fixture(scope="module")
def v101():
    return load_euroc(shared("euroc_V1_01_30s_features"))


def _config() -> PipelineConfig:
    cfg = PipelineConfig()
    vision = dataclasses.replace(cfg.backend.vision, eliminate_depth=True)
    return dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, vision=vision))


def test_eliminated_depth_on_real_v1_01_tracks(v101, monkeypatch):
    """12 s of real IMU + real KLT tracks: ATE 0.017 m measured (variable mode 0.011 m;
    over the whole 30 s 0.025 vs 0.027 m)."""
    kinds, handed, rejected = [], [], []
    prep, hand, outl = (EliminatedLandmarks.prepare_update, EliminatedLandmarks._hand_over_eliminated,
                        EliminatedLandmarks.outlier_removals)

    def spy_prepare(self, *a):
        kinds.append({chr(gtsam.Symbol(k).chr()) for k in self.est.values.keys()})
        return prep(self, *a)

    def spy_hand(self, tr, *a):
        hand(self, tr, *a)
        handed.append(tr.key is not None)

    def spy_outliers(self, values):
        out = outl(self, values)
        rejected.append(out[3])
        return out

    monkeypatch.setattr(EliminatedLandmarks, "prepare_update", spy_prepare)
    monkeypatch.setattr(EliminatedLandmarks, "_hand_over_eliminated", spy_hand)
    monkeypatch.setattr(EliminatedLandmarks, "outlier_removals", spy_outliers)
    res = run_dataset(v101, _config(), max_frames=240)
    assert res.recoveries == 0 and res.restarts == 0
    assert len(kinds) > 50 and all(k <= {"x", "v", "b", "e", "d", "z"} for k in kinds)   # z: padding
    assert sum(handed) > 20 and sum(rejected) > 0
    assert len(res.landmarks) > 30
    ate = evaluate(*res.arrays(), v101.groundtruth).ate_rmse
    print(f"ATE {ate:.4f} m, {sum(handed)} re-anchored, {sum(rejected)} rejected")
    assert ate < 0.03
    monkeypatch.undo()
    again = run_dataset(v101, _config(), max_frames=240)
    a, b = res.arrays(), again.arrays()
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_similarity_scales_the_eliminated_depths():
    """The scale refinement's similarity (``vio.backend.regauge.apply_similarity``) moves
    the depths kept outside ``Values`` too: a 10 % scale shrinks every inverse depth by it
    exactly, the window's extent grows (after the first update on the moved state, in which
    the IMU factors pull back: 1.029 measured here, 1.066 in the variable mode, whose test
    is ``tests/test_scale_refine.py``; without the depths scaled it shrank, 0.98), and the run
    goes on without recovery."""
    from test_scale_refine import _pipeline
    from vio.backend import graph
    from vio.backend.regauge import Similarity, apply_similarity
    from vio.run import default_config
    cfg = default_config("features")
    vision = dataclasses.replace(cfg.backend.vision, eliminate_depth=True)
    pipe, it = _pipeline(200, dataclasses.replace(cfg, backend=dataclasses.replace(cfg.backend, vision=vision)))
    est = pipe.est
    est.lm._sync()
    before = gtsam.Values(est.values)
    lam0 = {tr.lid: tr.lam for tr in est.lm.tracks.values() if tr.key is not None}
    T0 = est.latest()[0]
    apply_similarity(est, Similarity(1.1, gtsam.Rot3.Ry(np.radians(1.0)), T0.translation(),
                                     est.extrinsic().translation()))
    ks = sorted(est.kf_t)
    ext = [np.linalg.norm(v.atPose3(graph.X(ks[0])).translation() - v.atPose3(graph.X(ks[-1])).translation())
           for v in (before, est.values)]
    assert 1.02 < ext[1] / ext[0] < 1.11
    est.lm._sync()
    ratio = np.median([tr.lam / lam0[tr.lid] for tr in est.lm.tracks.values() if tr.lid in lam0])
    assert ratio == pytest.approx(1 / 1.1, rel=1e-9)
    for _ in range(20):
        pipe.process(next(it))
    assert est.recoveries == 0
