"""Nothing lost, nothing silent: full disks, failing writes, racing writers, dropped precision, a stripped seal,
records the writer could not have made and an unreachable Ray cluster (decompression bombs and forged resume
parts are with the other hostile inputs, tests/test_hostile.py).

Full disks are real: a 64 KiB tmpfs mounted for the test (root only; elsewhere those cases skip and say
why). Other write failures are injected into the writer (os.fsync raising). Every refusal is checked with
`assert_refused`: exit code 2, one line, no traceback, no output left behind.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import assert_refused, hidden_bundle, rewrite_bundle, run_main, run_reveal, write_raw
from noisenerf.cli.main import main as noisenerf_main
from noisenerf.cli.reveal import main as reveal_main
from noisenerf.runtime.bundle import secret_digest
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import read_native, write_image
from noisenerf.runtime.payload import RECORD, Record, unpack_record

NO_SPACE = "no space left on the file system of"


@pytest.fixture
def full_disk(tmp_path):
    """A 64 KiB tmpfs holding an old output and filled to its last blocks; unmounted afterwards."""
    mount = tmp_path / "tiny"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        pytest.skip("mounting a small tmpfs needs root")
    try:
        (mount / "old.png").write_bytes(b"the earlier output")
        with open(mount / "filler", "wb") as filler:
            with pytest.raises(OSError):
                filler.write(bytes(1 << 20))
                filler.flush()
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=True)


def listing(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in folder.iterdir() if path.is_file()}


# ---- writes that cannot lose data ------------------------------------------------------------------

@pytest.mark.parametrize("name, force", [("new.png", False), ("old.png", True), ("new.tif", False)])
def test_a_reveal_into_a_full_disk_leaves_everything_as_it_was(reveal_inputs, full_disk, capfd, name, force):
    _, model, bundle = reveal_inputs
    before = listing(full_disk)
    result = run_main(reveal_main, [model, bundle, "-o", full_disk / name, *(["--force"] if force else [])], capfd)
    assert_refused(result, None, f"{NO_SPACE} {full_disk} while writing {name}; nothing was written")
    assert listing(full_disk) == before and len(os.listdir(full_disk)) == len(before)


def test_a_hide_and_an_export_into_a_full_disk_leave_everything_as_it_was(reveal_inputs, full_disk, capfd):
    folder, _, _ = reveal_inputs
    secret = full_disk.parent / "s.png"
    write_image(secret, np.full((8, 8, 3), 90, np.uint8))
    before = listing(full_disk)
    hidden = run_main(noisenerf_main, ["hide", folder / "scene", secret, "-o", full_disk / "old.png", "--force",
                                       "--quiet"], capfd)
    assert_refused(hidden, None, NO_SPACE)
    exported = run_main(noisenerf_main, ["export", folder / "scene", "-o", full_disk / "old.png",
                                         "--force"], capfd)
    assert_refused(exported, None, f"{NO_SPACE} {full_disk} while writing old.png")
    shutil.rmtree(full_disk / "old.png.partial", ignore_errors=True)  # the resume folder a hide may keep
    assert listing(full_disk) == before


@pytest.mark.parametrize("failure", [errno.EIO, errno.ENOSPC])
@pytest.mark.parametrize("payload", [False, True])
def test_a_write_that_fails_late_keeps_the_old_file(reveal_inputs, tmp_path, capfd, monkeypatch, failure, payload):
    """A failure at the last step before publishing (fsync), injected into the writer: the old output is kept,
    no temporary file is left, one line."""
    _, model, bundle = reveal_inputs
    out = tmp_path / "out.png"
    out.write_bytes(b"the earlier output")
    if payload:
        raw = Record("file", b"payload bytes", b"p.txt")
        bundle = tmp_path / "p.bundle"
        folder = reveal_inputs[0]
        payload_file = tmp_path / "p.txt"
        payload_file.write_bytes(raw.body)
        assert run_main(noisenerf_main, ["hide", folder / "scene", "--file", payload_file, "-o", bundle,
                                         "--quiet"], capfd).code == 0

    def failing(fd):
        raise OSError(failure, os.strerror(failure))
    monkeypatch.setattr(os, "fsync", failing)
    result = run_main(reveal_main, [model, bundle, "-o", out, "--force"], capfd)
    monkeypatch.undo()
    expected = f"{NO_SPACE} {tmp_path}" if failure == errno.ENOSPC else f"cannot write {out}: {os.strerror(failure)}"
    assert_refused(result, None, expected)
    assert out.read_bytes() == b"the earlier output"
    assert sorted(path.name for path in tmp_path.iterdir() if path.name.startswith(".noisenerf-")) == []


def test_an_output_that_appears_while_a_reveal_writes_is_never_replaced(reveal_inputs, tmp_path, capfd, monkeypatch):
    """Another writer creates the output between the check and the publication: without --force, ours is refused."""
    from noisenerf.runtime import images

    _, model, bundle = reveal_inputs
    out = tmp_path / "out.png"
    check = images.check_written

    def racing(tmp, path, pixels, lossless):
        check(tmp, path, pixels, lossless)
        out.write_bytes(b"the other writer's")
    monkeypatch.setattr(images, "check_written", racing)
    result = run_main(reveal_main, [model, bundle, "-o", out], capfd)
    assert_refused(result, None, f"output exists (pass --force to overwrite): {out} appeared while this one was")
    assert out.read_bytes() == b"the other writer's"


def test_two_reveals_to_one_output_one_wins_the_other_is_refused(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    out = tmp_path / "out.png"
    command = [sys.executable, "-m", "noisenerf.cli.reveal", str(model), str(bundle), "-o", str(out)]
    runs = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = sorted((run.wait(120), run.stderr.read()) for run in runs)
    assert [code for code, _ in results] == [0, 2], results
    assert "output exists (pass --force to overwrite)" in results[1][1]
    assert secret_digest(read_native(out)) == hidden_bundle(bundle, model).secret_sha256  # the winner's, whole


# ---- precision ------------------------------------------------------------------------------------

def test_a_16_bit_secret_is_hidden_as_8_bits_and_says_so(reveal_inputs, tmp_path, capfd):
    folder, model, _ = reveal_inputs
    values = np.random.default_rng(5).integers(0, 65536, (8, 8, 3), dtype=np.uint16) | 1
    secret = write_raw(tmp_path / "deep.png", values, "uint16")
    result = run_main(noisenerf_main, ["hide", folder / "scene", secret, "-o", tmp_path / "s.bundle", "--json",
                                       "--quiet"], capfd)
    assert result.code == 0
    assert result.err.splitlines() == [f"noisenerf: warning: {secret} has 16-bit channels; it is hidden as 8 bits per "
                                       "channel (the finer values are not kept, and `exact` is about the 8-bit values)"]
    report = json.loads(result.out)
    assert report["precision"] == "8-bit (secret had 16)" and report["exact"] is True


# ---- a stripped seal ------------------------------------------------------------------------------

@pytest.mark.parametrize("how", ["file", "environment"])
def test_a_sealed_bundle_stripped_of_its_seal_is_not_revealed(reveal_inputs, tmp_path, capfd, how):
    folder, model, _ = reveal_inputs
    secret = tmp_path / "s.png"
    write_image(secret, np.random.default_rng(6).integers(0, 256, (8, 8, 3), dtype=np.uint8))
    (tmp_path / "pass.txt").write_text("correct horse")
    sealed = tmp_path / "sealed.bundle"
    assert run_main(noisenerf_main, ["hide", folder / "scene", secret, "-o", sealed, "--passphrase-file",
                                     tmp_path / "pass.txt", "--quiet"], capfd).code == 0
    stripped = rewrite_bundle(sealed, tmp_path / "stripped.bundle", lambda meta, tensors: meta.pop("payload"))
    out = tmp_path / "out.png"
    if how == "file":
        result = run_reveal(model, stripped, "-o", out, "--passphrase-file", tmp_path / "pass.txt")
    else:
        result = run_reveal(model, stripped, "-o", out, passphrase=b"correct horse")
    assert_refused(result, out, "a passphrase was given but the bundle is not sealed")
    assert run_reveal(model, stripped, "-o", out).returncode == 0  # without one: what an unsealed bundle is


# ---- payload records ------------------------------------------------------------------------------

def record_bytes(kind: int, name: bytes, body: bytes, width: int, height: int) -> bytes:
    return RECORD.pack(b"NNPL", 1, kind, len(name), len(body), width, height, hashlib.sha256(body).digest()) + name + body


@pytest.mark.parametrize("data, message", [
    (record_bytes(1, b"", b"", 0, 0), "the payload's image width must be between 1 and 16384, got 0"),
    (record_bytes(1, b"", bytes(3 * 20000), 20000, 1), "the payload's image width must be between 1 and 16384"),
    (record_bytes(0, b"n" * 256, b"x", 0, 0), "the payload's file name is 256 bytes; a record holds at most 255"),
])
def test_a_record_the_writer_could_not_have_written_is_refused(data, message):
    with pytest.raises(UserError, match=message.replace("(", r"\(")):
        unpack_record(data)
    assert unpack_record(record_bytes(0, b"n" * 255, b"x", 0, 0)).name == b"n" * 255


# ---- Ray -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("address, where", [
    ("127.0.0.1:9", "the flag"), ("127.0.0.1:9", "RAY_ADDRESS"), ("no-port", "the flag"), ("no-port", "RAY_ADDRESS")])
def test_an_unreachable_ray_address_is_one_line_within_seconds(reveal_inputs, tmp_path, capfd, monkeypatch, address,
                                                               where):
    """The flag's address and the default the help names (RAY_ADDRESS) are checked alike."""
    pytest.importorskip("ray")
    folder, _, _ = reveal_inputs
    secret = tmp_path / "s.png"
    write_image(secret, np.zeros((8, 8, 3), np.uint8))
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    if where == "RAY_ADDRESS":
        monkeypatch.setenv("RAY_ADDRESS", address)
    flags = ["--ray-address", address] if where == "the flag" else []
    started = time.monotonic()
    result = run_main(noisenerf_main, ["hide", folder / "scene", secret, "-o", tmp_path / "s.bundle", "--executor",
                                       "ray", *flags, "--quiet"], capfd)
    message = {("127.0.0.1:9", "the flag"): "cannot reach the Ray cluster at 127.0.0.1:9: Connection refused",
               ("127.0.0.1:9", "RAY_ADDRESS"): "cannot reach the Ray cluster at 127.0.0.1:9 (from RAY_ADDRESS): "
                                               "Connection refused",
               ("no-port", "the flag"): "--ray-address must be HOST:PORT or ray://HOST:PORT, got 'no-port'",
               ("no-port", "RAY_ADDRESS"): "RAY_ADDRESS must be HOST:PORT or ray://HOST:PORT, got 'no-port'"}
    assert_refused(result, tmp_path / "s.bundle", message[address, where], exact=True)
    assert time.monotonic() - started < 20
