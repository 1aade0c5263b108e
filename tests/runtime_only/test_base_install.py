"""The recipient's install: reveal the demo's bundle with the base package (CI runs these where torch is
not installed; elsewhere they need NOISENERF_DEMO_DIR pointing at a `noisenerf demo` output)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import assert_refused, readme_python, run_reveal

DEMO_DIR = os.environ.get("NOISENERF_DEMO_DIR")


@pytest.fixture(scope="module")
def demo_dir() -> Path:
    if not DEMO_DIR or not (Path(DEMO_DIR) / "secret.bundle").is_file():
        pytest.skip("set NOISENERF_DEMO_DIR to a `noisenerf demo` output folder to run the base-install checks")
    return Path(DEMO_DIR)


def test_reveal_never_loads_torch_and_reports_exactness(demo_dir, tmp_path):
    code = (
        "import json, sys\n"
        "from noisenerf.cli.reveal import main\n"
        f"status = main([{str(demo_dir / 'model.onnx')!r}, {str(demo_dir / 'secret.bundle')!r}, "
        f"'-o', {str(tmp_path / 'out.png')!r}, '--json'])\n"
        "assert status == 0 and 'torch' not in sys.modules and 'onnx' not in sys.modules, sorted(sys.modules)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["exact"] is True
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_base_install_reveal_equals_the_demo_reveal(demo_dir, tmp_path):
    from noisenerf.runtime.images import read_image

    result = run_reveal(demo_dir / "model.onnx", demo_dir / "secret.bundle", "-o", tmp_path / "r.png")
    assert result.returncode == 0, result.stderr
    assert (read_image(tmp_path / "r.png") == read_image(demo_dir / "revealed.png")).all()
    assert (read_image(tmp_path / "r.png") == read_image(demo_dir / "secret.png")).all()


def test_fingerprint_mismatch_is_one_line_and_exit_2(demo_dir, tmp_path):
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.model import load_model
    import dataclasses

    model = load_model(demo_dir / "model.onnx")
    bundle = dataclasses.replace(load_bundle(demo_dir / "secret.bundle", model.mask_secret), model_fingerprint="0" * 64)
    bundle.save(tmp_path / "other.bundle", mask_secret=model.mask_secret)
    result = run_reveal(demo_dir / "model.onnx", tmp_path / "other.bundle", "-o", tmp_path / "r.png")
    assert_refused(result, tmp_path / "r.png", f"bundle was made for model 000000000000…, this model is "
                   f"{model.fingerprint[:12]}…", exact=True)


def test_a_bundle_without_its_model_is_refused_in_the_base_install(demo_dir):
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.errors import UserError

    with pytest.raises(UserError) as refused:
        load_bundle(demo_dir / "secret.bundle")
    assert refused.value.code == "bundle.masked"


def test_ordinary_render_skips_and_matches_the_demo_render(demo_dir, tmp_path):
    from noisenerf.runtime.images import read_image

    result = run_reveal(demo_dir / "model.onnx", "--view", 2, "-o", tmp_path / "v.png", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["samples"] < report["samples_dense"]
    assert (read_image(tmp_path / "v.png") == read_image(demo_dir / "ordinary.png")).all()


DEMO_PASSPHRASE = "noisenerf demo"  # train.demo.DEMO_PASSPHRASE (these tests cannot import the torch side)


def reveal_note(demo_dir: Path, out: Path, passphrase: str | None) -> subprocess.CompletedProcess:
    return run_reveal(demo_dir / "model.onnx", demo_dir / "note.bundle", "-o", out, "--json",
                      passphrase=None if passphrase is None else passphrase.encode())


def test_base_install_opens_the_sealed_note_byte_for_byte(demo_dir, tmp_path):
    result = reveal_note(demo_dir, tmp_path / "note.txt", DEMO_PASSPHRASE)
    assert result.returncode == 0, result.stderr
    note = (demo_dir / "note.txt").read_bytes()
    assert (tmp_path / "note.txt").read_bytes() == note
    report = json.loads(result.stdout)
    assert report["sealed"] is True and report["payload"]["bytes"] == len(note)
    assert report["payload"]["name"] == "note.txt"


@pytest.mark.parametrize("passphrase, message", [
    ("not the passphrase", "wrong passphrase, or the bundle or model was altered"),
    (None, "the bundle is sealed: give its passphrase with --passphrase-file F, NOISENERF_PASSPHRASE, "
           "or at the prompt (stdin a terminal)"),
])
def test_base_install_refuses_the_note_without_its_passphrase(demo_dir, tmp_path, passphrase, message):
    assert_refused(reveal_note(demo_dir, tmp_path / "note.txt", passphrase), tmp_path / "note.txt", message,
                   exact=True)


def test_the_readme_python_api_runs_as_written_without_torch(demo_dir, tmp_path):
    """The README's Python API section, run where `noisenerf demo` wrote noisenerf-demo/: it reveals the image
    exactly, opens the sealed note, refuses it without its passphrase and renders a view, loading no torch."""
    (tmp_path / "noisenerf-demo").symlink_to(demo_dir.resolve())
    code = readme_python("Python API")[0] + "\nimport sys\nassert 'torch' not in sys.modules\n"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    image, note, refusal, view = result.stdout.splitlines()
    assert image.startswith("image True (72, 96, 3) ") and note == f"file note.txt {(demo_dir / 'note.txt').read_bytes()!r}"
    assert refusal.startswith("seal.no_passphrase the bundle is sealed: give its passphrase")
    assert view.startswith("float32 (") and " samples" in view
    from noisenerf.runtime.images import read_native
    assert (read_native(tmp_path / "revealed.png") == read_native(demo_dir / "secret.png")).all()
