"""``vio run``'s summary notes (``vio.run_cmd``)."""

from __future__ import annotations

from types import SimpleNamespace

from vio.run_cmd import TD_HINT_S, td_hint


def _res(td_s: float, init: bool = True, init_td_s: float = 0.0) -> SimpleNamespace:
    return SimpleNamespace(init=SimpleNamespace(td_s=init_td_s) if init else None,
                           outputs=[SimpleNamespace(td_s=0.0), SimpleNamespace(td_s=td_s)])


def test_mono_suggests_rerunning_at_an_estimate_far_from_the_starting_offset():
    note = td_hint(_res(0.0117), 0.0, "mono")
    assert note is not None and "+11.7 ms" in note and "--td 0.0117" in note
    assert td_hint(_res(0.0217), 0.010, "mono").endswith("--td 0.0217")       # from a --td start too
    assert td_hint(_res(0.010 + 0.9 * TD_HINT_S), 0.010, "mono") is None      # within the limit
    assert td_hint(_res(-0.020), 0.0, "mono") is not None                      # either sign


def test_no_td_note_when_the_initialization_aligned_at_the_estimate():
    """A dynamic initialization that found the offset (its remainder in ``InitInfo.td_s``)
    aligned its window there: the note measures from that offset."""
    assert td_hint(_res(-0.0249, init_td_s=-0.0243), 0.0, "mono") is None
    note = td_hint(_res(-0.0249, init_td_s=-0.018), 0.0, "mono")
    assert note is not None and "-6.9 ms" in note


def test_no_td_note_where_the_offset_does_not_cost_or_nothing_was_estimated():
    for mode in ("stereo", "features", "hybrid", "direct"):
        assert td_hint(_res(0.0117), 0.0, mode) is None
    assert td_hint(_res(0.0117, init=False), 0.0, "mono") is None              # never initialized
    assert td_hint(SimpleNamespace(init=object(), outputs=[]), 0.0, "mono") is None
    assert td_hint(_res(float("nan")), 0.0, "mono") is None


def test_log_records_during_the_progress_bar_get_lines_of_their_own(capsys):
    """A warning while ``vio run`` shows its progress bar (a dropped frame, an IMU gap) is
    written above the bar, not into its line; the console handler keeps its level and
    format, and gets its stream back afterwards."""
    import logging
    import sys

    from tqdm import tqdm

    from vio.run import _log_above
    root, log = logging.getLogger(), logging.getLogger("vio.test_progress")
    h = logging.StreamHandler(sys.stderr)
    h.setLevel(logging.WARNING)
    h.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    level = root.level
    root.addHandler(h)
    root.setLevel(logging.INFO)
    try:
        bar = tqdm(total=3, file=sys.stderr)
        bar.update(1)
        with _log_above(bar):
            log.warning("frame dropped")
            log.info("an info record the handler's level drops")
            bar.update(1)
        bar.close()
        assert h.stream is sys.stderr
    finally:
        root.removeHandler(h)
        root.setLevel(level)
    lines = capsys.readouterr().err.replace("\r", "\n").split("\n")
    assert "WARNING vio.test_progress: frame dropped" in lines
    assert not any("info record" in ln for ln in lines)


def test_summary_names_the_uncertainty_of_a_dynamic_start_scale():
    """A monocular dynamic initialization's window scale sigma is printed (real MH_05 mono
    from frame 140: 11.4 %, the window 20 % long); a stereo or still start has none."""
    from vio.outputs import InitInfo
    from vio.run import RunResult
    from vio.run_summary import summary

    data = SimpleNamespace(groundtruth=None)
    line = [ln for ln in summary(RunResult(init=InitInfo("dynamic", 1.5, 0.0, 0.0, 0.114)), data)
            if ln.startswith("initialization")][0]
    assert "metric scale +-11.4 % (1 sigma)" in line
    line = [ln for ln in summary(RunResult(init=InitInfo("stereo", 0.5, 0.0)), data)
            if ln.startswith("initialization")][0]
    assert "scale" not in line
