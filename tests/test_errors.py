"""The one-line form of solver errors in log records (``vio.errors.one_line``)."""

import gtsam
import numpy as np
import pytest

from vio.errors import one_line


def _indeterminate() -> RuntimeError:
    """GTSAM's own IndeterminateLinearSystem error: a 6-vector of which three rows are measured."""
    g = gtsam.GaussianFactorGraph()
    g.add(gtsam.JacobianFactor(0, np.eye(6)[:3], np.zeros(3), gtsam.noiseModel.Unit.Create(3)))
    with pytest.raises(RuntimeError) as info:
        g.optimize()
    return info.value


def test_gtsam_message_starts_with_its_first_words():
    exc = _indeterminate()
    assert str(exc).startswith("\n")                  # why str(exc).splitlines()[0] logged ""
    line = one_line(exc)
    assert line.startswith("Indeterminate linear system") and "\n" not in line


def test_blank_and_long_messages():
    assert one_line(RuntimeError("")) == "RuntimeError"
    assert one_line(ValueError("\n \n  x\ny")) == "x"
    assert len(one_line(RuntimeError("a" * 500), width=40)) == 40
