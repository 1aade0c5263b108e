"""Reveal in a browser: the same bundles revealed by headless Chromium through the web page (web/,
onnxruntime-web's WASM backend) and by the Python runtime, in one run.

Two pages: the single-file build (web/dist/noisenerf-reveal.html), served without cross-origin isolation,
so onnxruntime-web runs one thread, as it does opened from disk; and the static site (web/dist/site/),
served with the COOP/COEP headers that allow WASM threads. Both are served from 127.0.0.1 with the model
and bundles beside them. The browser's time covers parsing, checking and rendering (what a recipient
waits for after dropping the files), in a page that has revealed once already (its first reveal, which
also starts the worker and compiles the WASM, is reported apart); the Python time is `reveal` alone on an
already loaded model. Peak memory is the summed resident set of Chromium's
processes, sampled during the reveal.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from noisenerf.runtime.bundle import secret_digest
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, peak_sampled, resized, size_of
from noisenerf.cli.bench.report import verdict

BROWSER_RATIO_GOAL = 3  # browser reveal time ÷ Python reveal time, on the same bundle
CHROMIUM = Path(os.environ.get("NOISENERF_CHROMIUM", "/usr/lib/chromium/chromium"))
WEB_DIST = Path(__file__).resolve().parents[2] / "web" / "dist"  # a checkout's web/ build (not in a wheel)
PAGES = {"single file, 1 thread": ("noisenerf-reveal.html", False), "site, threads": ("site/index.html", True)}

REVEAL_IN_PAGE = """async ([modelUrl, bundleUrl]) => {
  const fetched = async url => new Uint8Array(await (await fetch(url)).arrayBuffer());
  const [model, bundle] = await Promise.all([fetched(modelUrl), fetched(bundleUrl)]);
  const started = performance.now();
  const revealed = await window.noisenerf.reveal({model, bundle});
  return {seconds: (performance.now() - started) / 1000, exact: revealed.exact, sha256: revealed.sha256,
          isolated: self.crossOriginIsolated};
}"""


def browser_missing() -> str | None:
    """Why the browser cannot be measured here, or None."""
    if importlib.util.find_spec("playwright") is None:
        return "Playwright is not installed (pip install playwright; its browser download is not needed)"
    if not CHROMIUM.is_file():
        return f"no Chromium at {CHROMIUM} (apt-get install chromium, or set NOISENERF_CHROMIUM)"
    missing = [page for page, _ in PAGES.values() if not (WEB_DIST / page).is_file()]
    if missing:
        return f"the web builds are missing ({', '.join(missing)}): run `npm ci && npm run build` in web/"
    return None


class PageHandler(SimpleHTTPRequestHandler):
    """Static files, with the headers that make a page cross-origin isolated when the server is."""

    def end_headers(self):
        if self.server.isolated:
            self.send_header("Cross-Origin-Opener-Policy", "same-origin")
            self.send_header("Cross-Origin-Embedder-Policy", "require-corp")
        super().end_headers()

    def log_message(self, *args):
        pass


@contextlib.contextmanager
def served(folder: Path, isolated: bool):
    """A static server for `folder` on 127.0.0.1; yields its base URL."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(PageHandler, directory=str(folder)))
    server.isolated = isolated
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def chromium_rss() -> int:
    """Bytes resident in every Chromium process on this machine (the bench's own, where it runs alone)."""
    total = 0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            if (entry / "cmdline").read_bytes().split(b"\0")[0] == str(CHROMIUM).encode():
                pages = int((entry / "statm").read_text().split()[1])
                total += pages * os.sysconf("SC_PAGE_SIZE")
    return total




def browser_reveals(site: Path, bundles: dict[str, Path], model: Path) -> list[dict]:
    """Each bundle revealed on each page; the page's own timing, exactness and digest, and peak memory."""
    from playwright.sync_api import sync_playwright

    for path in (model, *bundles.values()):
        shutil.copy(path, site / "site" / path.name)
        shutil.copy(path, site / path.name)
    rows = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            for page_name, (page_path, isolated) in PAGES.items():
                base_folder = site / Path(page_path).parent
                with served(base_folder, isolated) as base:
                    page = browser.new_page()
                    page.goto(f"{base}/{Path(page_path).name}")
                    page.wait_for_function("window.noisenerf !== undefined")
                    urls = [f"{base}/{model.name}", f"{base}/{next(iter(bundles.values())).name}"]
                    first = page.evaluate(REVEAL_IN_PAGE, urls)["seconds"]  # worker start and WASM compile too
                    for name, bundle in bundles.items():
                        with peak_sampled(chromium_rss) as peak:
                            result = page.evaluate(REVEAL_IN_PAGE, [f"{base}/{model.name}", f"{base}/{bundle.name}"])
                        rows.append({"page": page_name, "secret": name, **result, "peak_mib": peak[0] / 2 ** 20,
                                     "first_reveal_seconds": first})
                    page.close()
        finally:
            browser.close()
    return rows


def measure_browser(context: BenchContext) -> Measured:
    """The bench secret at native size and at browser_size² in tiles, hidden once, revealed by Python and
    by both pages."""
    config = context.config
    big = resized(context.secret, config.browser_size, config.browser_size)
    secrets = {"native": (context.secret, HideConfig(view=config.view)),
               f"{config.browser_size}²": (big, HideConfig(view=config.view, tile_size=config.twok_tile))}
    python, bundles = {}, {}
    for name, (secret, hide_config) in secrets.items():
        bundle_name = f"browser_{len(bundles)}"
        report, revealed, seconds = context.hide_and_reveal(secret, bundle_name, hide_config)
        python[name] = {"size": size_of(secret), "tiles": len(report["tiles"]), "python_seconds": seconds,
                        "python_exact": revealed.exact, "python_sha256": secret_digest(revealed.pixels)}
        bundles[name] = context.work / f"{bundle_name}.bundle"
    missing = browser_missing()
    if missing is not None:
        return Measured([{"secret": name, **values, "browser": missing} for name, values in python.items()])
    site = context.work / "browser_pages"
    shutil.rmtree(site, ignore_errors=True)
    shutil.copytree(WEB_DIST, site)
    rows = browser_reveals(site, bundles, context.model_path)
    for row in rows:
        row.update(python[row["secret"]], ratio=row["seconds"] / python[row["secret"]]["python_seconds"])
    return Measured(rows)


def describe_browser(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    if any("browser" in row for row in rows):
        return [f"Not measured in the browser: {rows[0]['browser']}. Python reveal: "
                + ", ".join(f"{row['secret']} {row['python_seconds']:.2f} s" for row in rows) + "."]
    worst = max(row["ratio"] for row in rows)
    lines = [f"Chromium {CHROMIUM} (headless), onnxruntime-web WASM; Python: `reveal` with onnxruntime on "
             f"{os.cpu_count()} cores. The bench secret at native size and resized to {context.config.browser_size}² "
             f"in {context.config.twok_tile}-px tiles.", "",
             f"- worst browser ÷ Python reveal: **{worst:.1f}×** (goal ≤ {BROWSER_RATIO_GOAL}: "
             f"{verdict(worst, BROWSER_RATIO_GOAL, lower_is_better=True)}). A page's first reveal (worker start, "
             "WASM compile, the native secret): " + ", ".join(sorted({f"{r['page']} {r['first_reveal_seconds']:.2f} s"
                                                                  for r in rows})) + ".", "",
             "| page | secret | size | tiles | browser s | Python s | browser ÷ Python | isolated | exact (browser, Python) | "
             "same digest | peak Chromium MiB |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['page']} | {r['secret']} | {r['size'][0]}×{r['size'][1]} | {r['tiles']} | {r['seconds']:.2f} | "
              f"{r['python_seconds']:.2f} | {r['ratio']:.1f} | {str(r['isolated']).lower()} | "
              f"{str(r['exact']).lower()}, {str(r['python_exact']).lower()} | "
              f"{str(r['sha256'] == r['python_sha256']).lower()} | {r['peak_mib']:.0f} |" for r in rows]
    return lines
