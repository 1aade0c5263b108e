// `npm run build`: the page's two builds with esbuild.
//   dist/site/                 index.html, page.js, worker.js and onnxruntime-web's .wasm (from node_modules):
//                              any static server
//   dist/noisenerf-reveal.html one self-contained file that works opened from disk (file://): the page's script,
//                              the worker (run from a Blob URL) and the WASM binary (base64) inline
// Neither fetches anything from elsewhere at run time: the site loads only its own files, the single file nothing.

import * as esbuild from "esbuild";
import fs from "node:fs";
import path from "node:path";
import { fileURLToPath } from "node:url";

const here = path.dirname(fileURLToPath(import.meta.url));
const dist = path.join(here, "dist");
const site = path.join(dist, "site");
const WASM = "ort-wasm-simd-threaded.wasm"; // the binary onnxruntime-web/wasm's bundle loads
const wasmPath = path.join(here, "node_modules", "onnxruntime-web", "dist", WASM);

// onnxruntime-web's WASM-only build (its default one embeds the WebGPU/JSEP glue, which needs the larger JSEP .wasm)
const common = { alias: { "onnxruntime-web": "onnxruntime-web/wasm" }, bundle: true, format: "esm", platform: "browser", target: "es2022", minify: !process.env.NOISENERF_DEBUG, legalComments: "none",
  logLevel: "warning" };

/** The page's "noisenerf-embedded" module: the worker's code and the WASM in the single file, nothing in the site. */
const embedded = (contents) => ({
  name: "noisenerf-embedded",
  setup(build) {
    build.onResolve({ filter: /^noisenerf-embedded$/ }, () => ({ path: "embedded", namespace: "noisenerf-embedded" }));
    build.onLoad({ filter: /.*/, namespace: "noisenerf-embedded" }, () => ({ contents, loader: "js" }));
  },
});

fs.rmSync(dist, { recursive: true, force: true });
fs.mkdirSync(site, { recursive: true });

// the site's worker is a module worker; the single file's a classic one (Chromium refuses module workers from Blob
// URLs on a file:// page), where import.meta.url is the worker's own Blob URL
const workerBuild = async (format) => (await esbuild.build({ ...common, format, write: false,
  entryPoints: [path.join(here, "src/page/worker.js")],
  ...(format === "iife" ? { define: { "import.meta.url": "self.location.href" } } : {}) })).outputFiles[0].text;
const workerCode = await workerBuild("esm");
const html = fs.readFileSync(path.join(here, "src/page/index.html"), "utf8");
const tag = '<script type="module" src="page.js"></script>';
if (!html.includes(tag)) throw new Error(`src/page/index.html must load page.js with ${tag}`);

// the static site
fs.writeFileSync(path.join(site, "worker.js"), workerCode);
await esbuild.build({ ...common, entryPoints: [path.join(here, "src/page/page.js")], outfile: path.join(site, "page.js"),
  plugins: [embedded("export const workerCode = null, wasmBase64 = null;")] });
fs.copyFileSync(wasmPath, path.join(site, WASM));
fs.writeFileSync(path.join(site, "index.html"), html);

// the single file
const wasmBase64 = fs.readFileSync(wasmPath).toString("base64");
const page = await esbuild.build({ ...common, entryPoints: [path.join(here, "src/page/page.js")], write: false,
  plugins: [embedded(`export const workerCode = ${JSON.stringify(await workerBuild("iife"))}; export const wasmBase64 = "${wasmBase64}";`)] });
// inside an inline <script>, "</script" would end it: only strings, regexes and comments can hold it, where "<\/" reads the same
const script = page.outputFiles[0].text.replace(/<\/(script)/gi, "<\\/$1");
fs.writeFileSync(path.join(dist, "noisenerf-reveal.html"), html.replace(tag, () => `<script type="module">${script}</script>`));

for (const file of [path.join(dist, "noisenerf-reveal.html"), ...fs.readdirSync(site).map((f) => path.join(site, f))]) {
  console.log(`${path.relative(here, file)}: ${fs.statSync(file).size} bytes`);
}
