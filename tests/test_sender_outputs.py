"""The sender's outputs follow the reveal's rules: nothing replaced without --force, and with it replaced whole.

`import-nerfstudio` and `import-nerf-pytorch` write a scene folder: a new or empty one, or with --force an
earlier scene (never a folder of other files), published in one rename so a folder never holds two scenes.
`export` refuses an existing model without --force. `demo` replaces only an earlier demo's folder.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from helpers import assert_refused, run_main, write_nerfstudio_run
from noisenerf.cli.main import main
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import atomic_folder
from noisenerf.train.scene.procedural import DEMO_SCENE


def digests(folder: Path) -> dict[str, str]:
    """Every file under `folder` (hidden ones too) -> its SHA-256."""
    return {str(path.relative_to(folder)): hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(folder.rglob("*")) if path.is_file()}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two nerfstudio runs with different weights, and the scene the first one imports as."""
    root = tmp_path_factory.mktemp("runs")
    first, data = write_nerfstudio_run(root / "a", "torch", seed=1)
    second, _ = write_nerfstudio_run(root / "b", "torch", seed=2)
    return first, second, data


def imported(tmp_path, capfd, run, data, output, *flags):
    return run_main(main, ["import-nerfstudio", run, "-o", output, "--data", data, *flags], capfd)


def earlier_scene(runs, tmp_path, capfd) -> Path:
    """The first run imported as tmp_path/scene, with an earlier fit's checkpoint beside its weights."""
    first, _, data = runs
    scene = tmp_path / "scene"
    assert imported(tmp_path, capfd, first, data, scene).code in (0, None)
    (scene / "checkpoint.safetensors").write_bytes(b"an earlier fit's checkpoint")
    return scene


def test_an_import_onto_a_scene_is_refused_without_force_and_the_scene_kept(runs, tmp_path, capfd):
    _, second, data = runs
    scene = earlier_scene(runs, tmp_path, capfd)
    before = digests(scene)
    result = imported(tmp_path, capfd, second, data, scene)
    assert_refused(result, None, f"output folder is not empty (pass --force to replace the scene in it): {scene}",
                   exact=True)
    assert digests(scene) == before and sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_force_replaces_the_whole_scene_folder(runs, tmp_path, capfd):
    _, second, data = runs
    scene = earlier_scene(runs, tmp_path, capfd)
    old = digests(scene)
    assert imported(tmp_path, capfd, second, data, scene, "--force").code in (0, None)
    fresh = tmp_path / "fresh"
    assert imported(tmp_path, capfd, second, data, fresh).code in (0, None)
    # the second run's scene alone: no file of the first left beside it, nothing left beside the folder
    assert digests(scene) == digests(fresh) != old and "checkpoint.safetensors" not in digests(scene)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh", "scene"]


@pytest.mark.parametrize("force", [False, True])
def test_a_folder_of_other_files_is_never_replaced(runs, tmp_path, capfd, force):
    first, _, data = runs
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.jpg").write_bytes(b"not ours")
    result = imported(tmp_path, capfd, first, data, folder, *(["--force"] if force else []))
    message = ("output folder holds files but no scene.json: --force replaces an earlier scene, not other files"
               if force else "output folder is not empty (pass --force to replace the scene in it)")
    assert_refused(result, None, message)
    assert digests(folder) == {"holiday.jpg": hashlib.sha256(b"not ours").hexdigest()}


def test_an_import_into_an_empty_folder_writes_the_scene(runs, tmp_path, capfd):
    first, _, data = runs
    (tmp_path / "empty").mkdir()
    assert imported(tmp_path, capfd, first, data, tmp_path / "empty").code in (0, None)
    assert (tmp_path / "empty" / "scene.json").is_file()


def test_export_onto_a_model_is_refused_without_force(tmp_path, capfd):
    model = tmp_path / "model.onnx"
    model.write_bytes(b"an earlier model")
    result = run_main(main, ["export", DEMO_SCENE, "-o", model], capfd)
    assert_refused(result, None, f"output exists (pass --force to overwrite): {model}", exact=True)
    assert model.read_bytes() == b"an earlier model"
    assert run_main(main, ["export", DEMO_SCENE, "-o", model, "--force"], capfd).code in (0, None)
    assert model.read_bytes()[:2] != b"an" and model.stat().st_size > 10_000


def test_the_library_export_refuses_an_existing_model_too(tmp_path):
    import noisenerf

    model = tmp_path / "model.onnx"
    model.write_bytes(b"an earlier model")
    with pytest.raises(UserError, match="output exists"):
        noisenerf.export_model(DEMO_SCENE, model)
    assert model.read_bytes() == b"an earlier model"


def test_the_demo_refuses_a_folder_that_is_not_an_earlier_demo(tmp_path, capfd):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "secret.png").write_bytes(b"my own picture")
    result = run_main(main, ["demo", "-o", tmp_path / "mine", "--quiet"], capfd)
    assert_refused(result, None, "--force replaces an earlier demo, not other files")
    assert (tmp_path / "mine" / "secret.png").read_bytes() == b"my own picture"


def test_a_failed_folder_output_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError), atomic_folder(tmp_path / "out", replace=False, marker="m", what="thing") as tmp:
        (tmp / "half").write_bytes(b"written before the failure")
        raise RuntimeError("the writer failed")
    assert list(tmp_path.iterdir()) == []


def test_a_folder_filled_while_the_output_was_written_is_not_replaced(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(UserError, match="output folder is not empty"):
        with atomic_folder(out, replace=False, marker="m", what="thing") as tmp:
            (tmp / "m").write_bytes(b"new")
            out.mkdir()
            (out / "theirs").write_bytes(b"another writer's")
    assert digests(out) == {"theirs": hashlib.sha256(b"another writer's").hexdigest()}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
