"""The procedural scene and secret: deterministic bytes, NeRF-Synthetic format, atomic folder writes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import read_image
from noisenerf.train.scene import procedural
from noisenerf.train.scene.datasets import load_dataset
from noisenerf.train.scene.procedural import procedural_secret, write_procedural_dataset

SMALL = dict(size=16, n_train=3, n_val=1, n_test=2)


def tree_bytes(folder) -> dict[str, bytes]:
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_same_seed_writes_byte_identical_files(tmp_path):
    first = tree_bytes(write_procedural_dataset(tmp_path / "a", **SMALL))
    assert first == tree_bytes(write_procedural_dataset(tmp_path / "b", **SMALL))
    assert len(first) == 3 + 6 and "train/r_2.png" in first
    other = tree_bytes(write_procedural_dataset(tmp_path / "c", **SMALL, seed=1))
    assert other["transforms_train.json"] != first["transforms_train.json"]


def test_default_dataset_loads_as_nerf_synthetic(tmp_path):
    folder = write_procedural_dataset(tmp_path / "scene")
    dataset = load_dataset(folder)
    assert dataset.kind == "blender" and (dataset.near, dataset.far) == (2.0, 6.0)
    assert {k: len(v) for k, v in dataset.splits.items()} == {"train": 40, "val": 4, "test": 8}
    assert dataset.images.shape == (52, 64, 64, 3)
    meta = json.loads((folder / "transforms_val.json").read_text())
    assert meta["camera_angle_x"] == pytest.approx(0.6911, abs=1e-4)
    assert set(meta["frames"][0]) == {"file_path", "rotation", "transform_matrix"}
    for camera in dataset.cameras:
        c2w = camera.matrix().astype(np.float64)
        eye, forward = c2w[:3, 3], -c2w[:3, 2]
        assert np.linalg.norm(eye) == pytest.approx(4.0) and eye[2] > 0
        np.testing.assert_allclose(eye + 4.0 * forward, 0.0, atol=1e-5)  # looks at the origin


def test_views_have_objects_background_and_soft_alpha_edges(tmp_path):
    folder = write_procedural_dataset(tmp_path / "scene", **SMALL)
    alpha = read_image(folder / "train" / "r_0.png")[..., 3]
    assert (alpha == 0).any() and (alpha == 1).any()
    assert ((alpha > 0) & (alpha < 1)).any()  # supersampled silhouette


def test_existing_folder_is_refused_and_failures_leave_nothing(tmp_path, monkeypatch):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")
    with pytest.raises(UserError, match="output exists and is not an empty folder"):
        write_procedural_dataset(tmp_path / "full", **SMALL)
    calls = []

    def failing_render(camera):
        calls.append(camera)
        if len(calls) == 2:
            raise OSError("disk full")
        return np.zeros((camera.height, camera.width, 4))

    monkeypatch.setattr(procedural, "render_rgba", failing_render)
    with pytest.raises(OSError, match="disk full"):
        write_procedural_dataset(tmp_path / "scene", **SMALL)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full"]  # no scene, no staging folder


def test_bad_sizes_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="at least 8 px"):
        write_procedural_dataset(tmp_path / "a", size=4)
    with pytest.raises(UserError, match="at least one train view"):
        write_procedural_dataset(tmp_path / "a", n_train=0)
    with pytest.raises(UserError, match="output folder does not exist"):
        write_procedural_dataset(tmp_path / "missing" / "a", **SMALL)


def test_procedural_secret_is_deterministic_and_spans_the_range():
    secret = procedural_secret(96, 72)
    assert secret.shape == (72, 96, 3) and secret.dtype == np.uint8
    np.testing.assert_array_equal(secret, procedural_secret(96, 72))
    assert secret.min() == 0 and secret.max() == 255
    assert len(np.unique(secret.reshape(-1, 3), axis=0)) > 500  # a picture, not a few flat colours
    assert not np.array_equal(secret, procedural_secret(96, 72, seed=1))
