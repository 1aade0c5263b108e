"""`noisenerf import-ingp`: Instant-NGP snapshots written from the documented format (tests/helpers.ngp_snapshot,
random weights) import as hashgrid scenes whose field equals Instant-NGP's network evaluated independently on the
snapshot's own parameters (helpers.ngp_spec_field), whose cameras are the snapshot's, and which hide photos
exactly; hostile snapshots are refused in one line."""

from __future__ import annotations

import gzip
import zlib

import numpy as np
import pytest

from helpers import (
    IngpNetwork, assert_hides_exactly, assert_refused, look_at_cameras, ngp_parameters, ngp_snapshot, ngp_spec_field, run_main,
    write_ingp, write_png,
)
from noisenerf.cli.main import main
from noisenerf.runtime.camera import pixel_rays
from noisenerf.runtime.model import load_model

SMALL = IngpNetwork(levels=4, features=2, log2_table=10, base_resolution=4, width=16, colour_layers=1)
CENTRE = (0.5, 0.5, 0.5)


def snapshot_of(network: IngpNetwork, seed: int = 0, size: int = 12, **options) -> tuple[dict, np.ndarray]:
    params = ngp_parameters(network, seed)
    poses = look_at_cameras(6, 1.3, CENTRE, size, seed)
    return ngp_snapshot(network, params, poses, size, **options), params


def field_points(aabb, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(aabb[:3]), np.asarray(aabb[3:])
    points = (lo + rng.uniform(0, 1, (n, 3)) * (hi - lo)).astype(np.float32)
    directions = rng.normal(size=(n, 3))
    return points, (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)


@pytest.fixture(scope="module")
def small_import(tmp_path_factory):
    """A small snapshot (float32 parameters, raw .msgpack), imported and exported through the command line."""
    folder = tmp_path_factory.mktemp("ingp")
    snapshot, params = snapshot_of(SMALL, seed=3, params_type="float")
    path = write_ingp(folder / "small.msgpack", snapshot)
    assert main(["import-ingp", str(path), "-o", str(folder / "scene")]) in (0, None)
    assert main(["export", str(folder / "scene"), "-o", str(folder / "model.onnx")]) in (0, None)
    return folder, snapshot, params


def test_the_default_network_imports_and_equals_instant_ngps_field(tmp_path, capfd):
    """configs/nerf/base.json's size (8 levels x 4 features, 2^19 entries: 11.7 M parameters in float16),
    gzip-compressed as zstr writes .ingp: the imported field equals the independent evaluation of the snapshot."""
    from noisenerf.train.scene.scene import load_scene

    network = IngpNetwork()
    snapshot, params = snapshot_of(network, seed=1)
    assert snapshot["snapshot"]["n_params"] == 64 * 32 + 16 * 64 + 64 * 32 + 64 * 64 + 16 * 64 + (16 ** 3 + 32 ** 3 + 64 ** 3 + 5 * 2 ** 19) * 4
    path = write_ingp(tmp_path / "lego.ingp", snapshot)
    assert path.read_bytes()[:2] == b"\x1f\x8b"
    result = run_main(main, ["import-ingp", path, "-o", tmp_path / "scene"], capfd)
    assert result.code in (0, None), result.err
    assert "8 levels x 4 features, 2^19 entries; 6 cameras" in result.out
    scene = load_scene(tmp_path / "scene")
    aabb = scene.config.aabb
    assert aabb == (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    points, directions = field_points(aabb, 4000, 2)
    import torch
    with torch.no_grad():
        rgb, sigma = scene.render_field(torch.from_numpy(points), torch.from_numpy(directions))
    want_rgb, want_sigma = ngp_spec_field(network, params, points, directions, aabb)
    assert np.abs(rgb.numpy() - want_rgb).max() < 2e-5
    assert np.allclose(sigma.numpy().ravel(), want_sigma, rtol=2e-4, atol=1e-9)


def test_field_through_onnxruntime_equals_instant_ngps(small_import):
    folder, snapshot, params = small_import
    model = load_model(folder / "model.onnx")
    aabb = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    points, directions = field_points(aabb, 3000, 4)
    rgb, sigma = model.field(points, directions)
    want_rgb, want_sigma = ngp_spec_field(SMALL, params.astype(np.float32), points, directions, aabb)
    assert np.abs(rgb - want_rgb).max() < 2e-5
    assert np.allclose(np.ravel(sigma), want_sigma, rtol=2e-4, atol=1e-9)


def test_cameras_are_the_snapshots(small_import):
    """Instant-NGP's xforms (its camera axes: y down, looking along +z) as OpenGL cameras in its frame: a pixel
    centre's ray is the direction Instant-NGP's pixel_to_ray gives, ((u − c)·res/f, 1) through its matrix."""
    folder, snapshot, _ = small_import
    model = load_model(folder / "model.onnx")
    dataset = snapshot["snapshot"]["nerf"]["dataset"]
    for camera, xform, meta in zip(model.cameras, dataset["xforms"], dataset["metadata"], strict=True):
        ngp = np.array(xform["start"])
        width, height = meta["resolution"]
        assert (camera.width, camera.height) == (width, height)
        assert np.allclose(camera.matrix()[:3, 3], ngp[:, 3])
        x, y = 3, 7
        u = np.array([(x + 0.5) / width, (y + 0.5) / height])
        local = np.append((u - meta["principal_point"]) * np.array([width, height]) / meta["focal_length"], 1.0)
        want = ngp[:, :3] @ local
        _, directions = pixel_rays(camera, np.array([x + 0.5]), np.array([y + 0.5]))
        assert np.allclose(directions[0] / np.linalg.norm(directions[0]), want / np.linalg.norm(want), atol=1e-6)


def test_a_photo_hidden_in_a_snapshot_reveals_exactly(small_import, tmp_path, capfd):
    folder, _, _ = small_import
    rng = np.random.default_rng(5)
    secret = write_png(tmp_path / "secret.png", rng.integers(0, 256, (8, 9, 3), dtype=np.uint8))
    assert_hides_exactly(folder, secret, 2, capfd)


def test_the_capture_gives_the_cameras_moved_into_instant_ngps_frame(tmp_path, capfd):
    """--data: the capture's transforms.json (NeRF frame) through nerf_matrix_to_ngp with the snapshot's scale 0.33
    and offset 0.5: the same cameras as the snapshot's own xforms."""
    import json

    snapshot, _ = snapshot_of(SMALL, seed=6)
    poses_ngp = [np.vstack([np.array(x["start"]) * np.array([1.0, -1.0, -1.0, 1.0]), [0, 0, 0, 1]])
                 for x in snapshot["snapshot"]["nerf"]["dataset"]["xforms"]]
    frames = []
    for k, pose in enumerate(poses_ngp):
        nerf = np.eye(4)
        nerf[:3] = pose[[2, 0, 1]]  # undo the cycle xyz <- yzx
        nerf[:3, 3] = (nerf[:3, 3] - 0.5) / 0.33
        frames.append({"file_path": f"images/{k}.png", "transform_matrix": nerf.tolist()})
    (tmp_path / "capture").mkdir()
    (tmp_path / "capture" / "transforms.json").write_text(json.dumps(
        {"fl_x": 13.2, "fl_y": 13.2, "cx": 6.0, "cy": 6.0, "w": 12, "h": 12, "frames": frames}))
    path = write_ingp(tmp_path / "s.ingp", snapshot)
    for name, extra in (("own", []), ("capture", ["--data", tmp_path / "capture"])):
        result = run_main(main, ["import-ingp", path, "-o", tmp_path / f"scene_{name}", *extra], capfd)
        assert result.code in (0, None), result.err
    own, capture = (json.loads((tmp_path / f"scene_{name}" / "scene.json").read_text())["cameras"] for name in ("own", "capture"))
    for a, b in zip(own, capture, strict=True):
        assert np.allclose(a["c2w"], b["c2w"], atol=1e-9) and np.allclose([a["fx"], a["cx"]], [b["fx"], b["cx"]])


def test_a_lego_fit_written_as_a_snapshot_imports_and_hides_exactly(shared_data, tmp_path, capfd):
    """`noisenerf fit`'s code fits lego (32 px, 400 steps: 25 dB) with Instant-NGP's own network
    (FitConfig.tcnn_layout: 8 levels x 4 features, no biases, the colour MLP reading all 16 density outputs); written
    as a snapshot
    (float16, Instant-NGP's frame), it imports to Instant-NGP's field evaluated independently, renders what the
    fit renders (its weights rounded to float16), and hides a photo exactly."""
    import dataclasses

    import torch

    from helpers import scene_snapshot
    from noisenerf.train.scene.datasets import load_dataset
    from noisenerf.train.scene.fit import PRESETS, Budget, fit
    from noisenerf.train.scene.hashgrid import HashGridConfig
    from noisenerf.train.scene.occupancy import OccupancyConfig
    from noisenerf.train.scene.scene import load_scene

    config = dataclasses.replace(PRESETS["hashgrid"], field=HashGridConfig(levels=8, features=4, log2_table=15,
                                                                            geo_features=16), tcnn_layout=True,
                                 occupancy=OccupancyConfig(warmup_steps=20), render_samples=None)
    dataset = load_dataset(shared_data / "scenes" / "blender" / "lego", resolution=32)
    report = fit(dataset, tmp_path / "fit", config, Budget(iters=400), torch.device("cpu"), curve_seconds=0,
                 test_share=None)
    assert report["test"]["psnr"] > 22
    fitted = load_scene(tmp_path / "fit")
    snapshot, network, params = scene_snapshot(fitted)
    path = write_ingp(tmp_path / "lego.ingp", snapshot)
    result = run_main(main, ["import-ingp", path, "-o", tmp_path / "scene"], capfd)
    assert result.code in (0, None), result.err
    assert main(["export", str(tmp_path / "scene"), "-o", str(tmp_path / "model.onnx")]) in (0, None)
    model = load_model(tmp_path / "model.onnx")
    aabb = (-1.0, -1.0, -1.0, 2.0, 2.0, 2.0)
    assert model.grid.aabb.tolist() == list(aabb)
    points, directions = field_points(aabb, 3000, 5)
    rgb, sigma = model.field(points, directions)
    want_rgb, want_sigma = ngp_spec_field(network, params, points, directions, aabb)
    assert np.abs(rgb - want_rgb).max() < 2e-5 and np.allclose(np.ravel(sigma), want_sigma, rtol=2e-4, atol=1e-9)
    with torch.no_grad():
        fit_rgb, fit_sigma = fitted.render_field(torch.from_numpy(points - 0.5), torch.from_numpy(directions))
    assert np.abs(rgb - fit_rgb.numpy()).max() < 0.02  # the same field, weights rounded to float16
    secret = write_png(tmp_path / "secret.png", np.random.default_rng(2).integers(0, 256, (8, 10, 3), dtype=np.uint8))
    assert_hides_exactly(tmp_path, secret, 3, capfd)


def hostile(tmp_path, case):
    snapshot, _ = snapshot_of(SMALL, seed=8)
    inner = snapshot["snapshot"]
    path = tmp_path / "s.ingp"
    if case == "sdf":
        inner["mode"] = "sdf"
    if case == "old":
        inner["version"] = 0
    if case == "short params":
        inner["params_binary"] = inner["params_binary"][:-2]
    if case == "wrong count":
        inner["n_params"] += 16
    if case == "nan params":
        inner["params_binary"] = b"\x00\x7e" + inner["params_binary"][2:]
    if case == "nan scale":
        snapshot["encoding"]["per_level_scale"] = float("nan")
    if case == "frequency":
        snapshot["encoding"]["otype"] = "Frequency"
    if case == "sigmoid":
        snapshot["rgb_network"]["activation"] = "Sigmoid"
    if case == "latents":
        inner["nerf"]["dataset"]["n_extra_learnable_dims"] = 16
    if case == "ftheta":
        inner["nerf"]["dataset"]["metadata"][0]["lens"] = {"ftheta_p0": 1.0}
    write_ingp(path, snapshot)
    if case == "truncated":
        path.write_bytes(path.read_bytes()[:-100])
    if case == "bomb":  # 600 MiB of zeros deflate to about 600 KB
        stream = zlib.compressobj(9, zlib.DEFLATED, 31)
        chunk = bytes(2 ** 24)
        path.write_bytes(b"".join(stream.compress(chunk) for _ in range(38)) + stream.flush())
    if case == "junk":
        path.write_bytes(b"\xc1" * 1000)
    if case == "not msgpack object":
        path.write_bytes(gzip.compress(b"\x93\x01\x02\x03"))
    return path


@pytest.mark.parametrize("case, message", [
    ("sdf", "an Instant-NGP 'sdf' snapshot; only NeRF snapshots import"),
    ("old", "snapshot version 0"),
    ("short params", "parameters in"),
    ("wrong count", "but the network config lays out"),
    ("nan params", "NaN or infinite values"),
    ("nan scale", "per_level_scale"),
    ("frequency", "only HashGrid imports"),
    ("sigmoid", "only ReLU with no output activation imports"),
    ("latents", "per-image latent codes"),
    ("ftheta", "a ftheta_p0 lens is not reproduced"),
    ("truncated", "the compressed stream ends early"),
    ("bomb", "inflates to more than 536870912 bytes"),
    ("junk", "not an Instant-NGP snapshot (msgpack"),
    ("not msgpack object", "not an Instant-NGP snapshot (no 'snapshot' object)"),
])
def test_hostile_and_unsupported_snapshots_are_refused_in_one_line(tmp_path, capfd, case, message):
    path = hostile(tmp_path, case)
    result = run_main(main, ["import-ingp", path, "-o", tmp_path / "out"], capfd)
    assert_refused(result, tmp_path / "out", message)


def test_the_python_api_imports_as_the_command_line_does(tmp_path):
    import noisenerf

    snapshot, _ = snapshot_of(SMALL, seed=9)
    report = noisenerf.import_ingp(write_ingp(tmp_path / "s.ingp", snapshot), tmp_path / "scene")
    assert (report["cameras"], report["levels"], report["features"], report["log2_table"]) == (6, 4, 2, 10)
    with pytest.raises(noisenerf.UserError, match="not found"):
        noisenerf.import_ingp(tmp_path / "missing.ingp", tmp_path / "other")
    assert not (tmp_path / "other").exists()
