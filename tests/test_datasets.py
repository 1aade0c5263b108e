"""Dataset loading: NeRF-Synthetic and LLFF (nerf-pytorch's pose processing), real lego/fern, bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import read_raw, turning_llff, write_blender, write_png
from noisenerf.runtime.errors import UserError
from noisenerf.train.scene.datasets import load_dataset

LEGO_FOV = 0.6911112070083618


def pose(k: int) -> list[list[float]]:
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1 * k, -4.0, 0.5]
    return c2w.tolist()


def gradient_blender(folder, splits=("train", "val", "test"), size=(8, 4), channels=4, file_suffix=""):
    """One frame per split, pixel (x, y) of frame k = (40k + 20x, 10y, 255 − 30x, alpha 255 − 60x)."""
    width, height = size
    x, y = np.meshgrid(np.arange(width), np.arange(height))
    frames = {}
    for k, split in enumerate(splits):
        pixels = np.stack([40 * k + 20 * x, 10 * y, 255 - 30 * x, 255 - 60 * x], axis=-1) % 256
        frames[split] = [(pixels[..., :channels].astype(np.uint8), pose(k))]
    return write_blender(folder, frames, camera_angle_x=0.8, file_suffix=file_suffix)


# ---- NeRF-Synthetic ------------------------------------------------------------------------------

def test_blender_composites_straight_alpha_on_the_background(tmp_path):
    folder = gradient_blender(tmp_path)
    dataset = load_dataset(folder, background=(0.0, 0.0, 1.0))
    assert dataset.kind == "blender" and dataset.images.shape == (3, 4, 8, 3)
    assert dataset.splits == {"train": (0,), "val": (1,), "test": (2,)}
    assert (dataset.near, dataset.far, dataset.ndc) == (2.0, 6.0, None)
    raw = read_raw(folder / "val" / "r_0.png").astype(np.float64) / 255.0
    alpha = raw[..., 3:]
    expected = raw[..., :3] * alpha + np.array([0.0, 0.0, 1.0]) * (1.0 - alpha)
    np.testing.assert_allclose(dataset.images[1], expected, atol=1e-6)
    camera = dataset.cameras[2]
    np.testing.assert_array_equal(camera.matrix(), np.asarray(pose(2), np.float32))
    assert camera.fx == pytest.approx(0.5 * 8 / math.tan(0.4)) and (camera.cx, camera.cy) == (4.0, 2.0)


def test_blender_resolution_composites_then_box_downscales(tmp_path):
    folder = gradient_blender(tmp_path, splits=("train",), size=(12, 10))
    full = load_dataset(folder).images[0]
    small = load_dataset(folder, resolution=6)
    assert small.images.shape == (1, 5, 6, 3)  # height 10 · 6 / 12 = 5
    np.testing.assert_allclose(small.images[0], full.reshape(5, 2, 6, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    assert small.cameras[0].fx == pytest.approx(0.5 * 6 / math.tan(0.4))
    assert small.splits == {"train": (0,), "val": (), "test": ()}


def test_blender_keeps_file_extensions_and_rgb_images(tmp_path):
    folder = gradient_blender(tmp_path, splits=("train",), channels=3, file_suffix=".png")
    dataset = load_dataset(folder, background=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(dataset.images[0], read_raw(folder / "train" / "r_0.png") / 255.0, atol=1e-6)


def test_without_images_gives_the_same_cameras(tmp_path):
    folder = gradient_blender(tmp_path)
    bare = load_dataset(folder, resolution=4, with_images=False)
    assert bare.images is None and bare.cameras == load_dataset(folder, resolution=4).cameras


def edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("break_it, message", [
    (lambda f: (f / "transforms_train.json").write_text("{not json"), "transforms_train.json is not valid JSON"),
    (lambda f: edit_json(f / "transforms_train.json", lambda d: d.pop("frames")), "'frames' must be a list of frames"),
    (lambda f: edit_json(f / "transforms_val.json", lambda d: d.pop("camera_angle_x")), "camera_angle_x"),
    (lambda f: edit_json(f / "transforms_test.json", lambda d: d["frames"][0].pop("transform_matrix")),
     "transforms_test.json frame 0: needs a numeric 4x4 'transform_matrix'"),
    (lambda f: edit_json(f / "transforms_train.json",
                         lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, float("nan"))),
     "must be a finite 4x4 matrix"),
    (lambda f: (f / "val" / "r_0.png").unlink(), "image not found: .*val/r_0.png"),
    (lambda f: write_png(f / "test" / "r_0.png", np.zeros((4, 8, 2), np.uint8)), "r_0.png has 2 channels"),
    (lambda f: write_png(f / "test" / "r_0.png", np.zeros((5, 8, 4), np.uint8)), "is 8x5, but"),
])
def test_bad_blender_input_is_one_user_error(tmp_path, break_it, message):
    folder = gradient_blender(tmp_path)
    break_it(folder)
    with pytest.raises(UserError, match=message):
        load_dataset(folder)


def test_unknown_folder_and_too_large_resolution(tmp_path):
    with pytest.raises(UserError, match="not a dataset: expected transforms_train.json"):
        load_dataset(tmp_path)
    with pytest.raises(UserError, match="dataset folder not found"):
        load_dataset(tmp_path / "absent")
    with pytest.raises(UserError, match="resolution 9 is larger than the images"):
        load_dataset(gradient_blender(tmp_path), resolution=9)


def test_real_lego_cameras_and_splits(shared_data):
    lego = shared_data / "scenes" / "blender" / "lego"
    dataset = load_dataset(lego, resolution=50, with_images=False)
    assert {k: len(v) for k, v in dataset.splits.items()} == {"train": 100, "val": 13, "test": 25}
    assert dataset.splits["test"][0] == 113 and len(dataset.cameras) == 138
    first_test = json.loads((lego / "transforms_test.json").read_text())["frames"][0]["transform_matrix"]
    np.testing.assert_array_equal(dataset.cameras[113].c2w, first_test)
    camera = dataset.cameras[0]
    assert (camera.width, camera.height) == (50, 50)
    assert camera.fx == camera.fy == pytest.approx(0.5 * 50 / math.tan(0.5 * LEGO_FOV), rel=1e-12)
    assert dataset.aabb == (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)


def test_real_lego_images_at_resolution_50(shared_data, tmp_path):
    """Two real frames (the full set would take seconds to decode): RGBA over white, 16×16 block means."""
    lego = shared_data / "scenes" / "blender" / "lego"
    meta = json.loads((lego / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][:2]
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    (tmp_path / "train").symlink_to(lego / "train")
    dataset = load_dataset(tmp_path, resolution=50)
    assert dataset.images.shape == (2, 50, 50, 3) and dataset.images.dtype == np.float32
    raw = read_raw(lego / "train" / "r_1.png").astype(np.float64) / 255.0
    over_white = raw[..., :3] * raw[..., 3:] + (1.0 - raw[..., 3:])
    np.testing.assert_allclose(dataset.images[1], over_white.reshape(50, 16, 50, 16, 3).mean(axis=(1, 3)), atol=1e-5)


# ---- LLFF ----------------------------------------------------------------------------------------

def nerf_pytorch_poses(poses_bounds: np.ndarray) -> np.ndarray:
    """load_llff_data(recenter=True, bd_factor=.75) re-derived: (n, 17) -> recentred c2w (n, 3, 4)."""
    llff = poses_bounds[:, :15].reshape(-1, 3, 5)
    down, right, back, t = (llff[:, :, i] for i in range(4))
    c2w = np.stack([right, -down, back, t], axis=-1)
    c2w[:, :, 3] /= poses_bounds[:, 15:].min() * 0.75
    z = c2w[:, :, 2].sum(0) / np.linalg.norm(c2w[:, :, 2].sum(0))
    x = np.cross(c2w[:, :, 1].sum(0), z)
    x /= np.linalg.norm(x)
    average = np.eye(4)
    average[:3] = np.stack([x, np.cross(z, x), z, c2w[:, :, 3].mean(0)], axis=-1)
    full = np.concatenate([c2w, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(c2w), 1, 1))], axis=1)
    return (np.linalg.inv(average) @ full)[:, :3]


def test_llff_poses_follow_nerf_pytorch(tmp_path):
    poses_bounds = turning_llff(tmp_path)
    dataset = load_dataset(tmp_path, factor=4)
    c2w = np.stack([camera.matrix() for camera in dataset.cameras])
    np.testing.assert_allclose(c2w[:, :3], nerf_pytorch_poses(poses_bounds), atol=2e-5)
    np.testing.assert_allclose(c2w[:, :3, 3].mean(0), 0.0, atol=1e-5)  # recentred: the mean centre is the origin
    camera = dataset.cameras[0]
    assert (camera.width, camera.height, camera.cx, camera.cy) == (20, 15, 10.0, 7.5)
    assert camera.fx == camera.fy == pytest.approx(70.0 / 4)
    assert dataset.ndc.tan_half_fov_x == pytest.approx(20 / (2 * 17.5))
    assert dataset.ndc.tan_half_fov_y == pytest.approx(15 / (2 * 17.5))
    assert dataset.splits == {"train": (1, 2, 3, 4, 5, 6, 7), "val": (0, 8), "test": (0, 8)}
    assert (dataset.near, dataset.far, dataset.aabb) == (0.0, 1.0, (-1.5, -1.5, -1.0, 1.5, 1.5, 1.0))
    np.testing.assert_allclose(dataset.images[3], 30 / 255, atol=1e-7)


def test_llff_picks_the_smallest_folder_wide_enough(tmp_path):
    turning_llff(tmp_path)
    assert load_dataset(tmp_path, resolution=20, with_images=False).cameras[0].fx == pytest.approx(17.5)
    at_30 = load_dataset(tmp_path, resolution=30).cameras[0]  # images_2 (40 px) downscaled to 30
    assert (at_30.width, at_30.height, at_30.fx) == (30, 23, pytest.approx(35.0 * 30 / 40))
    with pytest.raises(UserError, match="no LLFF image folder is at least 41 px wide"):
        load_dataset(tmp_path, resolution=41)
    with pytest.raises(UserError, match=r"images_8 not found \(available: images_2, images_4\)"):
        load_dataset(tmp_path, factor=8)


def test_llff_bad_input(tmp_path):
    turning_llff(tmp_path, extra_images=1)
    with pytest.raises(UserError, match="holds 10 images but poses_bounds.npy has 9 poses"):
        load_dataset(tmp_path, factor=2)
    np.save(tmp_path / "poses_bounds.npy", np.zeros((9, 15)))
    with pytest.raises(UserError, match=r"must hold an \(n, 17\) number array"):
        load_dataset(tmp_path, factor=2)
    np.save(tmp_path / "poses_bounds.npy", np.full((9, 17), np.inf))
    with pytest.raises(UserError, match="non-finite"):
        load_dataset(tmp_path, factor=2)
    np.save(tmp_path / "poses_bounds.npy", np.zeros((9, 17)))
    with pytest.raises(UserError, match="focal lengths and depth bounds must be positive"):
        load_dataset(tmp_path, factor=2)
    np.save(tmp_path / "poses_bounds.npy", np.array([{"pickled": 1}], dtype=object))
    with pytest.raises(UserError, match="cannot read .*poses_bounds.npy"):
        load_dataset(tmp_path, factor=2)


def test_real_fern_at_width_126(shared_data):
    fern = shared_data / "scenes" / "llff" / "fern"
    poses_bounds = np.load(fern / "poses_bounds.npy")
    dataset = load_dataset(fern, resolution=126)
    assert dataset.kind == "llff" and dataset.images.shape == (20, 95, 126, 3)
    focal_8 = np.float32(poses_bounds[0, 14] / 8)  # images_8 (504 px) is the smallest folder ≥ 126 px
    camera = dataset.cameras[0]
    assert (camera.width, camera.height) == (126, 95)
    assert camera.fx == pytest.approx(focal_8 * 126 / 504, rel=1e-6)
    assert dataset.ndc.tan_half_fov_x == pytest.approx(504 / (2 * focal_8), rel=1e-6)
    assert dataset.ndc.tan_half_fov_y == pytest.approx(95 / (2 * camera.fx), rel=1e-6)
    c2w = np.stack([camera.matrix() for camera in dataset.cameras])
    np.testing.assert_allclose(c2w[:, :3], nerf_pytorch_poses(poses_bounds), atol=2e-5)
    assert dataset.splits["test"] == (0, 8, 16) and len(dataset.splits["train"]) == 17
    assert 0.0 <= dataset.images.min() and dataset.images.max() <= 1.0
