"""Dataset loading: NeRF-Synthetic, LLFF (nerf-pytorch's pose processing) and captures (Instant-NGP's and
nerfstudio's transforms.json, lens distortion included), real lego/fern, bad input."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from helpers import (assert_refused, read_raw, run_main, run_reveal, tiny_fit, turning_llff, write_blender,
                     write_png)
from noisenerf.cli.main import main
from noisenerf.runtime.camera import Camera, camera_rays
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.lens import Lens, undistort
from noisenerf.train.scene import procedural
from noisenerf.train.scene.datasets import load_dataset, view_rays
from noisenerf.train.scene.fit import Budget, fit
from noisenerf.runtime.images import read_native, write_image
from noisenerf.train.scene.procedural import procedural_secret, write_procedural_dataset

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


# ---- captures: one transforms.json ---------------------------------------------------------------

LENS = {"k1": -0.05, "k2": 0.01, "k3": 0.001, "p1": 0.002, "p2": -0.001}
CAPTURE_TOP = {"camera_model": "OPENCV", "w": 8, "h": 6, "fl_x": 7.0, "fl_y": 7.5, "cx": 4.2, "cy": 2.9,
               "aabb_scale": 4, **LENS}


def capture_poses(n: int) -> np.ndarray:
    """n seeded random OpenGL c2w: rotations from QR, positions around (1, 2, 3). -> (n, 4, 4)."""
    rng = np.random.default_rng(5)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        c2w[k, :3, :3] = q * np.sign(np.linalg.det(q))  # a rotation, not a reflection
        c2w[k, :3, 3] = [1.0, 2.0, 3.0] + rng.normal(size=3)
    return c2w


def write_capture(folder, n=10, top=CAPTURE_TOP, own=None):
    """A transforms.json capture: frame k is images/frame_0000k.png, flat grey 20·k (8×6), pose
    capture_poses(n)[k], `own` {k: keys} its own intrinsics; the JSON lists the frames shuffled."""
    frames = []
    for k, c2w in enumerate(capture_poses(n)):
        write_png(folder / "images" / f"frame_{k:05d}.png", np.full((6, 8, 3), 20 * k, np.uint8))
        frames.append({"file_path": f"images/frame_{k:05d}.png", "transform_matrix": c2w.tolist(),
                       **(own or {}).get(k, {})})
    order = np.random.default_rng(1).permutation(n)
    (folder / "transforms.json").write_text(json.dumps({**top, "frames": [frames[k] for k in order]}))
    return folder


def test_capture_cameras_intrinsics_and_splits(tmp_path):
    folder = write_capture(tmp_path, own={3: {"fl_x": 9.0, "cy": 3.1, "k1": -0.1}})
    dataset = load_dataset(folder, resolution=4)  # 8×6 -> 4×3: both axes halve
    assert dataset.kind == "capture" and dataset.images.shape == (10, 3, 4, 3)
    np.testing.assert_allclose(dataset.images[:, 0, 0, 0], np.arange(10) * 20 / 255, atol=1e-6)  # sorted by file
    intrinsics = [(c.width, c.height, c.fx, c.fy, c.cx, c.cy) for c in dataset.cameras]
    assert intrinsics == [(4, 3, 3.5, 3.75, 2.1, 1.45)] * 3 + [(4, 3, 4.5, 3.75, 2.1, 1.55)] + [intrinsics[0]] * 6
    lens = six(tuple(LENS.values()))
    assert [c.lens for c in dataset.cameras] == [Lens("opencv", lens)] * 3 + [Lens("opencv", (-0.1,) + lens[1:])] + \
        [Lens("opencv", lens)] * 6
    assert dataset.splits == {"train": (1, 2, 3, 4, 5, 6, 7, 9), "val": (0, 8), "test": (0, 8)}
    assert (dataset.near, dataset.ndc, dataset.aabb, dataset.alphas) == (0.05, None, (-4.0,) * 3 + (4.0,) * 3, None)
    # nerfstudio's "up" + "poses" + auto scale, as properties: one rotation R for all cameras, taking the mean
    # up vector to +z about their common perpendicular, positions s · R (t − mean t) with max |coordinate| 1
    given, loaded = capture_poses(10), np.stack([np.asarray(camera.c2w) for camera in dataset.cameras])
    rotation = loaded[0, :3, :3] @ given[0, :3, :3].T
    np.testing.assert_allclose(loaded[:, :3, :3], rotation @ given[:, :3, :3], atol=1e-12)
    up = given[:, :3, 1].mean(0) / np.linalg.norm(given[:, :3, 1].mean(0))
    np.testing.assert_allclose(rotation @ up, [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(rotation @ np.cross(up, [0, 0, 1]), np.cross(up, [0, 0, 1]), atol=1e-12)
    centred = (given[:, :3, 3] - given[:, :3, 3].mean(0)) @ rotation.T
    np.testing.assert_allclose(loaded[:, :3, 3], centred / np.abs(centred).max(), atol=1e-12)
    corners = np.array([[x, y, z] for x in (-4, 4) for y in (-4, 4) for z in (-4, 4)])
    assert dataset.far == pytest.approx(np.linalg.norm(loaded[:, None, :3, 3] - corners, axis=-1).max())
    bare = load_dataset(folder, resolution=4, with_images=False)
    assert bare.images is None and bare.cameras == dataset.cameras


def test_capture_defaults_of_instant_ngp_files(tmp_path):
    """No camera_model, no w/h/cx/cy/fl_y, only camera_angle_x: the image's size, its centre, square pixels."""
    folder = write_capture(tmp_path, n=2, top={"camera_angle_x": 1.2})
    dataset = load_dataset(folder)
    camera = dataset.cameras[1]
    assert (camera.width, camera.height, camera.cx, camera.cy) == (8, 6, 4.0, 3.0)
    assert camera.fx == camera.fy == pytest.approx(4.0 / math.tan(0.6))
    assert all(c.lens is None for c in dataset.cameras) and dataset.aabb == (-1.0,) * 3 + (1.0,) * 3
    assert dataset.splits == {"train": (1,), "val": (0,), "test": (0,)}


PHONE_LENS = (-0.12, 0.08, -0.02, 0.001, -0.0015)  # k1, k2, k3, p1, p2: a strong phone wide angle


def six(coefficients: tuple[float, ...]) -> tuple[float, ...]:
    """OpenCV's k1, k2, k3, p1, p2 as runtime.lens's six (k4 = 0)."""
    return tuple(coefficients[:3]) + (0.0,) + tuple(coefficients[3:])


def opencv_project(points, fx, fy, cx, cy, lens):
    """OpenCV's projectPoints as its documentation writes it: points (n, 3) in OpenCV's camera frame (x right,
    y down, z forward) -> u, v (n,) pixels."""
    k1, k2, k3, p1, p2 = lens
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    r2 = x ** 2 + y ** 2
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return (fx * (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x ** 2)) + cx,
            fy * (y * radial + p1 * (r2 + 2 * y ** 2) + 2 * p2 * x * y) + cy)


@pytest.mark.parametrize("coefficients", [tuple(LENS.values()), PHONE_LENS])
def test_undistortion_inverts_the_lens_over_the_whole_image(coefficients):
    """OpenCV's distortion of the undistorted point is the pixel again, within 1e-5 px, on a grid reaching the
    corners of a wide 640×480 view."""
    fx, fy, cx, cy = 352.0, 355.0, 321.5, 238.0
    u, v = (g.ravel() for g in np.meshgrid(np.linspace(0, 640, 81), np.linspace(0, 480, 61)))
    x, y = undistort((u - cx) / fx, (v - cy) / fy, six(coefficients))
    back_u, back_v = opencv_project(np.stack([x, y, np.ones_like(x)], axis=1), fx, fy, cx, cy, coefficients)
    np.testing.assert_allclose(back_u, u, atol=1e-5)
    np.testing.assert_allclose(back_v, v, atol=1e-5)
    assert np.hypot(fx * x + cx - u, fy * y + cy - v).max() > 5.0  # the lens does move the corners


def test_distorted_rays_project_back_onto_their_pixels():
    """Each ray, projected with OpenCV's model (y down) in its camera's frame, lands on its pixel's centre."""
    c2w = np.eye(4)
    c2w[:3, :3] = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0]
    c2w[:3, 3] = [0.5, -1.0, 2.0]
    camera = Camera(tuple(map(tuple, c2w)), 40, 30, 22.0, 22.5, 20.3, 14.6)
    origins, directions = camera_rays(dataclasses.replace(camera, lens=Lens("opencv", six(PHONE_LENS))), 0.5)
    assert origins.shape == directions.shape == (1200, 3) and directions.dtype == np.float32
    np.testing.assert_allclose(origins, np.broadcast_to(c2w[:3, 3], (1200, 3)), atol=1e-6)
    local = directions.astype(np.float64) @ c2w[:3, :3]  # world -> camera: OpenGL, looking down −z
    np.testing.assert_allclose(local[:, 2], -1.0, atol=1e-5)
    u, v = opencv_project(local * [1.0, -1.0, -1.0], 22.0, 22.5, 20.3, 14.6, PHONE_LENS)  # OpenGL -> OpenCV axes
    j, i = np.indices((30, 40))
    np.testing.assert_allclose(u, i.ravel() + 0.5, atol=2e-4)
    np.testing.assert_allclose(v, j.ravel() + 0.5, atol=2e-4)


def test_a_lens_that_folds_over_is_refused():
    """k1 = −1 folds the image back at r = 0.58: the corners of this wide view have no undistorted point."""
    camera = Camera(tuple(map(tuple, np.eye(4))), 40, 30, 22.0, 22.0, 20.0, 15.0)
    with pytest.raises(UserError, match=r"a opencv lens \(-1.0, 0.0, 0.0, 0.0, 0.0, 0.0\) cannot be undone across "
                                        "a 40x30 image"):
        camera_rays(dataclasses.replace(camera, lens=Lens("opencv", six((-1.0, 0.0, 0.0, 0.0, 0.0)))), 0.5)


def test_training_rays_of_a_procedural_capture_see_its_pixels(tmp_path, monkeypatch):
    """One ray a pixel (no supersampling), rendered through the written lens: the loader's rays, taken back to
    the scene's world through each frame's written pose, shade every pixel as the photo shows it; pinhole rays
    do not."""
    monkeypatch.setattr(procedural, "SUPERSAMPLE", 1)
    folder = write_procedural_dataset(tmp_path / "capture", size=32, n_train=2, n_val=0, n_test=1, format="capture")
    meta = json.loads((folder / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["k1"] == -0.05
    names = [frame["file_path"] for frame in meta["frames"]]
    assert names != sorted(names) and sum("fl_x" in frame for frame in meta["frames"]) == 1
    dataset = load_dataset(folder)
    assert dataset.images.shape == (3, 24, 32, 3) and all(c.lens is not None for c in dataset.cameras)
    for index, frame in enumerate(sorted(meta["frames"], key=lambda f: f["file_path"])):
        written, loaded = np.asarray(frame["transform_matrix"]), dataset.cameras[index].matrix().astype(np.float64)
        matching = []
        camera = dataset.cameras[index]
        for origins, directions in (view_rays(camera, 0.5), camera_rays(dataclasses.replace(camera, lens=None), 0.5)):
            world = directions @ loaded[:3, :3] @ written[:3, :3].T
            rgb, hit = procedural.shade(np.broadcast_to(written[:3, 3], world.shape), procedural.unit(world))
            error = np.abs(np.where(hit[:, None], rgb, 1.0) - dataset.images[index].reshape(-1, 3)).max(axis=1)
            matching.append(np.mean(error <= 1 / 255))
        assert matching[0] > 0.995 and matching[1] < 0.98, matching


def edit_capture(edit):
    return lambda folder: edit_json(folder / "transforms.json", edit)


@pytest.mark.parametrize("break_it, message", [
    (edit_capture(lambda d: d.update(camera_model="OPENCV_FISHEYE")), "a fisheye capture is not fitted"),
    (edit_capture(lambda d: d.update(camera_model="EQUIRECTANGULAR")), "camera_model 'EQUIRECTANGULAR' is not"),
    (edit_capture(lambda d: d.update(is_fisheye=True)), "a fisheye capture is not fitted"),
    (edit_capture(lambda d: d.pop("fl_x")), r"transforms.json frame \d: needs a focal length, 'fl_x' or"),
    (edit_capture(lambda d: d["frames"][1].update(fl_x=-3)), r"transforms.json frame 1: 'fl_x' must be a finite"),
    (edit_capture(lambda d: d["frames"][2]["transform_matrix"][1].__setitem__(2, float("nan"))),
     "transforms.json frame 2: 'transform_matrix' must be a finite 4x4 matrix"),
    (edit_capture(lambda d: d["frames"][0].update(transform_matrix=np.zeros((4, 4)).tolist())),
     "frame 0: 'transform_matrix' has a rotation that is not invertible"),
    (edit_capture(lambda d: d.update(w=0)), r"transforms.json frame \d: image width must be between 1 and"),
    (edit_capture(lambda d: d.update(w=10)), "w and h say 10x6, but .*frame_0000.\\.png is 8x6"),
    (edit_capture(lambda d: d.update(k2=float("inf"))), "'k2' must be a finite number"),
    (edit_capture(lambda d: d.update(camera_model="PINHOLE")), "camera_model PINHOLE has no distortion, yet k1"),
    (edit_capture(lambda d: d.update(aabb_scale=0.5)), "'aabb_scale' must be a finite number in \\[1.0, 128"),
    (edit_capture(lambda d: d.update(frames=d["frames"][:1])), "needs at least two frames with images .*got 1$"),
    (lambda f: [p.unlink() for p in sorted((f / "images").iterdir())[1:]],
     r"needs at least two frames with images .*got 1 \(2 of 3 images missing, the first images/frame_0000[12].png\)"),
    (edit_capture(lambda d: [f["transform_matrix"][r].__setitem__(3, 1.0) for f in d["frames"] for r in range(3)]),
     "all cameras stand at one point"),
])
def test_bad_capture_input_is_one_user_error(tmp_path, break_it, message):
    folder = write_capture(tmp_path, n=3)
    break_it(folder)
    with pytest.raises(UserError, match=message):
        load_dataset(folder)


def test_frames_whose_images_are_missing_are_left_out_and_said(tmp_path, capfd):
    """As Instant-NGP's fox: colmap2nerf.py's transforms.json lists frames whose images were since removed; both
    tools leave them out. The held-out split is every 8th of the frames left, and the fit says what it left out."""
    folder = write_capture(tmp_path / "data", n=10)
    for k in (2, 7):
        (folder / "images" / f"frame_{k:05d}.png").unlink()
    dataset = load_dataset(folder, resolution=4)
    assert dataset.skipped == ("images/frame_00002.png", "images/frame_00007.png")
    assert len(dataset.cameras) == 8 and dataset.splits == {"train": (1, 2, 3, 4, 5, 6, 7), "val": (0,), "test": (0,)}
    np.testing.assert_allclose(dataset.images[:, 0, 0, 0], np.array([0, 1, 3, 4, 5, 6, 8, 9]) * 20 / 255, atol=1e-6)
    folder = write_procedural_dataset(tmp_path / "procedural", size=32, n_train=7, n_val=0, n_test=2, format="capture")
    removed = sorted(json.loads((folder / "transforms.json").read_text())["frames"], key=lambda f: f["file_path"])[3:5]
    for frame in removed:
        (folder / frame["file_path"]).unlink()
    result = run_main(main, ["fit", folder, "-o", tmp_path / "scene", "--iters", "2", "--resolution", "24",
                             "--quiet", "--device", "cpu"], capfd)
    assert result.code == 0, result.err
    names = ", ".join(frame["file_path"] for frame in removed)
    assert f"left out 2 frames whose images are missing ({names})" in result.out


def test_fit_refuses_a_fisheye_capture_in_one_line(tmp_path, capfd):
    folder = write_capture(tmp_path / "data", n=2, top={**CAPTURE_TOP, "camera_model": "OPENCV_FISHEYE"})
    result = run_main(main, ["fit", folder, "-o", tmp_path / "scene", "--iters", "1", "--device", "cpu"], capfd)
    assert_refused(result, tmp_path / "scene", "a fisheye capture is not fitted")


def test_fit_runs_on_a_distorted_capture(tmp_path, capfd):
    folder = write_procedural_dataset(tmp_path / "data", size=32, n_train=7, n_val=0, n_test=2, format="capture")
    result = run_main(main, ["fit", folder, "-o", tmp_path / "scene", "--minutes", "0.05", "--resolution", "24",
                             "--json", "--quiet", "--device", "cpu", "--all-test-views"], capfd)
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["test"]["views"] == 2 and np.isfinite(report["test"]["psnr"])
    assert json.loads((tmp_path / "scene" / "scene.json").read_text())["cameras"][0]["width"] == 24


def test_a_distorted_capture_fits_hides_and_reveals_end_to_end(tmp_path, capfd):
    """transforms.json with lens distortion -> a hash-grid fit (the test PSNR of held-out frames rendered along
    their lens's rays; the CLI's fit on a capture is the test above) -> export -> hide at a held-out camera ->
    an exact reveal, through the command lines."""
    folder = write_procedural_dataset(tmp_path / "data", size=32, n_train=14, n_val=0, n_test=2, format="capture")
    dataset = load_dataset(folder, resolution=24)
    report = fit(dataset, tmp_path / "scene", tiny_fit("hashgrid"), Budget(iters=300), torch.device("cpu"),
                 curve_seconds=0, test_share=None)
    assert report["test"]["views"] == 2 and report["test"]["psnr"] > 16.0  # a grey guess scores about 9 dB
    assert run_main(main, ["export", tmp_path / "scene", "-o", tmp_path / "model.onnx"], capfd).code == 0
    secret = tmp_path / "secret.png"
    write_image(secret, procedural_secret(24, 18, seed=5))
    hidden = run_main(main, ["hide", tmp_path / "scene", secret, "-o", tmp_path / "s.bundle", "--view",
                             dataset.splits["test"][0], "--quiet", "--device", "cpu"], capfd)
    assert hidden.code == 0, hidden.err
    result = run_reveal(tmp_path / "model.onnx", tmp_path / "s.bundle", "-o", tmp_path / "out.png", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["exact"] is True
    assert np.array_equal(read_native(tmp_path / "out.png")[..., :3], procedural_secret(24, 18, seed=5))
