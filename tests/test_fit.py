"""Fitting on the procedural scene: it learns, skips, checkpoints, resumes to the same weights, and
refuses bad input through the CLI with one line and exit code 2."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from helpers import assert_refused, run_main, tiny_fit
from noisenerf.runtime.errors import UserError
from noisenerf.train.scene.datasets import load_dataset
from noisenerf.train.scene.fit import Budget, Fitter, fit, held_out_quality, held_out_views, pooled_quality
from noisenerf.train.scene.fit_proposal import ProposalFitter
from noisenerf.train.scene.occupancy import carve
from noisenerf.train.scene.procedural import write_procedural_dataset
from noisenerf.train.scene.random_scene import SMALL_HASHGRID
from noisenerf.train.scene.scene import load_scene

CPU = torch.device("cpu")
TINY, TINY_HASHGRID = tiny_fit("mlp"), tiny_fit("hashgrid")
BOTH_KINDS = pytest.mark.parametrize("config", [TINY, TINY_HASHGRID], ids=["mlp", "hashgrid"])
TINY_NERFACTO = tiny_fit("nerfacto")
EVERY_KIND = pytest.mark.parametrize("config", [
    TINY, TINY_HASHGRID, dataclasses.replace(TINY_NERFACTO, proposal=dataclasses.replace(TINY_NERFACTO.proposal,
                                                                                         appearance_dim=8))],
    ids=["mlp", "hashgrid", "nerfacto with appearance"])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    folder = write_procedural_dataset(tmp_path_factory.mktemp("data") / "scene", size=24, n_train=12, n_val=1,
                                      n_test=2)
    return load_dataset(folder)


def quiet_fit(dataset, out, iters, config=TINY):
    return fit(dataset, out, config, Budget(iters=iters), CPU, curve_seconds=0, test_share=None)


def test_closing_test_renders_stop_at_their_budget_and_the_views_left_pool_to_every_view(dataset, tmp_path):
    whole = quiet_fit(dataset, tmp_path / "scene", 10)["test"]
    views, scene = held_out_views(dataset), load_scene(tmp_path / "scene")
    assert (whole["views"], whole["held_out"], len(views)) == (2, 2, 2)
    first = held_out_quality(scene, dataset, views, seconds=0.0)  # the first view always, then none
    assert (first["views"], first["held_out"], [s["view"] for s in first["per_view"]]) == (1, 2, views[:1])
    assert pooled_quality([first, held_out_quality(scene, dataset, views[1:])]) == whole


def test_fit_says_how_many_held_out_views_its_closing_renders_took(tmp_path, capfd, monkeypatch):
    from noisenerf.cli.main import main
    import noisenerf.train.scene.fit as fit_module

    folder = write_procedural_dataset(tmp_path / "d", size=16, n_train=4, n_val=0, n_test=2)
    monkeypatch.setattr(fit_module, "TEST_SHARE", 0.0)
    args = ["fit", folder, "--iters", "3", "--quiet", "--device", "cpu", "--field", "mlp"]
    result = run_main(main, [*args, "-o", tmp_path / "budget"], capfd)
    assert result.code == 0, result.err
    assert "over 1 of 2 held-out views (1 more would have taken the closing renders past a tenth of the training " \
           "time: --all-test-views)" in result.out
    result = run_main(main, [*args, "-o", tmp_path / "all", "--all-test-views"], capfd)
    assert result.code == 0, result.err
    assert "over 2 of 2 held-out views\n" in result.out


@BOTH_KINDS
def test_fit_learns_and_skips(dataset, tmp_path, config):
    report = quiet_fit(dataset, tmp_path / "scene", 120, config)
    assert report["steps"] == 120
    assert report["test"]["psnr"] > 12.0  # a grey guess scores about 9 dB on this scene
    assert report["test"]["samples_evaluated"] < report["test"]["samples_dense"] / 2
    scene = load_scene(tmp_path / "scene")
    assert scene.fingerprint() == report["fingerprint"]
    assert 0.0 < scene.grid.occupancy_fraction() < 0.9


@EVERY_KIND
def test_resume_after_interruption_gives_identical_weights(dataset, tmp_path, monkeypatch, config):
    whole = quiet_fit(dataset, tmp_path / "whole", 40, config)
    fitter = ProposalFitter if config.proposal else Fitter
    step = fitter.train_step

    def interrupted(self, lr):
        if self.step == 25:
            raise KeyboardInterrupt
        return step(self, lr)

    monkeypatch.setattr(fitter, "train_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit(dataset, tmp_path / "resumed", config, Budget(iters=40), CPU, checkpoint_seconds=0, curve_seconds=0)
    assert not (tmp_path / "resumed" / "scene.json").exists()
    monkeypatch.setattr(fitter, "train_step", step)
    resumed = quiet_fit(dataset, tmp_path / "resumed", 40, config)
    assert resumed["resumed"] and resumed["steps"] == 40
    assert resumed["fingerprint"] == whole["fingerprint"]


def test_checkpoint_of_another_fit_is_refused(dataset, tmp_path):
    quiet_fit(dataset, tmp_path / "scene", 5)
    with pytest.raises(UserError, match="checkpoint of a different fit"):
        quiet_fit(dataset, tmp_path / "scene", 5, dataclasses.replace(TINY, seed=7))


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "noisenerf.cli.main", *args], capture_output=True, text=True)


@pytest.mark.parametrize("args, message", [
    (["fit", "{missing}", "-o", "{out}", "--iters", "1"], "dataset folder not found"),
    (["fit", "{data}", "-o", "{out}"], "exactly one of --minutes"),
    (["hide", "{out}", "{data}/x.png", "-o", "{out}/s.bundle"], "not a scene directory"),
    (["fit", "{data}", "-o", "{out}", "--iters", "1", "--field", "hashgrid", "--preset", "small"],
     "preset small fits the mlp kind, not hashgrid"),
    (["fit", "{data}", "-o", "{out}", "--iters", "1", "--field", "nerfacto", "--preset", "hashgrid"],
     "preset hashgrid fits the hashgrid kind, not nerfacto"),
])
def test_cli_bad_input_is_one_line_and_exit_2(dataset, tmp_path, args, message):
    data = tmp_path / "data"
    data.mkdir()
    (data / "transforms_train.json").write_text("{}")
    fill = {"missing": tmp_path / "missing", "out": tmp_path / "out", "data": data, "nowhere": tmp_path / "no"}
    assert_refused(run_cli(*[a.format(**fill) for a in args]), None, message)


def test_fit_json_is_one_object_on_stdout(dataset, tmp_path):
    folder = write_procedural_dataset(tmp_path / "d", size=16, n_train=4, n_val=0, n_test=1)
    result = run_cli("fit", str(folder), "-o", str(tmp_path / "s"), "--iters", "3", "--json", "--quiet",
                     "--device", "cpu")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["steps"] == 3 and np.isfinite(report["test"]["psnr"])


def test_a_scene_renders_with_its_render_samples_through_the_finer_final_grid(dataset, tmp_path):
    config = dataclasses.replace(TINY_HASHGRID, render_samples=48,
                                 occupancy=dataclasses.replace(TINY_HASHGRID.occupancy, final_resolution=32))
    report = quiet_fit(dataset, tmp_path / "scene", 60, config)
    scene = load_scene(tmp_path / "scene")
    assert scene.config.render.sampling.n_samples == 48 and scene.config.grid_resolution == 32
    test_pixels = sum(dataset.cameras[i].width * dataset.cameras[i].height for i in dataset.splits["test"])
    assert report["test"]["samples_dense"] == 48 * test_pixels  # the report renders as recipients will
    train = list(dataset.splits["train"])
    hull = carve([dataset.cameras[i] for i in train], dataset.alphas[train], dataset.aabb, 32)
    assert scene.grid.occupied.shape == (32, 32, 32) and scene.grid.occupied.any()
    assert not (scene.grid.occupied & ~hull).any()  # only the hull's cells were evaluated


def test_a_hashgrid_fit_records_its_kind_and_the_datasets_box(dataset, tmp_path):
    quiet_fit(dataset, tmp_path / "scene", 3, TINY_HASHGRID)
    scene_json = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert scene_json["coarse"]["kind"] == "hashgrid" and "kind" not in json.loads(json.dumps(TINY.field.to_dict()))
    assert scene_json["coarse"]["aabb"] == list(dataset.aabb)
    assert load_scene(tmp_path / "scene").coarse.config == SMALL_HASHGRID.in_box(dataset.aabb)
