"""The Python API (`noisenerf.reveal`, `noisenerf.render`): the CLI's results and refusals, from paths or bytes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import noisenerf
from helpers import hidden_bundle, readme_python, run_reveal
from noisenerf.cli.main import main as noisenerf_main
from noisenerf.runtime.images import read_native, write_image
from noisenerf.runtime.sealing import NOT_SEALED, WRONG


@pytest.fixture(scope="module")
def sealed_note(reveal_inputs, tmp_path_factory):
    """(bundle, its payload's bytes): a file sealed with the passphrase "api"."""
    folder, _, _ = reveal_inputs
    work = tmp_path_factory.mktemp("api")
    (work / "note.txt").write_bytes(b"under the third stone\n")
    (work / "pass.txt").write_text("api")
    code = noisenerf_main([str(a) for a in ("hide", folder / "scene", "--file", work / "note.txt", "-o",
                                            work / "note.bundle", "--passphrase-file", work / "pass.txt", "--quiet")])
    assert code == 0
    return work / "note.bundle", (work / "note.txt").read_bytes()


def test_reveal_from_paths_or_bytes_is_the_cli_reveal(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    told = []
    from_paths = noisenerf.reveal(model, bundle, progress=told.append)
    from_bytes = noisenerf.reveal(model.read_bytes(), bundle.read_bytes())
    assert from_paths.kind == from_bytes.kind == "image" and from_paths.exact and from_bytes.exact
    np.testing.assert_array_equal(from_paths.pixels, from_bytes.pixels)
    assert from_paths.sha256 == hidden_bundle(bundle, model).secret_sha256
    rays = from_paths.width * from_paths.height
    assert told[-1] == noisenerf.ProgressEvent("render", rays, rays, "ray") and from_paths.rays == rays
    assert [event.done for event in told] == sorted(event.done for event in told)
    assert run_reveal(model, bundle, "-o", tmp_path / "cli.png").returncode == 0
    assert from_paths.save(tmp_path / "api.png") == {"written": "8-bit values"}
    assert (tmp_path / "api.png").read_bytes() == (tmp_path / "cli.png").read_bytes()
    with pytest.raises(noisenerf.UserError, match="output exists"):
        from_paths.save(tmp_path / "api.png")


def test_a_sealed_file_comes_back_with_its_name_and_bytes(reveal_inputs, sealed_note):
    _, model, _ = reveal_inputs
    bundle, body = sealed_note
    note = noisenerf.reveal(model, bundle, passphrase="api")
    assert (note.kind, note.name, note.bytes, note.sealed, note.exact) == ("file", "note.txt", body, True, True)
    assert note.pixels is None
    for passphrase, message, code in ((None, "the bundle is sealed", "seal.no_passphrase"),
                                      ("API", WRONG, "seal.wrong_passphrase"), (b"ap", WRONG, "seal.wrong_passphrase")):
        with pytest.raises(noisenerf.UserError, match=message) as refused:
            noisenerf.reveal(model, bundle, passphrase=passphrase)
        assert (refused.value.code, refused.value.params) == (code, {})


def test_a_passphrase_for_an_unsealed_bundle_is_refused(reveal_inputs):
    _, model, bundle = reveal_inputs
    with pytest.raises(noisenerf.UserError) as refused:
        noisenerf.reveal(model, bundle, passphrase="anything")
    assert (str(refused.value), refused.value.code) == (NOT_SEALED, "seal.not_sealed")


def test_render_is_the_cli_view_render(reveal_inputs, tmp_path):
    _, model, _ = reveal_inputs
    view = noisenerf.render(model, 2)
    result = run_reveal(model, "--view", 2, "-o", tmp_path / "v.png", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert (report["samples"], report["samples_dense"], report["skip"]) == (view.samples, view.samples_dense, True)
    np.testing.assert_array_equal(read_native(tmp_path / "v.png"), view.pixels)
    dense = noisenerf.render(model, 2, skip=False)
    unskipped = json.loads(run_reveal(model, "--view", 2, "-o", tmp_path / "d.png", "--json", "--no-skip").stdout)
    assert (dense.samples, dense.skip) == (unskipped["samples"], False) and view.samples <= dense.samples
    np.testing.assert_array_equal(read_native(tmp_path / "d.png"), dense.pixels)


def test_bad_input_is_the_cli_line(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    with pytest.raises(noisenerf.UserError, match="^bundle not found: "):
        noisenerf.reveal(model, tmp_path / "missing.bundle")
    with pytest.raises(noisenerf.UserError, match="^not a readable safetensors bundle: the bundle"):
        noisenerf.reveal(model, b"\x00" * 40)
    with pytest.raises(noisenerf.UserError, match="view"):
        noisenerf.render(model, 10 ** 6)
    write_image(tmp_path / "x.png", np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(noisenerf.UserError, match="lossy"):
        noisenerf.reveal(model, bundle).save(tmp_path / "x.jpg")


def test_import_noisenerf_loads_nothing_heavy_until_used():
    code = ("import sys, noisenerf\n"
            "assert 'onnxruntime' not in sys.modules and 'torch' not in sys.modules\n"
            "noisenerf.reveal\n"
            "assert 'onnxruntime' in sys.modules and 'torch' not in sys.modules\n"
            "try:\n    noisenerf.nothing\nexcept AttributeError as error:\n    print(error)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "module 'noisenerf' has no attribute 'nothing'"


# ---- the sender's half ------------------------------------------------------------------------------

def test_the_readme_sender_snippet_runs_as_written(tmp_path):
    result = subprocess.run([sys.executable, "-c", readme_python("Python API")[1]], capture_output=True, text=True,
                            cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "True True True" and result.stderr == ""


def test_hide_from_an_array_is_the_cli_hide_of_its_file(reveal_inputs, tmp_path, capfd):
    """Same secret, same seed: the API from an array and the CLI from a PNG write byte-identical bundles, and the
    API reports its progress up to every pixel, without printing."""
    folder, model, _ = reveal_inputs
    secret = np.random.default_rng(8).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    write_image(tmp_path / "s.png", secret)
    events = []
    report = noisenerf.hide(folder / "scene", secret, tmp_path / "api.bundle", tile_size=16, progress=events.append)
    assert report["exact"] and "precision" not in report
    assert events[-1] == noisenerf.ProgressEvent("hide", 240, 240, "px") and capfd.readouterr() == ("", "")
    code = noisenerf_main([str(a) for a in ("hide", folder / "scene", tmp_path / "s.png", "-o", tmp_path / "cli.bundle",
                                            "--tile-size", 16, "--quiet")])
    assert code == 0 and (tmp_path / "api.bundle").read_bytes() == (tmp_path / "cli.bundle").read_bytes()
    from_path = noisenerf.hide(folder / "scene", tmp_path / "s.png", tmp_path / "path.bundle", tile_size=16)
    assert (from_path["precision"], from_path["warnings"]) == ("8-bit", [])
    assert noisenerf.reveal(model, tmp_path / "api.bundle").exact


def test_hide_a_file_given_as_bytes_and_sealed(reveal_inputs, tmp_path):
    folder, model, _ = reveal_inputs
    report = noisenerf.hide(folder / "scene", output=tmp_path / "b.bundle", file=b"\x00\x01 raw bytes",
                            file_name="raw.bin", passphrase="pass")
    assert report["sealed"] and report["payload"]["name"] == "raw.bin"
    opened = noisenerf.reveal(model, tmp_path / "b.bundle", passphrase="pass")
    assert (opened.kind, opened.name, opened.bytes) == ("file", "raw.bin", b"\x00\x01 raw bytes")


@pytest.mark.parametrize("call, message", [
    (lambda scene, out: noisenerf.hide(scene, None, out), "give exactly one of SECRET_IMAGE or --file PAYLOAD"),
    (lambda scene, out: noisenerf.hide(scene, np.zeros((4, 4, 3), np.float32), out), "must be (h, w, 3) or (h, w) uint8"),
    (lambda scene, out: noisenerf.hide(scene, np.zeros((4, 4), np.uint8), out, method="magic"), "unknown method"),
    (lambda scene, out: noisenerf.hide(scene, np.zeros((4, 4), np.uint8), out, device="tpu"), "unknown --device"),
    (lambda scene, out: noisenerf.fit(scene, out), "give exactly one of --minutes M or --iters N"),
    (lambda scene, out: noisenerf.export_model(scene / "missing", out), "not a scene directory (no scene.json)"),
])
def test_the_sender_refuses_with_the_cli_line(reveal_inputs, tmp_path, call, message):
    folder, _, _ = reveal_inputs
    with pytest.raises(noisenerf.UserError, match=message.replace("(", r"\(").replace(")", r"\)")):
        call(folder / "scene", tmp_path / "out")
    assert not (tmp_path / "out").exists()


WRONG_TYPES = [  # (call on (scene, model, bundle, out), argument, expected, got)
    (lambda s, m, b, o: noisenerf.reveal(np.zeros(3), b), "model", "a path (str or os.PathLike) or bytes", "ndarray"),
    (lambda s, m, b, o: noisenerf.reveal(m, 7), "bundle", "a path (str or os.PathLike) or bytes", "int"),
    (lambda s, m, b, o: noisenerf.reveal(m, b, 5), "passphrase", "a str or bytes", "int"),
    (lambda s, m, b, o: noisenerf.reveal(m, b, threads="2"), "threads", "an integer", "str"),
    (lambda s, m, b, o: noisenerf.reveal(m, b, progress=3), "progress", "a function", "int"),
    (lambda s, m, b, o: noisenerf.render(m, "3"), "view", "an integer", "str"),
    (lambda s, m, b, o: noisenerf.render(m, 1.0), "view", "an integer", "float"),
    (lambda s, m, b, o: noisenerf.render(m, True), "view", "an integer", "bool"),
    (lambda s, m, b, o: noisenerf.hide(s, np.zeros((4, 4, 3), np.uint8), o, view=1.5), "view", "an integer", "float"),
    (lambda s, m, b, o: noisenerf.hide(s, 3, o), "secret",
     "a path (str or os.PathLike) or an (h, w, 3) uint8 array", "int"),
    (lambda s, m, b, o: noisenerf.hide(s, output=o, file=np.zeros(3)), "file", "a path (str or os.PathLike) or bytes",
     "ndarray"),
    (lambda s, m, b, o: noisenerf.hide(s, np.zeros((4, 4, 3), np.uint8), np.zeros(2)), "output",
     "a path (str or os.PathLike)", "ndarray"),
    (lambda s, m, b, o: noisenerf.hide(12, np.zeros((4, 4, 3), np.uint8), o), "scene",
     "a scene folder (str or os.PathLike) or a Scene", "int"),
    (lambda s, m, b, o: noisenerf.fit(s, o, iters="5"), "iters", "an integer", "str"),
    (lambda s, m, b, o: noisenerf.export_model(s, o, force=1), "force", "True or False", "int"),
    (lambda s, m, b, o: noisenerf.import_nerfstudio(None, o), "run", "a path (str or os.PathLike)", "NoneType"),
]


@pytest.mark.parametrize("call, argument, expected, got", WRONG_TYPES)
def test_an_argument_of_the_wrong_kind_is_a_user_error_naming_it(reveal_inputs, tmp_path, call, argument, expected,
                                                                 got):
    folder, model, bundle = reveal_inputs
    with pytest.raises(noisenerf.UserError) as refused:
        call(folder / "scene", model, bundle, tmp_path / "out")
    assert str(refused.value) == f"{argument} must be {expected}, not {got}"
    assert (refused.value.code, refused.value.params) == (
        "api.argument", {"argument": argument, "expected": expected, "got": got})
    assert list(tmp_path.iterdir()) == []


def test_numpy_integers_are_integers(reveal_inputs):
    _, model, _ = reveal_inputs
    assert noisenerf.render(model, np.int64(1)).view == 1


def test_fit_reports_its_steps_and_writes_a_scene(tmp_path):
    from noisenerf.train.scene.procedural import write_procedural_dataset

    data = write_procedural_dataset(tmp_path / "data", size=16, n_train=4, n_val=1, n_test=1)
    events = []
    report = noisenerf.fit(data, tmp_path / "scene", iters=2, device="cpu", progress=events.append)
    assert report["steps"] == 2 and (tmp_path / "scene" / "scene.json").is_file()
    assert [event.done for event in events] == [1, 2] and {event.stage for event in events} == {"fit"}
    assert events[-1].detail.startswith("loss ")
    exported = noisenerf.export_model(tmp_path / "scene", tmp_path / "m.onnx")
    assert exported["fingerprint"] == report["fingerprint"]


def test_every_public_name_is_the_api_not_a_subpackage():
    """A subpackage imported as noisenerf.<name> would shadow a lazy name (noisenerf.export is the package)."""
    import types

    import noisenerf.cli.main  # noqa: F401  (imports export, runtime, train)
    for name in noisenerf.API:
        assert not isinstance(getattr(noisenerf, name), types.ModuleType), name
