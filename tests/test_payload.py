"""File payloads and sealing: byte-exact round trips through `noisenerf-reveal`, and every refusal as one
line, exit code 2 and no output file (a wrong passphrase, a changed byte in the noise, the metadata or the
model's weights, a sealed bundle without a passphrase, pixels that do not reproduce the payload)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from helpers import assert_refused, hidden_bundle, mask_secret_of, run_reveal
from noisenerf.cli.main import main as noisenerf_main
from noisenerf.runtime.layouts import CompactNoise
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import read_native, write_image
from noisenerf.runtime.payload import (
    INEXACT, MIN_BUCKET, Record, checked_marker, image_record, near_square, sealed_shape, unpack_record,
)
from noisenerf.runtime.sealing import WRONG, ScryptParams, Seal, new_seal
from noisenerf.train.hide.payload import hide_payload
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.scene.procedural import DEMO_SCENE

CPU = torch.device("cpu")
PASSPHRASE = b"correct horse battery staple"
FAST_KDF = ScryptParams(log2_n=10, r=8, p=1)  # tests only: the default costs ~0.5 s per derivation
CONFIG = HideConfig(tile_size=64)


def fixed_seal() -> Seal:
    """A deterministic seal (fixed salt and nonce: tests only) with a cheap KDF."""
    return new_seal(FAST_KDF, salt=bytes(range(16)), nonce=bytes(range(12)))


@pytest.fixture(scope="module")
def demo(demo_scene, demo_model):
    """The demo scene and its exported model."""
    return demo_scene, demo_model


@pytest.fixture(scope="module")
def sealed(demo, tmp_path_factory):
    """A sealed bundle of a short text file."""
    scene, _ = demo
    path = tmp_path_factory.mktemp("sealed") / "note.bundle"
    hide_payload(scene, Record("file", b"the eagle lands at noon\n", b"note.txt"), path, CONFIG, CPU,
                 passphrase=PASSPHRASE, seal=fixed_seal())
    return path


def test_record_round_trip_ignores_padding_and_checks_its_digest():
    record = Record("file", b"\x00\xffpayload", b"a.bin")
    packed = record.pack()
    assert unpack_record(packed + bytes(7)) == record
    for altered in (packed[:-1] + b"!", b"XXXX" + packed[4:], packed[:-1]):
        with pytest.raises(UserError, match="do not reproduce"):
            unpack_record(altered)


def test_secret_shapes_near_square_and_size_buckets():
    assert near_square(0) == (1, 1) and near_square(1) == (1, 1) and near_square(10) == (4, 3)
    assert near_square(349_526) == (592, 591)
    assert sealed_shape(1, 512) == (MIN_BUCKET, MIN_BUCKET) and sealed_shape(257, 512) == (32, 32)
    assert sealed_shape(512 ** 2, 512) == (512, 512) and sealed_shape(512 ** 2 + 1, 512) == (1024, 512)
    assert sealed_shape(5 * 512 ** 2, 512) == (1536, 1024)
    assert sealed_shape(300, 20) == (20, 20) and sealed_shape(401, 20) == (40, 20)  # a tile, then whole tiles


def test_payload_marker_is_checked_and_kdf_capped():
    seal = fixed_seal().to_dict()
    assert checked_marker({"version": 1, "sealed": seal})["sealed"] == seal
    for bad in ({"version": 2, "sealed": None}, {"version": 1, "sealed": None, "x": 1},
                {"version": 1, "sealed": {**seal, "salt": "AAAA"}},
                {"version": 1, "sealed": {**seal, "kdf": {"name": "scrypt", "log2_n": 20, "r": 8, "p": 1}}},
                {"version": 1, "sealed": {**seal, "kdf": {"name": "scrypt", "log2_n": 17, "r": 8, "p": 64}}},
                {"version": 1, "sealed": {**seal, "cipher": "rot13"}}):
        with pytest.raises(UserError, match="bundle: "):
            checked_marker(bad)


@pytest.mark.parametrize("content", ["empty", "one byte", "random", "text"])
def test_file_payloads_reveal_byte_for_byte(demo, tmp_path, content):
    scene, model = demo
    data = {"empty": b"", "one byte": b"\x00", "random": np.random.default_rng(3).bytes(500),
            "text": Path(__file__).with_name("conftest.py").read_bytes()[:900]}[content]
    (tmp_path / "in.dat").write_bytes(data)
    result = subprocess.run([sys.executable, "-m", "noisenerf.cli.main", "hide", str(DEMO_SCENE), "--file",
                             str(tmp_path / "in.dat"), "-o", str(tmp_path / "x.bundle"), "--tile-size", "64", "--json",
                             "--quiet"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["payload"]["bytes"] == len(data)
    result = run_reveal(model, tmp_path / "x.bundle", "-o", tmp_path / "out.png", "--json")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "out.png").read_bytes() == data  # written as bytes, whatever the extension
    report = json.loads(result.stdout)
    assert report["exact"] and not report["sealed"]
    assert report["payload"]["bytes"] == len(data) and report["payload"]["name"] == "in.dat"
    assert report["payload"]["sha256"] == hashlib.sha256(data).hexdigest()


def test_hide_announces_capacity_and_time(demo, tmp_path, capsys):
    (tmp_path / "one").write_bytes(b"1")
    assert noisenerf_main(["hide", str(DEMO_SCENE), "--file", str(tmp_path / "one"), "-o", str(tmp_path / "o.bundle"),
                           "--tile-size", "64"]) == 0
    err = capsys.readouterr().err
    assert "noisenerf: file payload of 1 bytes -> 5x4 secret (20 px, 1 tiles of at most 64 px); expect about" in err


def test_sealed_file_through_the_command_line(demo, tmp_path):
    _, model = demo
    (tmp_path / "pass").write_bytes(PASSPHRASE + b"\n")
    (tmp_path / "plan.txt").write_bytes(b"plan B\n")
    result = subprocess.run([sys.executable, "-m", "noisenerf.cli.main", "hide", str(DEMO_SCENE), "--file",
                             str(tmp_path / "plan.txt"), "-o", str(tmp_path / "s.bundle"), "--tile-size", "64",
                             "--passphrase-file", str(tmp_path / "pass"), "--quiet"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    raw = (tmp_path / "s.bundle").read_bytes()
    assert b"plan.txt" not in raw and b"plan B" not in raw
    result = run_reveal(model, tmp_path / "s.bundle", "-o", tmp_path / "out.txt", "--passphrase-file",
                        tmp_path / "pass")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "out.txt").read_bytes() == b"plan B\n"
    assert "payload: file 'plan.txt', 7 bytes" in result.stdout and ", sealed" in result.stdout


def test_sealed_image_reveals_as_the_image(demo, tmp_path):
    scene, model = demo
    image = np.random.default_rng(5).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    hide_payload(scene, image_record(image), tmp_path / "i.bundle", CONFIG, CPU, passphrase=PASSPHRASE,
                 seal=fixed_seal())
    assert (hidden_bundle(tmp_path / "i.bundle", scene).width, hidden_bundle(tmp_path / "i.bundle", scene).height) == (16, 16)
    result = run_reveal(model, tmp_path / "i.bundle", "-o", tmp_path / "out.png", "--json", passphrase=PASSPHRASE)
    assert result.returncode == 0, result.stderr
    np.testing.assert_array_equal(read_native(tmp_path / "out.png"), image)
    assert json.loads(result.stdout)["payload"] | {"sha256": None} == {
        "kind": "image", "bytes": 144, "sha256": None, "name": None, "width": 8, "height": 6}


def test_sealed_metadata_hides_length_and_name(demo, sealed, tmp_path):
    scene, _ = demo
    hide_payload(scene, Record("file", bytes(150), b"a-much-longer-name.pdf"), tmp_path / "other.bundle", CONFIG,
                 CPU, passphrase=PASSPHRASE, seal=fixed_seal())
    for path in (sealed, tmp_path / "other.bundle"):
        bundle = hidden_bundle(path, scene)
        assert (bundle.width, bundle.height) == (16, 16)
        assert b"note.txt" not in path.read_bytes() and b".pdf" not in path.read_bytes()
    assert set(hidden_bundle(sealed, scene).payload_marker) == {"version", "sealed"}


def test_sealed_bundle_is_deterministic_only_with_a_fixed_seal(demo, sealed, tmp_path):
    scene, _ = demo
    hide_payload(scene, Record("file", b"the eagle lands at noon\n", b"note.txt"), tmp_path / "again.bundle", CONFIG,
                 CPU, passphrase=PASSPHRASE, seal=fixed_seal())
    assert (tmp_path / "again.bundle").read_bytes() == sealed.read_bytes()
    assert new_seal().salt != new_seal().salt and new_seal().nonce != new_seal().nonce


def flip_noise_byte(source: Path, target: Path) -> None:
    """One bit changed in the first tensor byte after the header: the noise."""
    data = bytearray(source.read_bytes())
    data[8 + int.from_bytes(data[:8], "little") + 3] ^= 1
    target.write_bytes(bytes(data))


def flip_metadata_byte(source: Path, target: Path) -> None:
    """One digit of the bundle's JSON metadata changed (the first tile's view), keeping it valid JSON."""
    data = source.read_bytes()
    at = data.index(b'\\"view\\": ') + len(b'\\"view\\": ')
    target.write_bytes(data[:at] + (b"5" if data[at:at + 1] != b"5" else b"4") + data[at + 1:])


@pytest.mark.parametrize("tamper", [flip_noise_byte, flip_metadata_byte])
def test_a_changed_byte_in_the_bundle_is_refused(demo, sealed, tmp_path, tamper):
    _, model = demo
    tamper(sealed, tmp_path / "t.bundle")
    assert (tmp_path / "t.bundle").read_bytes() != sealed.read_bytes()
    assert_refused(run_reveal(model, tmp_path / "t.bundle", "-o", tmp_path / "out", passphrase=PASSPHRASE),
                   tmp_path / "out", WRONG, exact=True)


def test_wrong_or_missing_passphrase_is_refused(demo, sealed, tmp_path):
    _, model = demo
    assert_refused(run_reveal(model, sealed, "-o", tmp_path / "out", passphrase=b"wrong"), tmp_path / "out", WRONG,
                   exact=True)
    assert_refused(run_reveal(model, sealed, "-o", tmp_path / "out"), tmp_path / "out",
                   "the bundle is sealed: give its passphrase with --passphrase-file F, NOISENERF_PASSPHRASE, or at "
                   "the prompt (stdin a terminal)", exact=True)
    result = run_reveal(model, sealed, "-o", tmp_path / "out", passphrase=PASSPHRASE)
    assert result.returncode == 0 and (tmp_path / "out").read_bytes() == b"the eagle lands at noon\n"


def test_a_passphrase_from_the_environment_is_capped_as_the_file_is(demo, sealed, tmp_path):
    _, model = demo
    (tmp_path / "long").write_bytes(b"p" * 4097)
    assert_refused(run_reveal(model, sealed, "-o", tmp_path / "out", "--passphrase-file", tmp_path / "long"),
                   tmp_path / "out", f"--passphrase-file must be a file of at most 4096 bytes: {tmp_path / 'long'}",
                   exact=True)
    assert_refused(run_reveal(model, sealed, "-o", tmp_path / "out", passphrase=b"p" * 4097), tmp_path / "out",
                   "NOISENERF_PASSPHRASE must hold at most 4096 bytes, not 4097", exact=True)


def test_a_changed_model_weight_is_refused(demo, sealed, tmp_path):
    _, model = demo
    proto = onnx.load(str(model))
    weight = next(init for init in proto.graph.initializer if init.raw_data)
    raw = bytearray(weight.raw_data)
    raw[0] ^= 1
    weight.raw_data = bytes(raw)
    onnx.save(proto, str(tmp_path / "m.onnx"))
    assert_refused(run_reveal(tmp_path / "m.onnx", sealed, "-o", tmp_path / "out", passphrase=PASSPHRASE),
                   tmp_path / "out", "its weights do not match its fingerprint")


def test_unsealed_payload_whose_pixels_changed_is_refused(demo, tmp_path):
    scene, model = demo
    hide_payload(scene, Record("file", b"exactly these bytes"), tmp_path / "p.bundle", CONFIG, CPU)
    bundle = hidden_bundle(tmp_path / "p.bundle", scene)
    tiles = tuple(dataclasses.replace(tile, noise=CompactNoise.of(np.zeros_like(tile.noise.coefficients()),
                                                                  tile.noise.basis, tile.noise.band_rows))
                  for tile in bundle.tiles)
    dataclasses.replace(bundle, tiles=tiles).save(tmp_path / "z.bundle", mask_secret=mask_secret_of(scene))
    assert_refused(run_reveal(model, tmp_path / "z.bundle", "-o", tmp_path / "out"), tmp_path / "out", INEXACT,
                   exact=True)


def test_hide_refuses_bad_payload_requests(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("NOISENERF_PASSPHRASE", raising=False)
    (tmp_path / "f").write_bytes(b"x")
    write_image(tmp_path / "s.png", np.zeros((4, 4, 3), np.uint8))
    cases = [
        (["hide", str(DEMO_SCENE), "-o", str(tmp_path / "o")], "give exactly one of SECRET_IMAGE or --file PAYLOAD"),
        (["hide", str(DEMO_SCENE), str(tmp_path / "s.png"), "--file", str(tmp_path / "f"), "-o", str(tmp_path / "o")],
         "give exactly one of SECRET_IMAGE or --file PAYLOAD"),
        (["hide", str(DEMO_SCENE), "--file", str(tmp_path / "f"), "-o", str(tmp_path / "o"), "--method", "paper"],
         "a file or sealed payload needs --method exact"),
        (["hide", str(DEMO_SCENE), "--file", str(tmp_path / "missing"), "-o", str(tmp_path / "o")],
         "payload file not found"),
        (["hide", str(DEMO_SCENE), "--file", str(tmp_path / "f"), "-o", str(tmp_path / "o"), "--seal"],
         "--seal needs a passphrase"),
    ]
    for argv, message in cases:
        assert noisenerf_main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "o").exists()


def test_a_sealed_bundle_is_written_once_whole(demo, tmp_path, monkeypatch):
    """The tag is computed over the bundle's bytes before they are written: one publication of the output, and
    the file published is the sealed one (it opens under the passphrase)."""
    from noisenerf.runtime import files

    scene, model = demo
    published, atomic_output = [], files.atomic_output

    def counted(path, **options):
        published.append(Path(path))
        return atomic_output(path, **options)
    monkeypatch.setattr(files, "atomic_output", counted)
    out = tmp_path / "once.bundle"
    hide_payload(scene, Record("file", b"written once\n", b"once.txt"), out, CONFIG, CPU, passphrase=PASSPHRASE,
                 seal=fixed_seal())
    assert published.count(out) == 1
    result = run_reveal(model, out, "-o", tmp_path / "once.txt", passphrase=PASSPHRASE)
    assert result.returncode == 0 and (tmp_path / "once.txt").read_bytes() == b"written once\n"
