"""Hostile and failing conditions, each run as a user would meet it (`noisenerf-reveal` in a process of its own),
counted by verdict: refused cleanly (exit 2, one line, no output left, earlier output intact), or not.

The cases are the classes of tests/test_reliability.py and tests/test_hostile.py on the bench's own scene and
secret: compressed bombs, a stripped seal, two reveals racing to one output, and a full file system (a 64 KiB
tmpfs; root only, else the case is counted as skipped).
"""

from __future__ import annotations

import contextlib
import json
import lzma
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file, save_file

from noisenerf.runtime.bundle import METADATA_KEY
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured

PASSPHRASE = "noisenerf bench"


def rewritten(source: Path, target: Path, edit) -> Path:
    """A copy of a bundle with edit(meta, tensors) applied to its metadata and tensors."""
    from safetensors import safe_open

    with safe_open(str(source), framework="numpy") as handle:
        meta = json.loads(handle.metadata()[METADATA_KEY])
    tensors = load_file(str(source))
    edit(meta, tensors)
    save_file(tensors, str(target), metadata={METADATA_KEY: json.dumps(meta)})
    return target


def stated(width: int, height: int):
    """A bundle edit: a compact bundle claiming a width x height secret in one tile, on the streams it holds."""
    def edit(meta, tensors):
        meta["secret"].update(width=width, height=height)
        meta["tiles"][0]["rect"] = [0, 0, width, height]
        del meta["tiles"][1:]
    return edit


def zeros_as_stated(width: int, height: int):
    """A bundle edit: a compact bundle whose one tile is a width x height camera with exactly the zero
    coefficients it states, a stream of a few KB: every number in the caps, every stream the size it says."""
    def edit(meta, tensors):
        stated(width, height)(meta, tensors)
        camera = meta["tiles"][0]["camera"]
        camera.update(width=width, height=height, cx=width / 2, cy=height / 2)
        item = 2 if meta["noise"]["dtype"] == "int16" else 1
        streamed(width * height * meta["noise"]["coefficients"] * item)(meta, tensors)
    return edit


def streamed(n_bytes: int):
    """A bundle edit: the first tile's stream replaced by one of n_bytes zeros."""
    def edit(meta, tensors):
        tensors["tile_0000"] = np.frombuffer(lzma.compress(bytes(n_bytes), format=lzma.FORMAT_XZ), np.uint8)
    return edit


def reveal_process(*args, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "noisenerf.cli.reveal", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})},
                            stdin=subprocess.DEVNULL)


def verdict(process: subprocess.Popen, output: Path, before: bytes | None) -> tuple[str, float]:
    """'refused' (exit 2, one stderr line, no traceback, the output as it was) or what went wrong; seconds."""
    started = time.monotonic()
    _, stderr = process.communicate(timeout=600)
    seconds = time.monotonic() - started
    kept = (output.read_bytes() if output.exists() else None) == before
    lines = stderr.splitlines()
    if process.returncode == 2 and len(lines) == 1 and "Traceback" not in stderr and kept:
        return "refused", seconds
    return f"exit {process.returncode}, {len(lines)} stderr lines, output {'kept' if kept else 'changed'}", seconds


@contextlib.contextmanager
def full_file_system(folder: Path):
    """A 64 KiB tmpfs under folder, holding one earlier output and filled; None where it cannot be mounted."""
    mount = folder / "full"
    mount.mkdir(exist_ok=True)
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        yield None
        return
    try:
        (mount / "old.png").write_bytes(b"an earlier output")
        with contextlib.suppress(OSError), open(mount / "filler", "wb") as filler:
            filler.write(bytes(1 << 20))
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def measure_reliability(context: BenchContext) -> Measured:
    work, model = context.work / "reliability", context.model_path
    work.mkdir(exist_ok=True)
    secret = context.secret[:64, :64]
    context.hide(secret, "reliability/compact", HideConfig(view=context.config.view))
    compact = work / "compact.bundle"
    rows = []

    def case(group: str, name: str, process: subprocess.Popen, output: Path, before: bytes | None = None):
        result, seconds = verdict(process, output, before)
        rows.append({"class": group, "case": name, "verdict": result, "seconds": round(seconds, 2)})

    out = work / "out.png"
    for name, edit in (("stated 8192x8192", stated(8192, 8192)), ("stated 4096x4096", stated(4096, 4096)),
                       ("stream of 256 MiB of zeros", streamed(256 << 20)), ("stream of 4 MiB of zeros", streamed(4 << 20)),
                       ("2048x2048 of zeros as stated", zeros_as_stated(2048, 2048))):
        case("decompression bomb", name, reveal_process(model, rewritten(compact, work / "bomb.bundle", edit), "-o", out), out)
    payload = work / "note.txt"
    payload.write_bytes(b"a sealed note")
    sealed = work / "sealed.bundle"
    subprocess.run([sys.executable, "-m", "noisenerf.cli.main", "hide", context.config.scene, "--file", payload,
                    "-o", sealed, "--seal", "--quiet", "--force"], check=True, capture_output=True,
                   env={**os.environ, "NOISENERF_PASSPHRASE": PASSPHRASE})
    stripped = rewritten(sealed, work / "stripped.bundle", lambda meta, tensors: meta.pop("payload"))
    case("downgrade", "seal stripped, passphrase given",
         reveal_process(model, stripped, "-o", out, env={"NOISENERF_PASSPHRASE": PASSPHRASE}), out)
    raced = work / "raced.png"
    raced.unlink(missing_ok=True)
    racers = [reveal_process(model, compact, "-o", raced) for _ in range(2)]
    codes = sorted(racer.wait(600) for racer in racers)
    rows.append({"class": "race", "case": "two reveals to one output",
                 "verdict": "refused" if codes == [0, 2] else f"exit codes {codes}", "seconds": None})
    with full_file_system(work) as full:
        for name, force in (("new output", False), ("over an earlier output, --force", True)):
            if full is None:
                rows.append({"class": "full disk", "case": name, "verdict": "skipped (needs root)", "seconds": None})
                continue
            target = full / ("old.png" if force else "new.png")
            before = target.read_bytes() if target.exists() else None
            case("full disk", name, reveal_process(model, compact, "-o", target, *(["--force"] if force else [])),
                 target, before)
    return Measured(rows)


def describe_reliability(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    refused = sum(row["verdict"] == "refused" for row in rows)
    skipped = sum(row["verdict"].startswith("skipped") for row in rows)
    lines = [f"{len(rows)} cases: {refused} refused cleanly (exit 2, one line, nothing written, earlier output "
             f"intact), {skipped} skipped, {len(rows) - refused - skipped} otherwise.", "",
             "| class | case | verdict | seconds |", "|---|---|---|---|"]
    lines += [f"| {row['class']} | {row['case']} | {row['verdict']} | {row['seconds'] if row['seconds'] is not None else ''} |"
              for row in rows]
    return lines
