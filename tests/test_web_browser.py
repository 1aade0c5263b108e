"""The page in a real headless Chromium: `web/dist/noisenerf-reveal.html` opened from disk (file://) reveals what
`noisenerf-reveal` reveals, byte for byte, and refuses what it refuses with the same line.

Through `window.noisenerf.reveal` (the page's API, run in its Web Worker): the demo's two-tile secret (the 8-bit
pixels of both PNGs equal), a secret hidden in an imported nerfstudio nerfacto run (its proposal networks in the
graph the page checks), the demo's sealed note (its bytes equal), a wrong passphrase and a tampered sealed
bundle (the CLI's message). Through the page's controls: the sealed note saved under a chosen name, the secret's
PNG downloaded, a bad bundle refused with one message and nothing downloaded.

Needs Debian's chromium (/usr/lib/chromium/chromium), Playwright for Python (its own browser download is not
used) and web/node_modules (`npm ci` in web/); the builds are made here with `npm run build`. Without any of
them the tests skip with the reason. `.ci/run` installs all of them.
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import flip_first_float32, run_reveal, write_nerfstudio_run, write_png
import noisenerf as library
from noisenerf.cli.bench.browser import CHROMIUM, WEB_DIST
from noisenerf.runtime.errors import UserError

WEB = WEB_DIST.parent
SINGLE = WEB_DIST / "noisenerf-reveal.html"
DEMO_PASSPHRASE = "noisenerf demo"  # cli/demo.py's, public


@pytest.fixture(scope="session")
def single_file() -> Path:
    """web/dist/noisenerf-reveal.html, built here by `npm run build`."""
    if shutil.which("npm") is None or not (WEB / "node_modules").is_dir():
        pytest.skip("npm or web/node_modules is missing: run `npm ci` in web/ (CI does)")
    result = subprocess.run(["npm", "run", "build"], cwd=WEB, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert SINGLE.is_file() and (WEB / "dist" / "site" / "index.html").is_file()
    return SINGLE


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (CI does)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("playwright is not installed: pip install playwright (the dev extra; no `playwright install`)")
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser, single_file):
    context = browser.new_context(accept_downloads=True)
    tab = context.new_page()
    errors = []
    tab.on("pageerror", lambda error: errors.append(error))
    tab.on("console", lambda line: line.type == "error" and errors.append(line.text))  # a failed load, too
    tab.goto(single_file.as_uri())
    tab.wait_for_function("window.noisenerf !== undefined")
    yield tab
    context.close()
    assert not errors, errors


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    """`noisenerf demo`'s files: model.onnx, secret.bundle (two tiles), note.bundle (sealed), note.txt."""
    folder = tmp_path_factory.mktemp("browser_demo") / "demo"
    result = subprocess.run([sys.executable, "-m", "noisenerf.cli.main", "demo", "-o", str(folder)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return folder


def noisenerf(*args) -> None:
    result = subprocess.run([sys.executable, "-m", "noisenerf.cli.main", *map(str, args)], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]


@pytest.fixture(scope="module")
def nerfacto(tmp_path_factory) -> Path:
    """A synthetic nerfstudio nerfacto run (tiny-cuda-nn's layout) through `noisenerf import-nerfstudio`, `export`
    and `hide --view 4` of a small random secret: model.onnx, secret.bundle."""
    folder = tmp_path_factory.mktemp("browser_nerfacto")
    run, data = write_nerfstudio_run(folder, "tcnn", seed=3, prefix="_model.module.")
    noisenerf("import-nerfstudio", run, "-o", folder / "scene", "--data", data)
    noisenerf("export", folder / "scene", "-o", folder / "model.onnx")
    secret = write_png(folder / "secret.png", np.random.default_rng(5).integers(0, 256, (6, 7, 3), dtype=np.uint8))
    noisenerf("hide", folder / "scene", secret, "-o", folder / "secret.bundle", "--view", "4")
    return folder


REVEAL = """async ([model, bundle, passphrase]) => {
  const decode = (text) => Uint8Array.from(atob(text), (c) => c.charCodeAt(0));
  const encode = (bytes) => { let s = ""; for (let i = 0; i < bytes.length; i += 32768) s += String.fromCharCode(...bytes.subarray(i, i + 32768)); return btoa(s); };
  const started = performance.now();
  try {
    const r = await window.noisenerf.reveal({ model: decode(model), bundle: decode(bundle), passphrase });
    return { kind: r.kind, bytes: encode(r.bytes), name: r.name, width: r.width, height: r.height, exact: r.exact,
             sha256: r.sha256, seconds: (performance.now() - started) / 1000 };
  } catch (error) {
    return { error: error.message, code: error.code, params: error.params };
  }
}"""


def browser_reveal(page, model: Path, bundle: Path | bytes, passphrase: str | None = None) -> dict:
    """window.noisenerf.reveal on the files' bytes -> the result (bytes decoded) or {"error": message, "code",
    "params"}."""
    data = bundle if isinstance(bundle, bytes) else bundle.read_bytes()
    result = page.evaluate(REVEAL, [base64.b64encode(model.read_bytes()).decode(), base64.b64encode(data).decode(),
                                    passphrase])
    if "bytes" in result:
        result["bytes"] = base64.b64decode(result["bytes"])
    return result


def cli_message(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, result
    return result.stderr.strip().splitlines()[-1].removeprefix("noisenerf-reveal: error: ")


def png_pixels(data: bytes, folder: Path) -> np.ndarray:
    from noisenerf.runtime.images import load_secret

    path = folder / "decoded.png"
    path.write_bytes(data)
    return load_secret(path)[0]


def test_the_demo_secret_is_the_clis_pixels(page, demo, tmp_path):
    started = time.perf_counter()
    cli = run_reveal(demo / "model.onnx", demo / "secret.bundle", "-o", tmp_path / "cli.png", "--json")
    python_seconds = time.perf_counter() - started
    assert cli.returncode == 0, cli.stderr
    report = json.loads(cli.stdout)
    got = browser_reveal(page, demo / "model.onnx", demo / "secret.bundle")
    assert got["kind"] == "image" and got["exact"] is True and report["exact"] is True
    assert report["tiles"] > 1  # the demo's secret is stitched from tiles
    assert (got["width"], got["height"]) == (report["width"], report["height"])
    want = png_pixels((tmp_path / "cli.png").read_bytes(), tmp_path)
    assert np.array_equal(png_pixels(got["bytes"], tmp_path), want)
    print(f"demo secret: browser reveal {got['seconds']:.3f} s, noisenerf-reveal (process, load included) "
          f"{python_seconds:.3f} s, its own report {report['seconds']} s (render {report['timings']['render']} s)")


def test_a_nerfacto_secret_is_the_clis_pixels(page, nerfacto, tmp_path):
    cli = run_reveal(nerfacto / "model.onnx", nerfacto / "secret.bundle", "-o", tmp_path / "cli.png", "--json")
    assert cli.returncode == 0, cli.stderr
    assert json.loads(cli.stdout)["exact"] is True
    got = browser_reveal(page, nerfacto / "model.onnx", nerfacto / "secret.bundle")
    assert got.get("kind") == "image" and got["exact"] is True, got.get("error")
    assert (got["width"], got["height"]) == (7, 6)
    assert np.array_equal(png_pixels(got["bytes"], tmp_path), png_pixels((tmp_path / "cli.png").read_bytes(), tmp_path))


def test_the_sealed_note_is_the_clis_bytes(page, demo, tmp_path):
    cli = run_reveal(demo / "model.onnx", demo / "note.bundle", "-o", tmp_path / "note.txt",
                     passphrase=DEMO_PASSPHRASE.encode())
    assert cli.returncode == 0, cli.stderr
    got = browser_reveal(page, demo / "model.onnx", demo / "note.bundle", DEMO_PASSPHRASE)
    assert got["kind"] == "file" and got["name"] == "note.txt"
    assert got["bytes"] == (tmp_path / "note.txt").read_bytes() == (demo / "note.txt").read_bytes()


@pytest.mark.parametrize("case", ["wrong passphrase", "tampered bundle", "no passphrase"])
def test_refusals_read_as_the_clis(page, demo, tmp_path, case):
    bundle = demo / "note.bundle"
    passphrase = {"wrong passphrase": "not the demo's", "tampered bundle": DEMO_PASSPHRASE}.get(case)
    if case == "tampered bundle":
        bundle = tmp_path / "note.bundle"
        bundle.write_bytes(flip_first_float32((demo / "note.bundle").read_bytes()))
    cli = run_reveal(demo / "model.onnx", bundle, "-o", tmp_path / "out.txt",
                     passphrase=None if passphrase is None else passphrase.encode())
    got = browser_reveal(page, demo / "model.onnx", bundle, passphrase)
    assert cli.returncode == 2, cli
    with pytest.raises(UserError) as caught:
        library.reveal(demo / "model.onnx", bundle, passphrase)
    assert (got["code"], got["params"]) == (caught.value.code, caught.value.params), (got, str(caught.value))
    assert got["code"] == {"no passphrase": "seal.no_passphrase"}.get(case, "seal.wrong_passphrase")
    assert "\n" not in got["error"]
    assert not (tmp_path / "out.txt").exists()


@pytest.mark.parametrize("bundle_kind", ["the demo's bundle", "a bundle of junk"])
def test_a_model_of_junk_is_refused_before_it_reaches_a_worker_in_the_librarys_order(page, demo, tmp_path,
                                                                                     bundle_kind):
    """The page checks a model's framing itself and sends the worker that refusal, not a copy of the file (one of
    1 GiB cannot be cloned to a worker); the bundle's checks still come first, as in the library."""
    (tmp_path / "junk.onnx").write_bytes(bytes(4096))
    bundle = demo / "secret.bundle"
    if bundle_kind == "a bundle of junk":
        bundle = tmp_path / "junk.bundle"
        bundle.write_bytes(b"\x08" + bytes(100))
    page.evaluate("""() => {  // what the page posts to its reveal worker, from here on
      window.postedModels = [];
      const post = Worker.prototype.postMessage;
      Worker.prototype.postMessage = function (message, ...rest) {
        if (message?.type === "reveal") window.postedModels.push(message.model === null ? null : message.model.length);
        return post.call(this, message, ...rest);
      };
    }""")
    got = browser_reveal(page, tmp_path / "junk.onnx", bundle)
    assert page.evaluate("window.postedModels") == [None]  # the refusal went to the worker, not the file
    with pytest.raises(UserError) as caught:
        library.reveal(tmp_path / "junk.onnx", bundle)
    assert (got["code"], got["params"]) == (caught.value.code, caught.value.params), (got, str(caught.value))
    assert got["code"] == {"a bundle of junk": "bundle.not_safetensors"}.get(bundle_kind, "onnx.malformed")


def test_the_page_saves_a_payload_under_a_chosen_name_and_the_secret_as_png(page, demo, tmp_path):
    page.set_input_files("#model", str(demo / "model.onnx"))
    page.set_input_files("#bundle", str(demo / "note.bundle"))
    page.wait_for_selector("#passphrase", state="visible")
    page.fill("#passphrase", DEMO_PASSPHRASE)
    page.press("#passphrase", "Enter")  # reveals, as the button does
    assert page.is_disabled("#model") and page.is_disabled("#bundle") and page.is_disabled("#reveal")  # while it runs
    page.wait_for_selector("#file-result", state="visible", timeout=60_000)
    assert page.is_enabled("#model") and page.is_enabled("#bundle") and page.is_enabled("#reveal")
    assert page.input_value("#save-name") == "note.txt"
    page.fill("#save-name", "the note.txt")
    with page.expect_download() as download:
        page.click("#save")
    assert download.value.suggested_filename == "the note.txt"
    assert Path(download.value.path()).read_bytes() == (demo / "note.txt").read_bytes()

    page.set_input_files("#bundle", str(demo / "secret.bundle"))
    page.wait_for_selector("#passphrase", state="hidden")
    page.click("#reveal")
    page.wait_for_selector("#image-result", state="visible", timeout=60_000)
    with page.expect_download() as download:
        page.click("#save-image")
    assert download.value.suggested_filename == "revealed.png"
    cli = run_reveal(demo / "model.onnx", demo / "secret.bundle", "-o", tmp_path / "cli.png")
    assert cli.returncode == 0, cli.stderr
    assert np.array_equal(png_pixels(Path(download.value.path()).read_bytes(), tmp_path),
                          png_pixels((tmp_path / "cli.png").read_bytes(), tmp_path))


def test_the_page_refuses_bad_input_with_one_message(page, demo, tmp_path):
    downloads = []
    page.on("download", lambda download: downloads.append(download))
    bad = tmp_path / "bad.bundle"
    bad.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all")
    page.set_input_files("#model", str(demo / "model.onnx"))
    page.set_input_files("#bundle", str(bad))
    page.wait_for_function("document.getElementById('message').textContent !== ''")
    text = page.text_content("#message")
    cli = run_reveal(demo / "model.onnx", bad, "-o", tmp_path / "out.png")
    # the same refusal; the CLI names the file by its path and adds the safetensors reader's own words
    assert text.startswith("not a readable safetensors bundle: ") and "\n" not in text
    assert cli_message(cli).startswith("not a readable safetensors bundle: ")
    assert page.is_disabled("#reveal") and page.is_hidden("#result") and not downloads
