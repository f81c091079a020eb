"""Shared fixtures: location of the real EuRoC data in ../shared/data."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared(*parts: str) -> Path:
    """Path inside ../shared/data, or skip the test with the reason when absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real EuRoC data not available at {path} (../shared is absent)")
    return path
