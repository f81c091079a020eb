"""The benchmark results' provenance: which commit and which machine measured each section."""

from __future__ import annotations

import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

from report_format import machine_line  # noqa: E402
from run_all import record_section  # noqa: E402


def _results(cpu: str, commit: str) -> dict:
    return {"machine": {"cpu": cpu, "cores": 2, "commit": commit}}


def test_refreshed_modes_replace_the_keys_they_cover_and_name_their_machine():
    res = _results("AMD EPYC", "a1")
    record_section(res, "accuracy", None)
    record_section(res, "micro", None)
    res["machine"]["commit"] = "b2"
    record_section(res, "accuracy", ["stereo", "mono"])
    record_section(res, "accuracy", ["mono"])
    res["machine"].update(cpu="Intel Xeon", commit="c3")
    record_section(res, "accuracy", ["mono", "features"])
    # accuracy[mono] is covered by the refresh; accuracy[stereo,mono] still holds stereo rows
    assert res["section_commits"] == {"accuracy": "a1", "micro": "a1", "accuracy[stereo,mono]": "b2",
                                      "accuracy[mono,features]": "c3"}
    assert res["section_machines"]["accuracy[mono,features]"] == "Intel Xeon"
    line = machine_line(res)
    assert line.startswith("Machine: AMD EPYC (accuracy, micro, accuracy[stereo,mono]); "
                           "Intel Xeon (accuracy[mono,features]), 2 cores")
    assert "accuracy[mono,features] at c3" in line


def test_a_full_accuracy_run_drops_every_mode_key_and_one_machine_is_named_once():
    res = _results("AMD EPYC", "a1")
    record_section(res, "accuracy", ["stereo"])
    record_section(res, "accuracy", None)
    assert res["section_commits"] == {"accuracy": "a1"}
    assert res["section_machines"] == {"accuracy": "AMD EPYC"}
    assert machine_line(res).startswith("Machine: AMD EPYC, 2 cores")


def test_an_earlier_key_goes_once_later_keys_have_measured_every_mode_of_it():
    """The plain ``accuracy`` key (every mode) and ``accuracy[features,mono]`` are gone once
    later refreshes have covered their modes between them; one still holding rows stays."""
    import datasets as ds
    res = _results("AMD EPYC", "a1")
    record_section(res, "accuracy", None)
    res["machine"]["commit"] = "b2"
    record_section(res, "accuracy", ["features", "mono"])
    record_section(res, "accuracy", ["stereo", "mono", "hybrid", "direct"])
    assert list(res["section_commits"]) == ["accuracy", "accuracy[features,mono]",
                                             "accuracy[stereo,mono,hybrid,direct]"]
    res["machine"]["commit"] = "c3"
    record_section(res, "accuracy", ["variants"])
    record_section(res, "accuracy", ["features"])
    assert {"features", "variants", "stereo", "mono", "direct", "hybrid"} >= set(ds.MODES)
    assert res["section_commits"] == {"accuracy[stereo,mono,hybrid,direct]": "b2",
                                      "accuracy[variants]": "c3", "accuracy[features]": "c3"}
    assert set(res["section_machines"]) == set(res["section_commits"])
