"""The page's reveal on onnxruntime-web's WebGPU provider against its WASM one and the Python runtime (issue 49; CI
never runs it): photos hidden at two views of the demo scene (MLP) and of a random hash grid, each bundle rendered in
headless Chromium by the page's own modules (web/src: the bundle, the model, LocalRenderer, renderTile) on
"webgpu" and on "wasm", every tile's float colours compared with onnxruntime's CPU provider: the largest difference
in levels, exactness, the smallest rounding margin. JSON lines on stdout, a summary last:

    python tools/webgpu_exactness.py WIDTH PHOTO...

Chromium runs with --enable-unsafe-webgpu; without a GPU its WebGPU adapter is SwiftShader's (Vulkan on the CPU),
which runs onnxruntime-web's WGSL kernels as a GPU would. Needs `npm ci` in web/ and Debian's chromium.
"""

from __future__ import annotations

import functools
import http.server
import json
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import torch

from noisenerf.cli.bench.context import small_secret
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret, to_uint8
from noisenerf.runtime.metrics import rounding_margins
from noisenerf.runtime.model import load_model
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import DEMO_SCENE
from noisenerf.train.scene.random_scene import random_scene
from noisenerf.train.scene.scene import load_scene

WEB = Path(__file__).resolve().parents[1] / "web"
CHROMIUM = "/usr/lib/chromium/chromium"
PROBE = """
import * as ort from "onnxruntime-web/webgpu";
import { loadBundle } from "./bundle.js";
import { checkModel } from "./model.js";
import { LocalRenderer, renderTile, tileNetwork } from "./reveal.js";
ort.env.wasm.numThreads = 1;
ort.env.wasm.wasmPaths = "/";
window.probe = async (modelUrl, bundleUrl, provider) => {
  const model = new Uint8Array(await (await fetch(modelUrl)).arrayBuffer());
  const checked = checkModel(model);
  const bundle = await loadBundle(new Uint8Array(await (await fetch(bundleUrl)).arrayBuffer()), "secret.bundle",
    checked.maskSecret);
  const renderer = await LocalRenderer.open(model, checked.networks, checked.networks, provider);
  const image = new Float32Array(bundle.width * bundle.height * 3);
  try {
    for (const tile of bundle.tiles) {
      const [x0, y0, w, h] = tile.rect;
      const colors = await renderTile(tile, bundle, checked.metadata.renderConfig, renderer,
        tileNetwork(tile, checked.networks));
      for (let y = 0; y < h; y++) image.set(colors.subarray(y * w * 3, (y + 1) * w * 3), ((y0 + y) * bundle.width + x0) * 3);
    }
  } finally {
    await renderer.release();
  }
  return Array.from(image);
};
"""


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # the JSON lines are the output
        pass


def build_probe(site: Path) -> None:
    """The probe's script, bundled by esbuild from web/src on onnxruntime-web's WebGPU build, and its JSEP binary."""
    script = ("import * as esbuild from 'esbuild'; await esbuild.build({stdin: {contents: process.argv[1], "
              "resolveDir: 'src', loader: 'js'}, bundle: true, format: 'esm', platform: 'browser', target: 'es2022', "
              f"outfile: {json.dumps(str(site / 'probe.js'))}, logLevel: 'warning'}});")
    subprocess.run(["node", "--input-type=module", "-e", script, PROBE], cwd=WEB, check=True)
    for name in ("ort-wasm-simd-threaded.jsep.mjs", "ort-wasm-simd-threaded.jsep.wasm"):
        shutil.copyfile(WEB / "node_modules" / "onnxruntime-web" / "dist" / name, site / name)
    (site / "index.html").write_text('<html><body><script type="module" src="probe.js"></script></body></html>')


def fixtures(site: Path, width: int, photos: list[str]) -> list[dict]:
    """Bundles hidden in the two scenes, each with the secret and onnxruntime's CPU render (float)."""
    cases = []
    for kind, scene, views in (("mlp", load_scene(DEMO_SCENE), (2, 30)),
                               ("hashgrid", random_scene(seed=2, kind="hashgrid"), (1, 4))):
        scene.save(site / kind)
        export_scene(site / kind, site / f"{kind}.onnx")
        model = load_model(site / f"{kind}.onnx")
        for photo in photos:
            secret = small_secret(load_secret(photo)[0], width)
            for view in views:
                name = f"{kind}_{Path(photo).stem}_{view}.bundle"
                hide(scene, secret, site / name, HideConfig(view=view), torch.device("cpu"))
                base = reveal_tiles(load_bundle(site / name, model.mask_secret), model.render_config, model.fields(),
                                    keep_float=True)
                cases.append({"kind": kind, "photo": Path(photo).name, "view": view, "model": f"{kind}.onnx",
                              "bundle": name, "secret": secret, "cpu": base.image})
    return cases


def main(width: int, photos: list[str]) -> None:
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as folder:
        site = Path(folder)
        build_probe(site)
        cases = fixtures(site, width, photos)
        handler = functools.partial(QuietHandler, directory=str(site))
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        rows = []
        try:
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True,
                                                     args=["--no-sandbox", "--enable-unsafe-webgpu"])
                page = browser.new_page()
                page.goto(f"http://127.0.0.1:{server.server_port}/index.html")
                page.wait_for_function("window.probe !== undefined")
                adapter = page.evaluate("async () => { const a = await navigator.gpu?.requestAdapter(); "
                                        "return a ? a.info.vendor + ' ' + a.info.architecture : null; }")
                print(json.dumps({"chromium": browser.version, "webgpu_adapter": adapter}), flush=True)
                for case in cases:
                    row = {key: case[key] for key in ("kind", "photo", "view")}
                    for provider in ("webgpu", "wasm"):
                        image = np.asarray(page.evaluate("([m, b, p]) => window.probe(m, b, p)",
                                                         [case["model"], case["bundle"], provider]), np.float32)
                        image = image.reshape(case["cpu"].shape)
                        row[provider] = {"exact": bool(np.array_equal(to_uint8(image), case["secret"])),
                                         "margin": float(rounding_margins(image, case["secret"]).min()),
                                         "levels_from_cpu": float(np.abs(image - case["cpu"]).max() * 255)}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
                browser.close()
        finally:
            server.shutdown()
    print(json.dumps({provider: {"exact": sum(row[provider]["exact"] for row in rows), "of": len(rows),
                                 "largest_levels_from_cpu": max(row[provider]["levels_from_cpu"] for row in rows),
                                 "smallest_margin": min(row[provider]["margin"] for row in rows)}
                      for provider in ("webgpu", "wasm")}), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2:])
