"""Reveal in a browser: the same bundles revealed by headless Chromium through the web page (web/,
onnxruntime-web's WASM backend) and by the Python runtime, in one run.

Both builds render in a pool of Web Workers, one onnxruntime-web session of one thread each (web/src/pool.js),
one per core by default (`navigator.hardwareConcurrency`): the single-file build (web/dist/noisenerf-reveal.html)
at its default and with one worker, and the static site (web/dist/site/) at its default. Both pages and the files
are served from 127.0.0.1 (the single file runs the same opened from disk: tests/test_web_browser.py). Both sides are timed over the same work, from the two files' bytes to the revealed PNG:
the browser's `noisenerf.reveal` (parse and check the bundle and the model, start the sessions, render, SHA-256,
encode the PNG), in a page that has revealed once already (its first reveal, which also starts the workers and
compiles the WASM, is reported apart); Python's `noisenerf-reveal` run in this process after one warm-up reveal
(read and check both files, start the session, render, write the PNG; the interpreter's start and imports
excluded), its fastest on 1 and on as many onnxruntime threads as the page has workers. Python's render alone is
reported beside it. Each reveal is timed several times on both sides (up to `browser_repeats`, fewer where they add
up to REPEAT_SECONDS: a 2048² reveal runs once) and its median is compared: a single second-long reveal in a page
varies by a third from run to run (V8 still tiering the WASM up, the collector). (The page starts from bytes already fetched and keeps its PNG in memory; Python reads the
files from the page cache and writes the PNG: a few hundredths of a second in the page's favour.) Peak memory is the
summed resident set of Chromium's processes, sampled during the reveal.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
import shutil
import statistics
import threading
from collections.abc import Callable
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from noisenerf.cli import reveal as reveal_cli
from noisenerf.runtime.bundle import secret_digest
from noisenerf.runtime.cores import available_cores
from noisenerf.runtime.images import load_secret
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, peak_sampled, resized, size_of
from noisenerf.cli.bench.report import verdict

BROWSER_RATIO_GOAL = 3  # browser reveal time ÷ Python reveal time, on the same bundle and cores
CHROMIUM = Path(os.environ.get("NOISENERF_CHROMIUM", "/usr/lib/chromium/chromium"))
WEB_DIST = Path(__file__).resolve().parents[2] / "web" / "dist"  # a checkout's web/ build (not in a wheel)
PAGES = {"single file": "noisenerf-reveal.html", "site": "site/index.html"}
RUNS = (("single file", None), ("single file", 1), ("site", None))  # (page, workers: None is the pages' default)
REPEAT_SECONDS = 10  # a reveal is repeated (up to browser_repeats times) until its runs add up to this



REVEAL_IN_PAGE = """async ([modelUrl, bundleUrl, workers]) => {
  const fetched = async url => new Uint8Array(await (await fetch(url)).arrayBuffer());
  const [model, bundle] = await Promise.all([fetched(modelUrl), fetched(bundleUrl)]);
  const started = performance.now();
  const revealed = await window.noisenerf.reveal({model, bundle, workers: workers ?? undefined});  // null: its default
  return {seconds: (performance.now() - started) / 1000, exact: revealed.exact, sha256: revealed.sha256,
          workers: revealed.workers};
}"""


def repeated(reveal: Callable[[], dict], most: int) -> dict:
    """`reveal()` -> {"seconds", ...} run up to `most` times, until REPEAT_SECONDS have been spent: the median of
    each timing (a key ending in "seconds"), the runs' seconds, the other fields where every run gave the same
    (else None: a reveal that differs from run to run is not exact)."""
    runs = [reveal()]
    while len(runs) < most and sum(run["seconds"] for run in runs) < REPEAT_SECONDS:
        runs.append(reveal())
    merged = {key: statistics.median(run[key] for run in runs) if key.endswith("seconds")
              else (runs[0][key] if all(run[key] == runs[0][key] for run in runs) else None) for key in runs[0]}
    return {**merged, "runs": [run["seconds"] for run in runs]}


def browser_missing() -> str | None:
    """Why the browser cannot be measured here, or None."""
    if importlib.util.find_spec("playwright") is None:
        return "Playwright is not installed (pip install playwright; its browser download is not needed)"
    if not CHROMIUM.is_file():
        return f"no Chromium at {CHROMIUM} (apt-get install chromium, or set NOISENERF_CHROMIUM)"
    missing = [page for page in PAGES.values() if not (WEB_DIST / page).is_file()]
    if missing:
        return f"the web builds are missing ({', '.join(missing)}): run `npm ci && npm run build` in web/"
    return None


class PageHandler(SimpleHTTPRequestHandler):
    """Static files, quietly."""

    def log_message(self, *args):
        pass


@contextlib.contextmanager
def served(folder: Path):
    """A static server for `folder` on 127.0.0.1; yields its base URL."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(PageHandler, directory=str(folder)))
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


def browser_reveals(dist: Path, bundles: dict[str, Path], model: Path, repeats: int) -> list[dict]:
    """Each bundle revealed in each of RUNS (`repeated`) from a copy of web/dist/ at `dist`; the page's own timing,
    exactness and digest, and peak memory."""
    from playwright.sync_api import sync_playwright

    for path in (model, *bundles.values()):
        shutil.copy(path, dist / "site" / path.name)
        shutil.copy(path, dist / path.name)
    rows = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            for page_name, workers in RUNS:
                page_path = Path(PAGES[page_name])
                with served(dist / page_path.parent) as base:
                    page = browser.new_page()
                    page.goto(f"{base}/{page_path.name}")
                    page.wait_for_function("window.noisenerf !== undefined")
                    urls = [f"{base}/{model.name}", f"{base}/{next(iter(bundles.values())).name}", workers]
                    first = page.evaluate(REVEAL_IN_PAGE, urls)["seconds"]  # workers' start and WASM compile too
                    for name, bundle in bundles.items():
                        with peak_sampled(chromium_rss) as peak:
                            result = repeated(functools.partial(page.evaluate, REVEAL_IN_PAGE, [
                                f"{base}/{model.name}", f"{base}/{bundle.name}", workers]), repeats)
                        rows.append({"page": page_name, "secret": name, **result, "default": workers is None,
                                     "peak_mib": peak[0] / 2 ** 20,
                                     "first_reveal_seconds": first})
                    page.close()
        finally:
            browser.close()
    return rows


def python_reveal(model: Path, bundle: Path, threads: int, out: Path) -> dict:
    """`noisenerf-reveal MODEL BUNDLE -o OUT --threads N` in this process: its seconds (files to PNG) and render."""
    report = reveal_cli.run(reveal_cli.build_parser().parse_args(
        [str(model), str(bundle), "-o", str(out), "--force", "--threads", str(threads)]))
    return {"seconds": float(report["seconds"]), "render_seconds": float(report["timings"]["render"]),
            "exact": report["exact"]}


def measure_browser(context: BenchContext) -> Measured:
    """The bench secret at native size and at browser_size² in tiles, hidden once, revealed by Python (at each
    worker count's threads) and in the pages."""
    config = context.config
    big = resized(context.secret, config.browser_size, config.browser_size)
    secrets = {"native": (context.secret, HideConfig(view=config.view)),
               f"{config.browser_size}²": (big, HideConfig(view=config.view, tile_size=config.twok_tile))}
    cores = available_cores()
    python, bundles = {}, {}
    for name, (secret, hide_config) in secrets.items():
        bundle_name = f"browser_{len(bundles)}"
        report = context.hide(secret, bundle_name, hide_config)
        bundles[name] = context.work / f"{bundle_name}.bundle"
        if not python:  # warm once, as the page is (its first reveal)
            python_reveal(context.model_path, bundles[name], cores, context.work / f"{bundle_name}.png")
        revealed = {threads: repeated(functools.partial(python_reveal, context.model_path, bundles[name], threads,
                                                        context.work / f"{bundle_name}.png"), config.browser_repeats)
                    for threads in sorted({cores, 1})}
        python[name] = {"size": size_of(secret), "tiles": len(report["tiles"]), "python": revealed,
                        "python_exact": all(r["exact"] is True for r in revealed.values()),
                        "python_sha256": secret_digest(load_secret(context.work / f"{bundle_name}.png")[0])}
    missing = browser_missing()
    if missing is not None:
        return Measured([{"secret": name, **flat_python(values, cores), "browser": missing}
                         for name, values in python.items()])
    dist = context.work / "browser_pages"
    shutil.rmtree(dist, ignore_errors=True)
    shutil.copytree(WEB_DIST, dist)
    rows = browser_reveals(dist, bundles, context.model_path, config.browser_repeats)
    for row in rows:
        row.update(flat_python(python[row["secret"]], row["workers"]))
        row["ratio"] = row["seconds"] / row["python_seconds"]
    return Measured(rows)


def flat_python(values: dict, cores: int) -> dict:
    """A secret's Python figures as a row's columns: its fastest reveal on at most `cores` threads (onnxruntime's
    threads need not pay: the conservative comparison for the browser)."""
    threads = min((t for t in values["python"] if t <= cores), key=lambda t: values["python"][t]["seconds"])
    measured = values["python"][threads]
    return {**{key: value for key, value in values.items() if key != "python"}, "python_threads": threads,
            "python_seconds": measured["seconds"], "python_render_seconds": measured["render_seconds"],
            "python_runs": measured["runs"],
            "python_seconds_by_threads": {t: r["seconds"] for t, r in values["python"].items()}}


def spread(runs: list[float]) -> str:
    """A repeated reveal's runs, for a table: their count and range."""
    return "1 run" if len(runs) == 1 else f"{len(runs)} runs, {min(runs):.2f}–{max(runs):.2f}"


def describe_browser(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    if any("browser" in row for row in rows):
        return [f"Not measured in the browser: {rows[0]['browser']}. Python reveal (files to PNG): "
                + ", ".join(f"{row['secret']} {row['python_seconds']:.2f} s" for row in rows) + "."]
    shipped = [row for row in rows if row["default"]]  # the pages as a recipient gets them
    cores = max(row["workers"] for row in shipped)
    worst = max(row["ratio"] for row in shipped)
    single = [row["ratio"] for row in rows if row["workers"] == 1]
    lines = [f"Chromium {CHROMIUM} (headless), onnxruntime-web WASM in a pool of workers of one thread each; Python: "
             "`noisenerf-reveal` in process, its fastest of 1 and as many onnxruntime threads as the page has workers; "
             f"medians of up to {context.config.browser_repeats} runs (a {REPEAT_SECONDS} s budget) on both sides; "
             f"both from the files' bytes to the PNG. {os.cpu_count()} cores. The bench secret at native size and "
             f"resized to {context.config.browser_size}² in {context.config.twok_tile}-px tiles.", "",
             f"- the pages as shipped ({cores} workers, one per core) ÷ Python on as many cores, worst: **{worst:.1f}×** "
             f"(goal ≤ {BROWSER_RATIO_GOAL}: {verdict(worst, BROWSER_RATIO_GOAL, lower_is_better=True)}).",
             f"- single-threaded (1 worker ÷ Python on 1 thread): {min(single):.1f}–{max(single):.1f}×; its floor is "
             "onnxruntime-web's WASM matrix kernels (128-bit SIMD without fused multiply-add) against native AVX2/FMA.",
             "- A page's first reveal (workers' start, WASM compile, the native secret): "
             + ", ".join(sorted({f"{r['page']}, {r['workers']} workers {r['first_reveal_seconds']:.2f} s" for r in rows}))
             + ".", "- Python on 1 / " + f"{cores} threads, s: "
             + ", ".join(sorted({f"{r['secret']} " + " / ".join(f"{v:.2f}" for _, v in sorted(r["python_seconds_by_threads"].items()))
                                 for r in rows})) + ".", "",
             "| page | workers | secret | size | tiles | browser s (runs) | Python s (render; runs), threads | browser ÷ Python | "
             "exact (browser, Python) | same digest | peak Chromium MiB |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['page']} | {r['workers']} | {r['secret']} | {r['size'][0]}×{r['size'][1]} | {r['tiles']} | "
              f"{r['seconds']:.2f} ({spread(r['runs'])}) | {r['python_seconds']:.2f} ({r['python_render_seconds']:.2f}; "
              f"{spread(r['python_runs'])}), {r['python_threads']} "
              f"thread{'s' if r['python_threads'] > 1 else ''} | {r['ratio']:.1f} | "
              f"{str(r['exact']).lower()}, {str(r['python_exact']).lower()} | "
              f"{str(r['sha256'] == r['python_sha256']).lower()} | {r['peak_mib']:.0f} |" for r in rows]
    return lines
