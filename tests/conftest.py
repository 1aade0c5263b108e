"""Shared fixtures: the real data folder (skipped with a reason where absent), tiny scenes, the reveal's
inputs and the demo scene. Plain helpers live in helpers.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from helpers import make_tiny_scene, write_reveal_inputs

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


@pytest.fixture(scope="session")
def reveal_inputs(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(folder, model, bundle): a tiny scene (folder/scene), its exported model and a two-tile bundle for it."""
    folder = tmp_path_factory.mktemp("reveal")
    return (folder, *write_reveal_inputs(folder))


@pytest.fixture(scope="session")
def demo_model(tmp_path_factory) -> Path:
    """The demo scene's exported model.onnx (in a folder of its own)."""
    from noisenerf.export.onnx_export import export_scene
    from noisenerf.train.scene.procedural import DEMO_SCENE

    path = tmp_path_factory.mktemp("demo") / "model.onnx"
    export_scene(DEMO_SCENE, path)
    return path


@pytest.fixture(scope="module")
def demo_scene():
    """The demo scene, loaded once per test module."""
    from noisenerf.train.scene.procedural import DEMO_SCENE
    from noisenerf.train.scene.scene import load_scene

    return load_scene(DEMO_SCENE)
