"""Exact means exact: hard secrets at every camera, revealed through onnxruntime, and never a silent
inexact bundle.

The small version of the bench's coverage sweep (cli/bench/coverage.py): the demo scene at all of its
cameras, a random-weight scene (another fit entirely, whose shared position noise lifts nothing), and
of the hash-grid kind a random-weight scene and a fitted one, each at all of its own cameras, with a
mosaic of every hard secret; single-colour secrets (whose compact basis is
made of that colour alone) at a spread of cameras. Then an unsolvable tile (a solver allowed one
iteration) must stop the hide with exit code 3 and no bundle, unless --allow-inexact.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from helpers import fitted_tiny_scene, hidden_bundle, make_tiny_scene, run_main
from noisenerf.cli.bench.coverage import hard_secrets
from noisenerf.cli.main import main as noisenerf_main
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime.images import write_image
from noisenerf.runtime.model import load_model
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide import exact
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import DEMO_SCENE
from noisenerf.train.scene.scene import Scene, load_scene

SIZE = 8  # px a side of each hard secret in the mosaic


def mosaic(secrets: dict[str, np.ndarray]) -> np.ndarray:
    """Every secret side by side: one hide per camera tries them all."""
    return np.concatenate(list(secrets.values()), axis=1)


SCENES = {"demo": lambda folder: load_scene(DEMO_SCENE), "random weights": lambda folder: make_tiny_scene(seed=4),
          "random hash grid": lambda folder: make_tiny_scene(seed=4, kind="hashgrid"),
          "fitted hash grid": lambda folder: fitted_tiny_scene(folder, "hashgrid")}


@pytest.fixture(scope="module", params=list(SCENES))
def scene_and_model(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp("coverage")
    scene = SCENES[request.param](folder)
    scene.save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    return scene, load_model(folder / "model.onnx"), folder


def hide_and_reveal(scene: Scene, model, secret: np.ndarray, view: int, folder) -> np.ndarray:
    """The secret hidden at `view` (an inexact hide raises) and revealed through onnxruntime."""
    hide(scene, secret, folder / "s.bundle", HideConfig(view=view), torch.device("cpu"), force=True, workers=1)
    return reveal_tiles(hidden_bundle(folder / "s.bundle", model), model.render_config, model.fields()).pixels


def test_every_hard_secret_is_exact_at_every_camera(scene_and_model):
    scene, model, folder = scene_and_model
    secret = mosaic(hard_secrets(SIZE, scene.config.render.background, seed=1))
    for view in range(len(scene.config.cameras)):
        revealed = hide_and_reveal(scene, model, secret, view, folder)
        assert np.array_equal(revealed, secret), f"view {view}: {(revealed != secret).any(-1).sum()} pixels off"


@pytest.mark.parametrize("name", ["white", "black", "background", "near saturated"])
def test_a_secret_of_one_hard_colour_is_exact_across_cameras(scene_and_model, name):
    scene, model, folder = scene_and_model
    secret = hard_secrets(16, scene.config.render.background, seed=2)[name]
    cameras = len(scene.config.cameras)
    for view in range(0, cameras, max(1, cameras // 6)):
        assert np.array_equal(hide_and_reveal(scene, model, secret, view, folder), secret), f"view {view}"


@pytest.fixture
def one_iteration(monkeypatch):
    """Every Levenberg–Marquardt run of the exact solver stops after one iteration: most pixels stay off.
    Patched in this process only, so the hides below run with --workers 1."""
    real_refine = exact.refine

    def refine(problem, *args, **kwargs):
        return real_refine(dataclasses.replace(problem, settings=dataclasses.replace(problem.settings, max_iters=1)),
                           *args, **kwargs)

    monkeypatch.setattr(exact, "refine", refine)


@pytest.fixture
def demo_secret(tmp_path):
    path = tmp_path / "secret.png"
    write_image(path, hard_secrets(12, (1.0, 1.0, 1.0), seed=3)["random bytes"])
    return path


def test_an_unsolvable_tile_stops_the_hide_with_no_bundle(one_iteration, demo_secret, tmp_path, capfd):
    out = tmp_path / "s.bundle"
    result = run_main(noisenerf_main, ["hide", DEMO_SCENE, demo_secret, "-o", out, "--workers", 1, "--quiet"], capfd)
    lines = result.err.splitlines()
    assert result.code == 3 and len(lines) == 1, result
    assert "noisenerf: error: tile 0 (view 0, 12x12 px at x=0, y=0) has " in lines[0]
    assert "pixels off, by up to" in lines[0] and "--allow-inexact writes the bundle anyway" in lines[0]
    assert not out.exists() and any((tmp_path / "s.bundle.partial").glob("*.safetensors"))


def test_allow_inexact_writes_the_bundle_and_says_so(one_iteration, demo_secret, tmp_path, capfd):
    out = tmp_path / "s.bundle"
    result = run_main(noisenerf_main, ["hide", DEMO_SCENE, demo_secret, "-o", out, "--workers", 1, "--quiet",
                                       "--allow-inexact", "--json"], capfd)
    assert result.code == 0, result
    assert result.err.startswith("noisenerf: warning: the bundle is not exact (--allow-inexact): tile 0: ")
    report = json.loads(result.out)
    assert report["exact"] is False and out.is_file() and report["tiles"][0]["inexact_pixels"] > 0


def test_a_payload_is_never_inexact(one_iteration, tmp_path, capfd):
    payload = tmp_path / "note.txt"
    payload.write_bytes(b"every byte or nothing\n" * 20)
    out = tmp_path / "p.bundle"
    refused = run_main(noisenerf_main, ["hide", DEMO_SCENE, "--file", payload, "-o", out, "--workers", 1,
                                        "--quiet", "--allow-inexact"], capfd)
    assert refused.code == 2 and "a payload is revealed whole or not at all" in refused.err
    failed = run_main(noisenerf_main, ["hide", DEMO_SCENE, "--file", payload, "-o", out, "--workers", 1, "--quiet"],
                      capfd)
    assert failed.code == 3 and "pixels off" in failed.err and len(failed.err.splitlines()) == 1
    assert not out.exists()
