"""vio.overlap's worker pipes: replies that reach the parent together are all seen."""

from __future__ import annotations

import operator
import time
from types import SimpleNamespace

from vio.overlap import overlapped


def test_replies_arriving_together_are_all_received():
    """The worker answers four packets while the parent is busy, so one pipe read could
    take all four replies; a buffered reader then hid three of them from ``select`` and
    the last results timed out (``LivePipeline.close`` waited forever)."""
    def source():
        for i in range(4):
            yield SimpleNamespace(index=i)
        time.sleep(1.5)   # the worker replies to all four meanwhile

    got = list(overlapped(operator.attrgetter, ("index",), source(), depth=5, timeout_s=5.0))
    assert got == [0, 1, 2, 3]
