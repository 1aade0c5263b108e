"""Shared fixtures: the real data folder (skipped with a reason where absent) and tiny scenes. Plain helpers
live in helpers.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from helpers import make_tiny_scene  # test_stress.py imports it from here

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NOISENERF_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (lego, fern, secret photos); tests needing it skip where it is absent."""
    if not (SHARED_DATA / "scenes").is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (set NOISENERF_SHARED_DATA to run these)")
    return SHARED_DATA


@pytest.fixture
def tiny_scene():
    return make_tiny_scene()
