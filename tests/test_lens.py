"""Cameras with lenses (runtime.lens): nerfstudio's radial-tangential and fisheye rays, checked by projecting each ray
back through the forward model onto its pixel; stored, checked and refused like every camera number; hidden in and
revealed exactly, in a random scene and in an imported nerfstudio run of a distorted capture."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

import noisenerf
from helpers import lens_scene, run_reveal, write_nerfstudio_run
from noisenerf.runtime.camera import Camera, camera_rays
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.lens import Lens, distort
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import look_at_origin

PHONE = Lens("opencv", (-0.12, 0.03, -0.004, 0.0005, 0.001, -0.0008))  # a phone's barrel distortion, all six terms
FISHEYE = Lens("fisheye", (0.05, -0.01, 0.002, -0.0003, 0.0, 0.0))


def lens_camera(lens: Lens | None) -> Camera:
    camera = Camera.from_fov(look_at_origin(np.array([3.0, -2.0, 1.0])), 37, 23, 1.4)
    return dataclasses.replace(camera, cx=17.3, cy=12.1, fy=camera.fx * 1.01, lens=lens)


@pytest.mark.parametrize("lens", [PHONE, FISHEYE], ids=["opencv", "fisheye"])
def test_each_ray_projects_back_through_the_lens_onto_its_pixel(lens):
    """Independent of the inversion: the ray's camera-space direction, projected (pinhole or equidistant) and
    distorted by the forward model, lands on the pixel centre it was shot through."""
    camera = lens_camera(lens)
    _, rays_d = camera_rays(camera, 0.5)
    local = rays_d.astype(np.float64) @ camera.matrix()[:3, :3].astype(np.float64)  # R is orthonormal: R⁻¹ = Rᵀ
    if lens.model == "opencv":
        x, y = local[:, 0] / -local[:, 2], local[:, 1] / -local[:, 2]
    else:
        theta = np.arctan2(np.hypot(local[:, 0], local[:, 1]), -local[:, 2])
        radius = np.hypot(local[:, 0], local[:, 1])
        x, y = theta * local[:, 0] / radius, theta * local[:, 1] / radius
    x_d, y_d = distort(x, -y, lens.coefficients)  # OpenGL's y up to OpenCV's down
    j, i = np.indices((camera.height, camera.width))
    assert np.abs(camera.fx * x_d + camera.cx - (i.ravel() + 0.5)).max() < 2e-3
    assert np.abs(camera.fy * y_d + camera.cy - (j.ravel() + 0.5)).max() < 2e-3
    _, pinhole = camera_rays(dataclasses.replace(camera, lens=None), 0.5)
    assert np.abs(rays_d / np.linalg.norm(rays_d, axis=1, keepdims=True)
                  - pinhole / np.linalg.norm(pinhole, axis=1, keepdims=True)).max() > 1e-3  # the lens bends them


def test_a_lens_of_zeros_is_the_pinhole_and_a_pinhole_states_no_lens():
    zeros = lens_camera(Lens("opencv", (0.0,) * 6))
    np.testing.assert_allclose(camera_rays(zeros, 0.5)[1], camera_rays(dataclasses.replace(zeros, lens=None), 0.5)[1],
                               rtol=0, atol=2e-7)
    assert "lens" not in lens_camera(None).to_dict()  # what every camera before lenses wrote
    assert Camera.from_dict(lens_camera(PHONE).to_dict()) == lens_camera(PHONE)


@pytest.mark.parametrize("lens, code", [
    ({"model": "equirectangular", "k1": 0, "k2": 0, "k3": 0, "k4": 0, "p1": 0, "p2": 0}, "camera.lens"),
    ({"model": "opencv", "k1": 0, "k2": 0, "k3": 0, "k4": 0, "p1": 0}, "camera.lens"),
    ({"model": "opencv", "k1": 2e3, "k2": 0, "k3": 0, "k4": 0, "p1": 0, "p2": 0}, "camera.lens_coefficient"),
    ({"model": "opencv", "k1": float("nan"), "k2": 0, "k3": 0, "k4": 0, "p1": 0, "p2": 0}, "camera.lens_coefficient"),
    ({"model": "fisheye", "k1": 0, "k2": 0, "k3": 0, "k4": 0, "p1": 0.1, "p2": 0}, "camera.lens_coefficient"),
    ({"model": "opencv", "k1": -5, "k2": 0, "k3": 0, "k4": 0, "p1": 0, "p2": 0}, "camera.lens_folds"),
])
def test_a_lens_a_file_states_is_checked_when_read(lens, code):
    with pytest.raises(UserError) as refused:
        Camera.from_dict({**lens_camera(None).to_dict(), "lens": lens})
    assert refused.value.code == code


@pytest.mark.parametrize("model", ["opencv", "fisheye"])
def test_secrets_hidden_at_a_lens_camera_reveal_exactly_through_onnxruntime(tmp_path, model):
    scene = lens_scene(model)
    assert scene.config.cameras[2].lens.model == model
    scene.save(tmp_path / "scene")
    noisenerf.export_model(tmp_path / "scene", tmp_path / "model.onnx")
    secret = np.random.default_rng(4).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    for layout in ("compact", "ray"):
        report = hide(scene, secret, tmp_path / f"{layout}.bundle", HideConfig(view=2, layout=layout),
                      torch.device("cpu"), workers=1)
        assert report["exact"]
        revealed = noisenerf.reveal(tmp_path / "model.onnx", tmp_path / f"{layout}.bundle")
        assert revealed.exact and np.array_equal(revealed.pixels, secret)


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_a_nerfstudio_run_of_a_distorted_capture_imports_and_hides_at_its_cameras(tmp_path, capfd, model):
    """nerfstudio's dataparser's lens: OPENCV's six coefficients, OPENCV_FISHEYE's k1 to k4 (p1, p2 dropped)."""
    from noisenerf.cli.main import main
    from noisenerf.runtime.model import load_model
    run, data = write_nerfstudio_run(tmp_path, "torch", seed=3)
    transforms = json.loads((data / "transforms.json").read_text())
    transforms.update(camera_model=model, k1=-0.04, k2=0.01, p1=0.002, p2=-0.001)
    (data / "transforms.json").write_text(json.dumps(transforms))
    assert main(["import-nerfstudio", str(run), "-o", str(tmp_path / "scene"), "--data", str(data)]) in (0, None)
    assert main(["export", str(tmp_path / "scene"), "-o", str(tmp_path / "model.onnx")]) in (0, None)
    lenses = {camera.lens for camera in load_model(tmp_path / "model.onnx").cameras}
    expected = (-0.04, 0.01, 0.0, 0.0) + ((0.0, 0.0) if model == "OPENCV_FISHEYE" else (0.002, -0.001))
    assert lenses == {Lens("fisheye" if model == "OPENCV_FISHEYE" else "opencv", expected)}
    secret = np.random.default_rng(1).integers(0, 256, (6, 7, 3), dtype=np.uint8)
    report = noisenerf.hide(tmp_path / "scene", secret, tmp_path / "s.bundle", view=4, workers=1)
    assert report["exact"]
    result = run_reveal(tmp_path / "model.onnx", tmp_path / "s.bundle", "-o", tmp_path / "out.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True, result.stderr
    rendered = run_reveal(tmp_path / "model.onnx", "--view", "4", "-o", tmp_path / "view.png")
    assert rendered.returncode == 0, rendered.stderr
