"""One reader of a capture's transforms.json (train.scene.captures) for the fit and the nerfstudio import: files
exactly as Instant-NGP's colmap2nerf.py and nerfstudio's ns-process-data write them, the same cameras from both
readers where their conventions coincide, and malformed files refused by both in the same one line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import assert_refused, run_main, write_png
from noisenerf.cli.main import main
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.lens import Lens
from noisenerf.train.scene.captures import read_capture
from noisenerf.train.scene.datasets import load_dataset
from noisenerf.train.scene.import_nerfstudio import dataset_cameras

# what ns-process-data writes for COLMAP data (nerfstudio/process_data/colmap_utils.py, colmap_to_json)
NS_APPLIED = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [-0.0, -1.0, -0.0, -0.0]]


def random_poses(n: int, seed: int = 4) -> np.ndarray:
    """n OpenGL c2w: rotations from QR, positions around (1, 2, 3). -> (n, 4, 4)."""
    rng = np.random.default_rng(seed)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        c2w[k, :3, :3] = q * np.sign(np.linalg.det(q))
        c2w[k, :3, 3] = [1.0, 2.0, 3.0] + rng.normal(size=3)
    return c2w


def write_transforms(folder, top: dict, frames: list[dict], size=(8, 6)):
    """transforms.json of `top` keys and `frames` (listed in reverse), and each frame's image (grey, size)."""
    for frame in frames:
        write_png(folder / frame["file_path"], np.full((size[1], size[0], 3), 60, np.uint8))
    (folder / "transforms.json").write_text(json.dumps({**top, "frames": frames[::-1]}, indent=2))
    return folder


def colmap2nerf(folder, n=4):
    """As Instant-NGP's scripts/colmap2nerf.py writes one COLMAP PINHOLE camera: sizes and principal point as
    floats, both focal lengths and both angles, every coefficient (0: COLMAP's PINHOLE has none), is_fisheye,
    aabb_scale 16, "./images/…" paths and each frame's sharpness."""
    w, h, fl_x, fl_y = 8.0, 6.0, 7.0, 7.5
    top = {"camera_angle_x": math.atan(w / (fl_x * 2)) * 2, "camera_angle_y": math.atan(h / (fl_y * 2)) * 2,
           "fl_x": fl_x, "fl_y": fl_y, "k1": 0, "k2": 0, "k3": 0, "k4": 0, "p1": 0, "p2": 0, "is_fisheye": False,
           "cx": 4.25, "cy": 2.75, "w": w, "h": h, "aabb_scale": 16}
    frames = [{"file_path": f"./images/{k + 1:04d}.png", "sharpness": 80.5 + k, "transform_matrix": c2w.tolist()}
              for k, c2w in enumerate(random_poses(n))]
    return write_transforms(folder, top, frames)


def ns_process_data(folder, n=4, lens=(0.0, 0.0, 0.0, 0.0)):
    """As nerfstudio's ns-process-data writes one COLMAP camera: integer sizes, camera_model OPENCV, k1 k2 p1 p2
    (`lens`), applied_transform, ply_file_path, each frame's colmap_im_id."""
    k1, k2, p1, p2 = lens
    top = {"w": 8, "h": 6, "fl_x": 7.0, "fl_y": 7.5, "cx": 4.25, "cy": 2.75, "k1": k1, "k2": k2, "p1": p1, "p2": p2,
           "camera_model": "OPENCV", "applied_transform": NS_APPLIED, "ply_file_path": "sparse_pc.ply"}
    frames = [{"file_path": f"images/frame_{k + 1:05d}.png", "transform_matrix": c2w.tolist(), "colmap_im_id": k + 1}
              for k, c2w in enumerate(random_poses(n))]
    return write_transforms(folder, top, frames)


def test_a_colmap2nerf_file_reads_as_written(tmp_path):
    capture = read_capture(colmap2nerf(tmp_path))
    frame = capture.frames[0]
    assert (frame.width, frame.height) == (8, 6) and isinstance(frame.width, int)
    assert frame.file_path == "./images/0004.png" and frame.path == tmp_path / "images" / "0004.png"
    assert (frame.sharpness, frame.model, frame.distortion) == (83.5, None, (0.0,) * 6)
    assert capture.aabb_scale == 16 and capture.applied_transform is None and capture.applied_scale == 1.0
    dataset = load_dataset(tmp_path)
    assert dataset.aabb == (-16.0,) * 3 + (16.0,) * 3 and all(c.lens is None for c in dataset.cameras)
    assert {(c.width, c.height, c.fx, c.fy, c.cx, c.cy) for c in dataset.cameras} == {(8, 6, 7.0, 7.5, 4.25, 2.75)}


def test_an_ns_process_data_file_reads_as_written(tmp_path):
    lens = (-0.05, 0.01, 0.002, -0.001)
    capture = read_capture(ns_process_data(tmp_path, lens=lens))
    frame = capture.frames[0]
    assert frame.model == "OPENCV" and frame.distortion == (-0.05, 0.01, 0.0, 0.0, 0.002, -0.001)
    assert frame.camera() == frame.camera((8, 6))
    assert (frame.camera().width, frame.camera().fy) == (8, 7.5)
    np.testing.assert_array_equal(frame.camera().c2w, random_poses(4)[3])
    np.testing.assert_array_equal(capture.applied_transform, NS_APPLIED)
    dataset = load_dataset(tmp_path)
    assert {c.lens for c in dataset.cameras} == {Lens("opencv", (-0.05, 0.01, 0.0, 0.0, 0.002, -0.001))}
    cameras = dataset_cameras(tmp_path, np.eye(4)[:3], 1.0, None)  # the import: the lens as nerfstudio bends rays
    assert {camera.lens for camera in cameras} == {Lens("opencv", (-0.05, 0.01, 0.0, 0.0, 0.002, -0.001))}


def nerfstudio_normalization(poses: np.ndarray) -> tuple[np.ndarray, float]:
    """nerfstudio's default dataparser (camera_utils.auto_orient_and_center_poses, method "up", center "poses",
    then auto_scale_poses) in float64: its transform (3, 4) and scale, as dataparser_transforms.json holds them."""
    up = poses[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    v = np.cross(up, [0.0, 0.0, 1.0])
    skew = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    rotation = np.eye(3) + skew + skew @ skew / (1.0 + up[2])
    transform = np.concatenate([rotation, -rotation @ poses[:, :3, 3].mean(0)[:, None]], 1)
    return transform, 1.0 / np.abs((transform @ poses)[:, :3, 3]).max()


@pytest.mark.parametrize("write", [colmap2nerf, ns_process_data])
def test_the_fit_and_the_import_build_the_same_cameras(tmp_path, write):
    """Where the conventions coincide (the dataparser's transform and scale those the fit normalises by, as
    nerfstudio's default dataparser finds them; no downscale; frames named so that both orders agree), the
    fit's cameras and the import's are the same: intrinsics to the bit (a frame's own fl_x and cx included),
    poses within float64 rounding. The import undoes the applied_transform ns-process-data wrote."""
    folder = write(tmp_path)
    meta = json.loads((folder / "transforms.json").read_text())
    meta["frames"][1].update(fl_x=9.0, cx=3.5)
    (folder / "transforms.json").write_text(json.dumps(meta))
    fit = load_dataset(folder, with_images=False).cameras
    poses = np.stack([frame["transform_matrix"] for frame in sorted(meta["frames"], key=lambda f: f["file_path"])])
    transform, scale = nerfstudio_normalization(poses)
    if "applied_transform" in meta:  # dataparser_transforms.json holds the transform from the original coordinates
        transform = transform @ np.vstack([meta["applied_transform"], [0, 0, 0, 1]])
    imported = dataset_cameras(folder, transform, scale, None)
    assert [(c.width, c.height, c.fx, c.fy, c.cx, c.cy) for c in imported] == \
        [(c.width, c.height, c.fx, c.fy, c.cx, c.cy) for c in fit]
    assert sum(c.fx == 9.0 for c in fit) == 1
    np.testing.assert_allclose(np.array([c.c2w for c in imported]), np.array([c.c2w for c in fit]), atol=1e-12)


def edit(change):
    def apply(meta):
        change(meta)
        return meta
    return apply


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(w=1080.5), "transforms.json frame 0: 'w' must be a whole number, got 1080.5"),
    (lambda d: d["frames"][2].update(h=float("nan")), "transforms.json frame 2: 'h' must be a whole number, got nan"),
    (lambda d: d.update(w="8"), "transforms.json frame 0: image width must be an integer, got '8'"),
    (lambda d: d.update(fl_x=float("nan")), "transforms.json frame 0: 'fl_x' must be a finite number in"),
    (lambda d: d["frames"][1].update(fl_y=0.0), "transforms.json frame 1: 'fl_y' must be a finite number in"),
    (lambda d: d["frames"][1].pop("transform_matrix"),
     "transforms.json frame 1: needs a numeric 4x4 'transform_matrix'"),
    (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, 1e300),
     "frame 0: 'transform_matrix' must be a finite 4x4 matrix (numbers within ±1e+09)"),
    (lambda d: d["frames"][0].update(transform_matrix=d["frames"][0]["transform_matrix"][:3]),
     "frame 0: 'transform_matrix' must be a finite 4x4 matrix"),
    (lambda d: d.update(w=20000), "transforms.json frame 0: image width must be between 1 and 16384, got 20000"),
    (lambda d: d.update(w=16384, h=16384),
     "transforms.json frame 0: image is 16384x16384, more than the 67108864 pixels"),
    (lambda d: d.update(cx=2e9), "transforms.json frame 0: 'cx' must be a finite number in"),
    (lambda d: d.update(camera_angle_x=4.0), "'camera_angle_x' must be a finite number in"),
    (lambda d: d.update(is_fisheye="no"), "transforms.json: 'is_fisheye' must be true or false, got 'no'"),
    (lambda d: d["frames"][3].update(camera_model="EQUIRECTANGULAR"),
     "transforms.json frame 3: camera_model 'EQUIRECTANGULAR' is not supported"),
    (lambda d: d.update(k1=2e3), "transforms.json frame 0: lens k1 must be a finite number in"),
    (lambda d: d.update(camera_model="SIMPLE_PINHOLE", k2=0.1),
     "camera_model SIMPLE_PINHOLE has no distortion, yet k2"),
    (lambda d: d.update(distortion_params=[0.0] * 4), "'distortion_params' must hold 6 items, got 4"),
    (lambda d: d.update(distortion_params=[0.0, float("inf"), 0.0, 0.0, 0.0, 0.0]),
     "'distortion_params' k2 must be"),
    (lambda d: d.update(applied_transform=[[0.0] * 4] * 3),
     "'applied_transform' has a rotation that is not invertible"),
    (lambda d: d.update(applied_transform=[[1.0, 0.0, 0.0]] * 3), "'applied_transform' must be a finite 3x4 matrix"),
    (lambda d: d.update(applied_scale=0.0), "'applied_scale' must be a finite number in"),
    (lambda d: d.update(aabb_scale=float("nan")), "'aabb_scale' must be a finite number in [1.0, 128]"),
    (lambda d: d["frames"][0].update(sharpness=float("inf")), "frame 0: 'sharpness' must be a finite number"),
    (lambda d: d.update(frames=[]), "transforms.json: 'frames' lists no frames"),
])
def test_malformed_files_are_refused_by_both_in_one_line(tmp_path, capfd, change, message):
    """The same refusal from the reader, the fit's command line (one line, nothing written) and the import."""
    folder = ns_process_data(tmp_path / "data")
    path = folder / "transforms.json"
    path.write_text(json.dumps(edit(change)(json.loads(path.read_text()))))
    with pytest.raises(UserError) as refused:
        read_capture(folder)
    assert message in str(refused.value) and "\n" not in str(refused.value)
    result = run_main(main, ["fit", folder, "-o", tmp_path / "scene", "--iters", "1", "--device", "cpu"], capfd)
    assert_refused(result, tmp_path / "scene", message)
    with pytest.raises(UserError) as imported:
        dataset_cameras(folder, np.eye(4)[:3], 1.0, None)
    assert str(imported.value) == str(refused.value)


def test_what_one_reader_alone_refuses(tmp_path):
    """The fit needs two frames and no k4 (its lens lacks the r^8 term), and takes w and h from the images; the
    import, which reads no image, needs them."""
    folder = ns_process_data(tmp_path)
    path = folder / "transforms.json"
    meta = json.loads(path.read_text())
    path.write_text(json.dumps({**meta, "k4": 0.01}))
    with pytest.raises(UserError, match="frame 3: k4 is not supported"):
        load_dataset(folder)
    path.write_text(json.dumps({key: value for key, value in meta.items() if key not in ("w", "h")}))
    assert load_dataset(folder, with_images=False).cameras[0].width == 8
    with pytest.raises(UserError, match=r"transforms.json frame 3: needs the image's size, 'w' and 'h'"):
        dataset_cameras(folder, np.eye(4)[:3], 1.0, None)
    path.write_text(json.dumps({**meta, "frames": meta["frames"][:1]}))
    with pytest.raises(UserError, match="needs at least two frames"):
        load_dataset(folder)
    assert len(dataset_cameras(folder, np.eye(4)[:3], 1.0, None)) == 1
