"""Hostile, careless and failing conditions, each met as a user meets it, counted by verdict: refused cleanly or
accepted with the right result, or not.

Where: `cli` runs a command in a process of its own (refused cleanly: exit 2, one stderr line, no traceback,
the output as it was, a folder file for file; peak MiB: its resident high-water mark); `api` calls the library in
this process (a UserError with a code and a one-line message, the output as it was); `page` calls the site build's
window.noisenerf.reveal in Chromium on the same files (refused cleanly: the library's code and params, one line;
peak MiB: Chromium's resident growth during the call, over what it held with the files' bytes loaded, as a page
holds a file its user picks). Classes: compressed bombs, streams framed otherwise, files of junk as a model or a
bundle (a constant time and memory whatever their size), a stripped seal, two reveals
racing to one output and a full file system (a 64 KiB tmpfs; root only, else skipped); the sender's outputs
(nothing replaced without --force, a scene folder replaced whole); image formats (every one hides as its pixels
or is refused); defaults from the environment (checked as their flags); the API's argument kinds; imports of
weights or scales that cannot render (these need the bench's nerfstudio run, else skipped).
"""

from __future__ import annotations

import contextlib
import json
import lzma
import os
import shutil
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path
from dataclasses import dataclass
from typing import Callable

import numpy as np
from safetensors.numpy import load_file, save_file

from noisenerf.runtime.bundle import METADATA_KEY
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.big_secret import high_water_mib
from noisenerf.cli.bench.browser import CHROMIUM, WEB_DIST, browser_missing, chromium_rss, served
from noisenerf.cli.bench.context import BenchContext, Measured, peak_sampled

PASSPHRASE = "noisenerf bench"
CASE_SECONDS = 300  # a case still running after this is killed and counted as not refused


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
    return command_process("noisenerf.cli.reveal", *args, env=env)


def command_process(module: str, *args, env: dict | None = None) -> subprocess.Popen:
    """`python -m MODULE ARGS` (noisenerf-reveal, or noisenerf's own commands), stdin closed, stdout dropped."""
    return subprocess.Popen([sys.executable, "-m", module, *map(str, args)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})},
                            stdin=subprocess.DEVNULL)


def finished(process: subprocess.Popen) -> tuple[str, float, float]:
    """Wait for a command_process: its stderr, its seconds from here, its peak resident MiB as last sampled (VmHWM:
    the exec'd program's own, where wait4's count would include the forked bench's pages)."""
    started = time.monotonic()
    with peak_sampled(lambda: high_water_mib(process.pid) or 0.0, 0.01) as peak:
        try:
            _, stderr = process.communicate(timeout=CASE_SECONDS)
        except subprocess.TimeoutExpired:  # a case that hangs is a finding, not the end of the run
            process.kill()
            _, stderr = process.communicate()
            stderr = f"killed after {CASE_SECONDS} s\n{stderr}"
    return stderr, time.monotonic() - started, peak[0]


def noisenerf_process(*args, env: dict | None = None) -> subprocess.Popen:
    return command_process("noisenerf.cli.main", *args, env=env)


def snapshot(path: Path):
    """What is at `path`, to compare before and after: a file's bytes, a folder's files (name -> bytes), or None."""
    if path.is_dir():
        return {str(item.relative_to(path)): item.read_bytes() for item in sorted(path.rglob("*")) if item.is_file()}
    return path.read_bytes() if path.exists() else None


def verdict(process: subprocess.Popen, output: Path, before=None) -> tuple[str, float, float]:
    """'refused' (exit 2, one stderr line, no traceback, the output as it was: `before` is its snapshot) or what
    went wrong; seconds; peak MiB."""
    stderr, seconds, peak = finished(process)
    kept = snapshot(output) == before
    lines = stderr.splitlines()
    if process.returncode == 2 and len(lines) == 1 and "Traceback" not in stderr and kept:
        return "refused", seconds, peak
    return f"exit {process.returncode}, {len(lines)} stderr lines, output {'kept' if kept else 'changed'}", seconds, peak


def api_verdict(call: Callable[[], object], output: Path | None = None) -> tuple[str, float]:
    """'refused' (a UserError with a code and a one-line message, `output` as it was) or what happened; seconds."""
    from noisenerf.runtime.errors import UserError

    before = None if output is None else snapshot(output)
    started = time.monotonic()
    try:
        call()
        result = "accepted"
    except UserError as error:
        one_line = "\n" not in str(error) and error.code is not None
        result = "refused" if one_line else f"refused without a code or in {len(str(error).splitlines())} lines"
    except Exception as error:  # what the class is about: anything else is the finding
        result = f"{type(error).__name__}: {str(error)[:80]}"
    seconds = time.monotonic() - started
    if output is not None and snapshot(output) != before:
        result += ", output changed"
    return result, seconds


def indexed_png(path: Path, indices: np.ndarray, palette: np.ndarray, alpha: np.ndarray | None = None) -> Path:
    """An indexed (colour type 3) PNG with an optional tRNS chunk, written byte by byte: OpenImageIO writes none.
    indices: (h, w) palette entries; palette: (n, 3) uint8; alpha: (n,) uint8 per entry."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    height, width = indices.shape
    rows = b"".join(b"\0" + bytes(row.astype(np.uint8)) for row in indices)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 3, 0, 0, 0))
    data += chunk(b"PLTE", bytes(palette.astype(np.uint8).ravel()))
    if alpha is not None:
        data += chunk(b"tRNS", bytes(alpha.astype(np.uint8)))
    path.write_bytes(data + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    return path


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


@dataclass(frozen=True)
class PageCase:
    """A reveal the page is given too: its files (served to the page, read by the library) and passphrase."""

    group: str
    name: str
    model: Path
    bundle: Path
    passphrase: str | None = None


FETCH_IN_PAGE = """async ([modelUrl, bundleUrl]) => {
  const fetched = async url => new Uint8Array(await (await fetch(url)).arrayBuffer());
  window.reliabilityCase = {model: await fetched(modelUrl), bundle: await fetched(bundleUrl)};
}"""
REVEAL_IN_PAGE = """async (passphrase) => {
  const {model, bundle} = window.reliabilityCase;
  delete window.reliabilityCase;
  const started = performance.now();
  try {
    const revealed = await window.noisenerf.reveal({model, bundle, passphrase: passphrase ?? undefined});
    return {seconds: (performance.now() - started) / 1000, exact: revealed.exact};
  } catch (error) {
    return {seconds: (performance.now() - started) / 1000, code: error.code ?? null, params: error.params ?? null,
            message: String(error.message)};
  }
}"""


def page_cases(cases: Cases, context: BenchContext, work: Path, in_page: list[PageCase]) -> None:
    """Each case given to the page (the site build, window.noisenerf.reveal on the fetched files) and to the library:
    'refused' where both refuse with the same code and params in one line. Skipped where no browser runs."""
    from noisenerf.runtime.api import reveal
    from noisenerf.runtime.errors import UserError

    missing = browser_missing()
    if missing is not None:
        for case in in_page:
            cases.add(case.group, case.name, "page", f"skipped ({missing})")
        return
    from playwright.sync_api import sync_playwright

    site = work / "site"
    shutil.copytree(WEB_DIST / "site", site)
    files = {path: f"file{k}{path.suffix}" for k, path in enumerate(
        dict.fromkeys(path for case in in_page for path in (case.model, case.bundle)))}
    for path, name in files.items():
        os.link(path, site / name)  # the same file system: no copy of a GiB
    with sync_playwright() as playwright, served(site) as base:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            page = browser.new_page()
            page.goto(f"{base}/index.html")
            page.wait_for_function("window.noisenerf !== undefined")
            for case in in_page:
                try:
                    reveal(case.model, case.bundle, case.passphrase)
                    library = None
                except UserError as error:
                    library = {"code": error.code, "params": error.params}
                page.evaluate(FETCH_IN_PAGE, [f"{base}/{files[case.model]}", f"{base}/{files[case.bundle]}"])
                holding = chromium_rss()  # the files' bytes, which a page holds once the user picks them
                with peak_sampled(chromium_rss) as peak:
                    got = page.evaluate(REVEAL_IN_PAGE, case.passphrase)
                same = library is not None and "code" in got and got["code"] == library["code"] and \
                    got["params"] == library["params"] and "\n" not in got["message"]
                result = "refused" if same else f"page {got.get('code', 'revealed')} {got.get('params', '')}, library " \
                                                f"{library}"
                cases.add(case.group, case.name, "page", result, got["seconds"], max(0, peak[0] - holding) / 2 ** 20)
        finally:
            browser.close()


class Cases:
    """The rows a reliability run counts: class, case, where (cli, api, page), verdict, seconds."""

    def __init__(self):
        self.rows: list[dict] = []

    def add(self, group: str, name: str, where: str, result: str, seconds: float | None = None,
            peak_mib: float | None = None) -> None:
        self.rows.append({"class": group, "case": name, "where": where, "verdict": result,
                          "seconds": None if seconds is None else round(seconds, 2),
                          "peak_mib": None if peak_mib is None else round(peak_mib)})

    def cli(self, group: str, name: str, process: subprocess.Popen, output: Path, before=None) -> None:
        self.add(group, name, "cli", *verdict(process, output, before))

    def api(self, group: str, name: str, call: Callable[[], object], output: Path | None = None) -> None:
        self.add(group, name, "api", *api_verdict(call, output))


def measure_reliability(context: BenchContext) -> Measured:
    work = context.work / "reliability"
    work.mkdir(exist_ok=True)
    context.hide(context.secret[:64, :64], "reliability/compact", HideConfig(view=context.config.view))
    cases = Cases()
    compact = work / "compact.bundle"
    sealed, in_page = reveal_cases(cases, context, work, compact)
    in_page += framing_cases(cases, context, work, compact)
    junk = junk_files(work, context.config.junk_bytes)
    in_page += junk_cases(cases, context, junk, compact)
    page_cases(cases, context, work, in_page)
    for path in junk:
        path.unlink()
    output_cases(cases, context, work / "outputs")
    image_cases(cases, context, work / "images")
    environment_cases(cases, context, work, sealed)
    argument_cases(cases, context, work / "arguments", compact)
    import_cases(cases, context, work / "imports")
    return Measured(cases.rows)


def reveal_cases(cases: Cases, context: BenchContext, work: Path, compact: Path) -> tuple[Path, list[PageCase]]:
    """Bombs, a stripped seal, racing reveals, a full disk. -> the sealed bundle it hid (PASSPHRASE), and the cases
    the page is given too."""
    model, out, in_page = context.model_path, work / "out.png", []
    for k, (name, edit) in enumerate((
            ("stated 8192x8192", stated(8192, 8192)), ("stated 4096x4096", stated(4096, 4096)),
            ("stream of 256 MiB of zeros", streamed(256 << 20)), ("stream of 4 MiB of zeros", streamed(4 << 20)),
            ("2048x2048 of zeros as stated", zeros_as_stated(2048, 2048)))):
        bomb = rewritten(compact, work / f"bomb{k}.bundle", edit)
        cases.cli("decompression bomb", name, reveal_process(model, bomb, "-o", out), out)
        in_page.append(PageCase("decompression bomb", name, model, bomb))
    payload = work / "note.txt"
    payload.write_bytes(b"a sealed note")
    sealed = work / "sealed.bundle"
    subprocess.run([sys.executable, "-m", "noisenerf.cli.main", "hide", context.config.scene, "--file", payload,
                    "-o", sealed, "--seal", "--quiet", "--force"], check=True, capture_output=True,
                   env={**os.environ, "NOISENERF_PASSPHRASE": PASSPHRASE})
    stripped = rewritten(sealed, work / "stripped.bundle", lambda meta, tensors: meta.pop("payload"))
    cases.cli("downgrade", "seal stripped, passphrase given",
              reveal_process(model, stripped, "-o", out, env={"NOISENERF_PASSPHRASE": PASSPHRASE}), out)
    in_page.append(PageCase("downgrade", "seal stripped, passphrase given", model, stripped, PASSPHRASE))
    raced = work / "raced.png"
    raced.unlink(missing_ok=True)
    racers = [reveal_process(model, compact, "-o", raced) for _ in range(2)]
    codes = sorted(racer.wait(600) for racer in racers)
    cases.add("race", "two reveals to one output", "cli", "refused" if codes == [0, 2] else f"exit codes {codes}")
    with full_file_system(work) as full:
        for name, force in (("new output", False), ("over an earlier output, --force", True)):
            if full is None:
                cases.add("full disk", name, "cli", "skipped (needs root)")
                continue
            target = full / ("old.png" if force else "new.png")
            cases.cli("full disk", name, reveal_process(model, compact, "-o", target, *(["--force"] if force else [])),
                      target, snapshot(target))
    return sealed, in_page


def framing_cases(cases: Cases, context: BenchContext, work: Path, compact: Path) -> list[PageCase]:
    """A compact tile's compressed stream framed otherwise than the writer frames it: refused, with the same code
    and params in the library and the page."""
    def framed(frame):
        def edit(meta, tensors):
            tensors["tile_0000"] = np.frombuffer(frame(tensors["tile_0000"].tobytes()), np.uint8)
        return edit
    in_page = []
    for k, (name, frame) in enumerate((
            ("padding after the stream", lambda stream: stream + bytes(16)),
            ("a second stream after the first", lambda stream: stream + stream),
            ("the stream cut short", lambda stream: stream[:-16]),
            ("junk after the stream", lambda stream: stream + b"noisenerf"))):
        bundle = rewritten(compact, work / f"framed{k}.bundle", framed(frame))
        cases.cli("framing", name, reveal_process(context.model_path, bundle, "-o", work / "out.png"), work / "out.png")
        in_page.append(PageCase("framing", name, context.model_path, bundle))
    return in_page


def junk_files(work: Path, size: int) -> list[Path]:
    """Two files of `size` bytes: zeros (sparse) and random bytes."""
    zeros, noise = work / "zeros.junk", work / "random.junk"
    with open(zeros, "wb") as handle:
        handle.truncate(size)
    with open(noise, "wb") as handle:
        for start in range(0, size, 1 << 24):
            handle.write(os.urandom(min(1 << 24, size - start)))
    return [zeros, noise]


def junk_cases(cases: Cases, context: BenchContext, junk: list[Path], compact: Path) -> list[PageCase]:
    """Files of junk given as the model and as the bundle: refused in a time and memory their size does not set."""
    in_page, out = [], compact.parent / "out.png"
    for path in junk:
        what = f"{path.stat().st_size / 2 ** 20:,.0f} MiB of {path.stem}"
        for role, model, bundle in (("model", path, compact), ("bundle", context.model_path, path)):
            cases.cli("files of junk", f"{what} as the {role}", reveal_process(model, bundle, "-o", out), out)
            in_page.append(PageCase("files of junk", f"{what} as the {role}", model, bundle))
    return in_page


def output_cases(cases: Cases, context: BenchContext, work: Path) -> None:
    """The sender's outputs: nothing replaced without --force, and a scene folder replaced only whole."""
    from noisenerf.api import export_model

    work.mkdir()
    scene, group = context.config.scene, "sender's outputs"
    model = work / "model.onnx"
    model.write_bytes(b"an earlier model")
    cases.cli(group, "export onto an earlier model", noisenerf_process("export", scene, "-o", model), model,
              snapshot(model))
    cases.api(group, "export_model onto an earlier model", lambda: export_model(scene, model), model)
    theirs = work / "photos"
    theirs.mkdir()
    (theirs / "holiday.jpg").write_bytes(b"not ours")
    cases.cli(group, "demo into a folder of other files", noisenerf_process("demo", "-o", theirs, "--quiet"), theirs,
              snapshot(theirs))
    run, data = context.config.nerfstudio_run, context.config.nerfstudio_data
    named = ("import onto an earlier scene", "import --force onto a folder of other files",
             "import --force onto an earlier scene")
    if run is None:
        for name in named:
            cases.add(group, name, "cli", "skipped (needs --nerfstudio-run)")
        return

    def imported(folder: Path, *flags) -> subprocess.Popen:
        return noisenerf_process("import-nerfstudio", run, "--data", data, "-o", folder, *flags)
    earlier = work / "scene"
    if imported(earlier).wait(600) != 0:
        raise RuntimeError(f"the bench's nerfstudio run did not import: {run}")
    (earlier / "checkpoint.safetensors").write_bytes(b"an earlier fit's checkpoint")
    cases.cli(group, named[0], imported(earlier), earlier, snapshot(earlier))
    cases.cli(group, named[1], imported(theirs, "--force"), theirs, snapshot(theirs))
    started = time.monotonic()
    code = imported(earlier, "--force").wait(600)
    seconds = time.monotonic() - started
    fresh = work / "fresh"
    imported(fresh).wait(600)
    whole = code == 0 and snapshot(earlier) == snapshot(fresh)
    cases.add(group, named[2], "cli", "accepted, replaced whole" if whole else f"exit {code}, not the new scene alone",
              seconds)


def image_cases(cases: Cases, context: BenchContext, work: Path) -> None:
    """Secrets in formats OpenImageIO reads: each hides as its pixels (the reveal equals what load_secret read)
    or is refused in one line."""
    import OpenImageIO as oiio

    from noisenerf.runtime.api import reveal
    from noisenerf.runtime.images import load_secret, write_image

    work.mkdir()
    rng = np.random.default_rng(11)
    pixels = rng.integers(0, 256, (8, 8, 4), dtype=np.uint8)

    def written(name: str, values: np.ndarray, pixel_type: str = "uint8") -> Path:
        output = oiio.ImageOutput.create(str(work / name))
        spec = oiio.ImageSpec(values.shape[1], values.shape[0], values.shape[2], pixel_type)
        spec.attribute("oiio:UnassociatedAlpha", 1)
        output.open(str(work / name), spec)
        output.write_image(values)
        output.close()
        return work / name
    accepted = {
        "GIF with transparency (alpha stated as channel 4 of 4)": written("a.gif", pixels),
        "indexed PNG with transparency": indexed_png(work / "indexed.png", rng.integers(0, 16, (8, 8)),
                                                     rng.integers(0, 256, (16, 3)), np.array([0, 64] + [255] * 14)),
        "grey+alpha TIFF": written("ga.tif", pixels[..., :2]),
        "RGBA BMP (straight alpha, stated by no flag)": written("a.bmp", pixels),
        "RGBA OpenEXR (associated alpha)": written("a.exr", pixels.astype(np.float32) / 255, "float"),
        "16-bit PNG": written("deep.png", pixels[..., :3].astype(np.uint16) * 257, "uint16"),
    }
    for name, path in accepted.items():
        bundle = work / "secret.bundle"
        process = noisenerf_process("hide", context.config.scene, path, "-o", bundle, "--force", "--quiet",
                                    "--view", context.config.view)
        stderr, seconds, _ = finished(process)
        if process.returncode != 0:
            cases.add("image formats", name, "cli", f"exit {process.returncode}: {stderr.strip()[-80:]}", seconds)
            continue
        same = np.array_equal(reveal(context.model_path, bundle).pixels, load_secret(path).pixels)
        cases.add("image formats", name, "cli", "accepted, exact" if same else "accepted, other pixels", seconds)
    write_image(work / "whole.png", pixels[..., :3])
    (work / "truncated.png").write_bytes((work / "whole.png").read_bytes()[:60])
    refused = {"JPEG 2000 that OpenImageIO writes but cannot read": written("broken.jp2", pixels[..., :3]),
               "truncated PNG": work / "truncated.png"}
    for name, path in refused.items():
        cases.cli("image formats", name, noisenerf_process("hide", context.config.scene, path, "-o",
                                                           work / "refused.bundle", "--quiet"), work / "refused.bundle")


def environment_cases(cases: Cases, context: BenchContext, work: Path, sealed: Path) -> None:
    """Defaults taken from the environment, checked as their flags are."""
    import importlib.util

    group, out = "defaults from the environment", work / "env.out"
    for name, address in (("RAY_ADDRESS where nothing listens", "127.0.0.1:9"),
                          ("RAY_ADDRESS that is no address", "not-an-address")):
        if importlib.util.find_spec("ray") is None:
            cases.add(group, name, "cli", "skipped (needs the cluster extra)")
            continue
        cases.cli(group, name, noisenerf_process("hide", context.config.scene, context.config.secret, "-o", out,
                                                 "--executor", "ray", "--quiet", env={"RAY_ADDRESS": address}), out)
    cases.cli(group, "NOISENERF_PASSPHRASE of 5000 bytes", reveal_process(
        context.model_path, sealed, "-o", out, env={"NOISENERF_PASSPHRASE": "p" * 5000}), out)


def argument_cases(cases: Cases, context: BenchContext, work: Path, bundle: Path) -> None:
    """The library's public functions given arguments of the wrong kind."""
    from noisenerf.api import export_model, hide
    from noisenerf.runtime.api import reveal, render

    work.mkdir()
    model, scene, out, group = context.model_path, context.config.scene, work / "out", "API argument kinds"
    secret = context.secret[:8, :8]
    for name, call in (("reveal: an array for the model", lambda: reveal(np.zeros(3), bundle)),
                       ("reveal: a number for the passphrase", lambda: reveal(model, bundle, 5)),
                       ("reveal: a str for threads", lambda: reveal(model, bundle, threads="2")),
                       ("render: a float view", lambda: render(model, 1.5)),
                       ("render: a bool view", lambda: render(model, True)),
                       ("hide: a str view", lambda: hide(scene, secret, out, view="2")),
                       ("hide: an array for the output", lambda: hide(scene, secret, np.zeros(2))),
                       ("hide: a number for the file", lambda: hide(scene, output=out, file=7)),
                       ("export_model: a number for force", lambda: export_model(scene, out, force=1))):
        cases.api(group, name, call, out)


def import_cases(cases: Cases, context: BenchContext, work: Path) -> None:
    """A nerfstudio run whose weights or scale cannot render, imported: refused, nothing written."""
    import torch

    group = "imports that cannot render"
    named = ("a NaN weight", "an infinite weight", "a dataparser scale of 1e6")
    run, data = context.config.nerfstudio_run, context.config.nerfstudio_data
    if run is None:
        for name in named:
            cases.add(group, name, "cli", "skipped (needs --nerfstudio-run)")
        return
    for k, name in enumerate(named):
        copy = shutil.copytree(run, work / f"run{k}")
        if k < 2:
            checkpoint = max((copy / "nerfstudio_models").glob("step-*.ckpt"))
            state = torch.load(checkpoint, map_location="cpu", weights_only=False)  # our own copy of the bench's run
            tensor = next(value for key, value in state["pipeline"].items()  # the colour head, either layout
                          if ".field.mlp_head." in key and value.is_floating_point() and value.numel())
            tensor.view(-1)[0] = float("nan") if k == 0 else float("inf")
            torch.save(state, checkpoint)
        else:
            transforms = copy / "dataparser_transforms.json"
            transforms.write_text(json.dumps({**json.loads(transforms.read_text()), "scale": 1e6}))
        out = work / f"scene{k}"
        cases.cli(group, name, noisenerf_process("import-nerfstudio", copy, "--data", data, "-o", out), out)


def describe_reliability(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    refused = sum(row["verdict"] == "refused" for row in rows)
    accepted = sum(row["verdict"] in ("accepted, exact", "accepted, replaced whole") for row in rows)
    skipped = sum(row["verdict"].startswith("skipped") for row in rows)
    lines = [f"{len(rows)} cases: {refused} refused cleanly (exit 2, one line, nothing written, earlier output "
             f"intact; in the library a coded UserError), {accepted} accepted with the right result, {skipped} "
             f"skipped, {len(rows) - refused - accepted - skipped} otherwise.", "",
             "| class | case | where | verdict | seconds | peak MiB |", "|---|---|---|---|---|---|"]
    def blank(value) -> str:
        return "" if value is None else str(value)
    lines += [f"| {row['class']} | {row['case']} | {row['where']} | {row['verdict']} | {blank(row['seconds'])} | "
              f"{blank(row['peak_mib'])} |" for row in rows]
    return lines
