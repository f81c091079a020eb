"""``vio run``'s summary notes (``vio.run_cmd``)."""

from __future__ import annotations

from types import SimpleNamespace

from vio.run_cmd import TD_HINT_S, td_hint


def _res(td_s: float, init: bool = True) -> SimpleNamespace:
    return SimpleNamespace(init=object() if init else None, outputs=[SimpleNamespace(td_s=0.0),
                                                                    SimpleNamespace(td_s=td_s)])


def test_mono_suggests_rerunning_at_an_estimate_far_from_the_starting_offset():
    note = td_hint(_res(0.0117), 0.0, "mono")
    assert note is not None and "+11.7 ms" in note and "--td 0.0117" in note
    assert td_hint(_res(0.0217), 0.010, "mono").endswith("--td 0.0217")       # from a --td start too
    assert td_hint(_res(0.010 + 0.9 * TD_HINT_S), 0.010, "mono") is None      # within the limit
    assert td_hint(_res(-0.020), 0.0, "mono") is not None                      # either sign


def test_no_td_note_where_the_offset_does_not_cost_or_nothing_was_estimated():
    for mode in ("stereo", "features", "hybrid", "direct"):
        assert td_hint(_res(0.0117), 0.0, mode) is None
    assert td_hint(_res(0.0117, init=False), 0.0, "mono") is None              # never initialized
    assert td_hint(SimpleNamespace(init=object(), outputs=[]), 0.0, "mono") is None
    assert td_hint(_res(float("nan")), 0.0, "mono") is None
