"""Heap management of long and image-heavy runs (``vio.memory``)."""

from __future__ import annotations

import ctypes.util
import platform

import pytest

from vio import memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc" and ctypes.util.find_library("c")


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_tune_heap_sets_the_three_glibc_parameters(monkeypatch) -> None:
    calls = []
    real = memory._mallopt()
    assert real is not None and memory.tune_heap()       # accepted by this glibc
    monkeypatch.setattr(memory, "_mallopt", lambda: lambda opt, val: calls.append((opt, val)) or 1)
    assert memory.tune_heap(mmap_threshold=1 << 25, trim_threshold=1 << 27, top_pad=1 << 24)
    assert sorted(calls) == sorted([(memory.M_MMAP_THRESHOLD, 1 << 25), (memory.M_TRIM_THRESHOLD, 1 << 27),
                                    (memory.M_TOP_PAD, 1 << 24)])
    monkeypatch.setattr(memory, "_mallopt", lambda: lambda opt, val: 0)   # refused
    assert memory.tune_heap() is False


def test_pipeline_config_switch_and_trim_are_safe_everywhere(monkeypatch) -> None:
    from vio.config import from_dict
    from vio.pipeline import PipelineConfig
    assert from_dict(PipelineConfig, {"tune_heap": False}).tune_heap is False
    monkeypatch.setattr(memory, "_mallopt", lambda: None)   # non-glibc platforms
    assert memory.tune_heap() is False
    assert isinstance(memory.trim_heap(), bool)
