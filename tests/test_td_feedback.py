"""The sync layer's td feedback (``vio.run.td_feedback``): the initialization's offset at
once (``CalibConfig.td_feedback_at_init``), then steps towards the estimate after
``td_feedback_after_s``."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest

from vio.run import default_config, td_feedback


class _Est:
    """The estimator as the feedback reads it: initialized, keyframe times, td()."""

    def __init__(self, td: float) -> None:
        self.initialized, self.k, self.kf_t, self._td = False, 0, {0: 0}, td

    def td(self) -> float:
        return self._td


@pytest.mark.parametrize("at_init", [True, False])
def test_the_initializations_offset_is_applied_at_once(at_init):
    cfg = default_config("features")
    calib = dataclasses.replace(cfg.backend.calib, td_feedback_at_init=at_init, td_feedback_after_s=1.0)
    cfg = dataclasses.replace(cfg, td_s=0.0, backend=dataclasses.replace(cfg.backend, calib=calib))
    est = _Est(0.0203)               # a dynamic initialization's search found 20.3 ms
    source = td_feedback(SimpleNamespace(est=est), cfg)
    assert source() == 0.0           # before the initialization: the configured td
    est.initialized = True
    assert source() == pytest.approx(0.0203 if at_init else 0.0)
    est._td = 0.0249                 # the window's estimate moves on
    for k, t_s in enumerate((0.5, 1.0, 1.1, 1.2), start=1):
        est.k, est.kf_t[k] = k, int(t_s * 1e9)
        applied = source()
    # from 1 s after initialization on, 1 ms a frame towards the estimate
    assert applied == pytest.approx(0.0233 if at_init else 0.003)
