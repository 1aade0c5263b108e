// Mirrors runtime/bundle.py: the safetensors bundle (header JSON + tensors, dtypes F16/F32/U8/I32 only), its
// metadata checked with the same messages and caps before anything is allocated (formats 1–2; ray, sample and
// compact layouts), the compact layout's xz byte planes, and the noise expansion per layout (`rows`).

import xz from "xz-decompress";
import { UserError, repr, reprCut, tuple, PyFloat } from "./errors.js";
import { isJsonObject as isObject, parseJson } from "./json.js";
import {
  MAX_CAMERAS, MAX_COMPACT_COEFFICIENTS, checkedExpansion, MAX_IMAGE_SIDE, MAX_NOISE_DIMS, MAX_RAY_LAYOUT_SAMPLES, MAX_TILES,
  checkedFloat, checkedImageSize, checkedInt, checkedList,
} from "./limits.js";
import { cameraFromDict } from "./camera.js";
import { fmaf32 } from "./float32.js";
import { samplingFromDict } from "./sampling.js";
import { checkedPayload } from "./payload.js";

const { XzReadableStream } = xz;
const f32 = Math.fround;
export const NOISENERF_VERSION = "0.1.0"; // noisenerf.__version__ of the Python runtime this port mirrors
export const METADATA_KEY = "noisenerf_bundle";
const READABLE_FORMATS = { 1: ["ray", "sample"], 2: ["ray", "sample", "compact"] };
const LAYOUTS = READABLE_FORMATS[2];
const LAYOUT_DTYPES = { ray: ["float16", "float32"], sample: ["float32", "float16"], compact: ["int16", "int8"] };
const SAFETENSORS_DTYPES = ["F16", "F32", "U8", "I32"];
const NUMPY_NAMES = { F16: "float16", F32: "float32", U8: "uint8", I32: "int32" };
const ITEM_SIZE = { F16: 2, F32: 4, U8: 1, I32: 4, I8: 1, I16: 2, BOOL: 1, F64: 8, I64: 8, U16: 2, U32: 4, U64: 8, BF16: 2 };
export const NETWORKS = ["coarse", "fine"];
const FLOAT32_TINY = 1.1754943508222875e-38, FLOAT32_MAX = 3.4028234663852886e38;

/** IEEE half -> float. */
const HALF = new Float32Array(65536);
for (let h = 0; h < 65536; h++) {
  const sign = h & 0x8000 ? -1 : 1, exp = (h >> 10) & 0x1f, frac = h & 0x3ff;
  HALF[h] = exp === 0 ? sign * frac * 2 ** -24 : exp === 31 ? (frac ? NaN : sign * Infinity) : sign * (1 + frac / 1024) * 2 ** (exp - 15);
}

/** float16 values (their bits) -> Float32Array. */
function widened(halves) {
  const values = new Float32Array(halves.length);
  for (let i = 0; i < halves.length; i++) values[i] = HALF[halves[i]];
  return values;
}

/** A tensor as read: {dtype (numpy name), shape, values (typed array; float16 kept as its bits, a Uint16Array, and
 * widened a chunk at a time as runtime/ does: a float16 view's noise is not held twice as large)}. */
function decodeTensor(dtype, shape, bytes) {
  const copy = bytes.slice();
  const count = copy.length / ITEM_SIZE[dtype];
  const Kind = { F32: Float32Array, I32: Int32Array, U8: Uint8Array, F16: Uint16Array }[dtype];
  return { dtype: NUMPY_NAMES[dtype], shape, values: new Kind(copy.buffer, 0, count) };
}

/** The safetensors file: header checks as the safetensors library makes them -> {metadata, tensors (lazy)}. */
function readSafetensors(data, source) {
  const fail = (why) => new UserError(`not a readable safetensors bundle: ${source} (${why})`);
  if (data.length < 8) throw fail("HeaderTooSmall");
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const size = Number(view.getBigUint64(0, true));
  if (size > 100_000_000) throw fail("HeaderTooLarge");
  if (8 + size > data.length) throw fail("InvalidHeaderLength");
  let header;
  try {
    header = JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(data.subarray(8, 8 + size)));
  } catch (error) {
    throw fail(`InvalidHeaderDeserialization`);
  }
  if (header === null || typeof header !== "object" || Array.isArray(header)) throw fail("InvalidHeaderDeserialization");
  const metadata = header.__metadata__ ?? null;
  const entries = Object.entries(header).filter(([name]) => name !== "__metadata__")
    .sort((a, b) => a[1]?.data_offsets?.[0] - b[1]?.data_offsets?.[0]);
  const body = data.subarray(8 + size);
  let end = 0;
  const tensors = new Map();
  for (const [name, info] of entries) {
    if (!info || typeof info.dtype !== "string" || !Array.isArray(info.shape) || !Array.isArray(info.data_offsets)) {
      throw fail("InvalidHeaderDeserialization");
    }
    const [begin, stop] = info.data_offsets;
    if (!(info.dtype in ITEM_SIZE)) throw fail("InvalidHeaderDeserialization");
    const count = info.shape.reduce((a, b) => a * b, 1);
    if (begin !== end || stop < begin || stop - begin !== count * ITEM_SIZE[info.dtype]) throw fail(`InvalidOffset(${repr(name)})`);
    end = stop;
    tensors.set(name, { dtype: info.dtype, shape: info.shape, bytes: body.subarray(begin, stop) });
  }
  if (end !== body.length) throw fail("MetadataIncompleteBuffer");
  return { metadata, tensors };
}

function checkedText(value, what) {
  if (typeof value !== "string" || value.length > 256) throw new UserError(`${what} must be a string of at most 256 characters`);
  return value;
}

function checkedFormat(meta, source) {
  let version = meta.format_version;
  const key = typeof version === "number" ? version : version instanceof PyFloat ? version.value : null;
  if (typeof version === "boolean" || !(key in READABLE_FORMATS)) {
    throw new UserError(`${source} is bundle format ${reprCut(version === undefined ? null : version, 20)}; noisenerf ${NOISENERF_VERSION} reads formats 1 to 2` +
      (typeof version === "number" && Number.isInteger(version) && version > 2 ? "; a newer noisenerf is needed" : ""));
  }
  return key;
}

function validateNoiseHeader(layout, dtype, dims, coefficients, layouts = LAYOUTS) {
  if (!layouts.includes(layout)) throw new UserError(`bundle: unknown noise layout ${reprCut(layout, 40)} (expected one of ${repr(tuple(...layouts))})`);
  if (!LAYOUT_DTYPES[layout].includes(dtype)) {
    throw new UserError(`bundle: unknown noise dtype ${reprCut(dtype, 40)} for the ${layout} layout (expected one of ${repr(tuple(...LAYOUT_DTYPES[layout]))})`);
  }
  if ((coefficients !== null) !== (layout === "compact")) throw new UserError("bundle: coefficients per pixel are given for, and only for, the compact layout");
  const most = Math.min(dims, MAX_COMPACT_COEFFICIENTS);
  if (layout === "compact" && !(coefficients >= 1 && coefficients <= most)) {
    throw new UserError(`bundle: ${coefficients} coefficients per pixel, expected 1 to ${most}`);
  }
}

function noiseHeader(noise, layouts) {
  const layout = checkedText(noise.layout, "bundle: noise layout");
  const header = { layout, dims: checkedInt(noise.dims, "bundle: noise dims", 1, MAX_NOISE_DIMS),
    dtype: checkedText(noise.dtype, "bundle: noise dtype"), coefficients: null };
  if (layout === "compact") {
    header.coefficients = checkedInt(noise.coefficients, "bundle: coefficients per pixel", 1, MAX_COMPACT_COEFFICIENTS);
    if (noise.codec !== "xz-byte-planes") throw new UserError(`bundle: unknown coefficient codec ${reprCut(noise.codec ?? null, 40)} (expected 'xz-byte-planes')`);
  }
  validateNoiseHeader(header.layout, header.dtype, header.dims, header.coefficients, layouts);
  return header;
}

function checkedRect(i, data) {
  if (!isObject(data)) throw new UserError(`bundle: tile ${i} must be a JSON object`);
  const rect = checkedList(data.rect, `bundle: tile ${i} rect`, 4);
  const x0 = checkedInt(rect[0], `bundle: tile ${i} rect origin`, 0, MAX_IMAGE_SIDE);
  const y0 = checkedInt(rect[1], `bundle: tile ${i} rect origin`, 0, MAX_IMAGE_SIDE);
  return [x0, y0, ...checkedImageSize(rect[2], rect[3], `bundle: tile ${i} rect`)];
}

function tileTensor(tensors, name, what, dtype = null, ndim = null) {
  if (!tensors.has(name)) throw new UserError(`${what} tensor ${reprCut(name, 60)} is missing`);
  const value = tensors.get(name);
  if ((dtype !== null && value.dtype !== dtype) || (ndim !== null && value.shape.length !== ndim)) {
    throw new UserError(`${what} tensor ${reprCut(name, 60)} is ${value.dtype} ${repr(tuple(...value.shape))}`);
  }
  return value;
}

// xz-embedded's error codes (enum xz_ret) in liblzma's words, as Python's lzma gives them. Its dictionaries stop at
// 64 MiB; the next size a stream can state, 96 MiB, is over runtime's MAX_XZ_MEMORY too.
const XZ_ERRORS = { 2: "Unsupported integrity check", 3: "Cannot allocate memory", 4: "Memory usage limit exceeded",
  5: "Input format not supported by decoder", 6: "Invalid or unsupported options", 7: "Corrupt input data" };
const XZ_BUF_ERROR = 8; // the stream ended early, or more followed it: Python reads on and finds the length wrong

/** unpack_coefficients: the xz stream of byte planes -> Int8Array/Int16Array (h·w·k, row-major (h, w, k)). */
async function unpackCoefficients(packed, shape, dtype, what) {
  const [height, width, k] = shape;
  const item = dtype === "int16" ? 2 : 1;
  const expected = height * width * k * item;
  let data;
  try {
    const stream = new XzReadableStream(new Blob([packed]).stream());
    const reader = stream.getReader();
    const parts = [];
    let total = 0;
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      parts.push(value);
      total += value.length;
      if (total > expected) { await reader.cancel(); break; }
    }
    data = new Uint8Array(total);
    let at = 0;
    for (const part of parts) { data.set(part, at); at += part.length; }
  } catch (error) {
    const code = Number(/error code (\d+)/.exec(String(error?.message ?? error))?.[1]);
    if (code !== XZ_BUF_ERROR) {
      throw new UserError(`${what}: compressed coefficients are corrupt (${XZ_ERRORS[code] ?? "Corrupt input data"})`);
    }
    data = null;
  }
  if (data === null || data.length !== expected) {
    throw new UserError(`${what}: compressed coefficients do not hold exactly ${repr(tuple(height, width, k))} ${dtype} values`);
  }
  const n = height * width;
  const out = dtype === "int16" ? new Int16Array(n * k) : new Int8Array(n * k);
  for (let c = 0; c < k; c++) {
    for (let p = 0; p < n; p++) {
      if (item === 1) out[p * k + c] = (data[c * n + p] << 24) >> 24;
      else out[p * k + c] = ((data[(c * 2) * n + p] | (data[(c * 2 + 1) * n + p] << 8)) << 16) >> 16;
    }
  }
  return out;
}

/** expand_coefficients: noise of m compact pixels (coefficients m·k), float32 (one multiply by the scale, then the
 * matmul offset + params @ basisᵀ), escaped pixels' stored noise in place. -> Float32Array (m·dims).
 * numpy's float32 matmul is OpenBLAS's sgemm, which on FMA hardware (Haswell and later) accumulates
 * k = 0..K-1 with one fused multiply-add each: the order reproduced here (web/test checks it bit for bit). */
export function expandCoefficients(coefficients, k, basis) {
  const dims = basis.offset.length, m = coefficients.length / k;
  const out = new Float32Array(m * dims);
  const scale = f32(basis.scale), matrix = basis.basis, offset = basis.offset;
  // A zero basis entry adds +0 to a sum that is never −0, so leaving it out changes no bit; a compact tile's
  // basis is zero on every γ(x) row (its noise moves the view direction only): those rows are the offset for
  // every pixel (`fixed`). The others are `live`: terms[first[i] .. first[i + 1]) are live row i's nonzero
  // columns and values, in the order numpy sums them.
  const fixed = new Float32Array(dims), liveRows = [], first = [0], columns = [], values = [];
  for (let d = 0; d < dims; d++) {
    fixed[d] = f32(offset[d] + 0);
    const before = columns.length;
    for (let c = 0; c < k; c++) if (matrix[d * k + c] !== 0) { columns.push(c); values.push(matrix[d * k + c]); }
    if (columns.length > before) { liveRows.push(d); first.push(columns.length); }
  }
  const live = Int32Array.from(liveRows), from = Int32Array.from(first), column = Int32Array.from(columns);
  const value = Float64Array.from(values), params = new Float64Array(k);
  for (let p = 0; p < m; p++) {
    const row = p * k, at = p * dims;
    for (let c = 0; c < k; c++) params[c] = f32(coefficients[row + c] * scale);
    out.set(fixed, at);
    for (let i = 0; i < live.length; i++) {
      let t = from[i];
      let dot = f32(params[column[t]] * value[t]) + 0; // fmaf(a, b, +0): the product rounded once, −0 made +0
      for (t++; t < from[i + 1]; t++) dot = fmaf32(params[column[t]], value[t], dot);
      out[at + live[i]] = f32(offset[live[i]] + dot);
    }
  }
  const escapes = basis.escapes;
  for (let e = 0; e < escapes.length; e++) out.set(basis.escapeNoise.subarray(e * dims, (e + 1) * dims), escapes[e] * dims);
  return out;
}

/** A tile's noise for its pixels start..stop, on its own: only those pixels' stored values (copies, so that a
 * worker is sent them alone), escaped pixels renumbered from the chunk's first. -> a record chunkRows expands. */
export function chunkNoise(tile, bundle, start, stop) {
  const dims = bundle.noiseDims;
  if (bundle.layout !== "compact") {
    const per = bundle.layout === "sample" ? tile.sampling.nSamples : 1;
    const stored = tile.noise.values.subarray(start * per * dims, stop * per * dims);
    return { layout: bundle.layout, values: stored instanceof Uint16Array ? widened(stored) : stored.slice(), perSample: per, dims };
  }
  const k = bundle.coefficients, { basis, offset, scale, escapes, escapeNoise } = tile.noise.basis;
  const inside = [];
  for (let e = 0; e < escapes.length; e++) if (escapes[e] >= start && escapes[e] < stop) inside.push(e);
  const chunkEscapes = Int32Array.from(inside, (e) => escapes[e] - start);
  const chunkEscapeNoise = new Float32Array(inside.length * dims);
  inside.forEach((e, i) => chunkEscapeNoise.set(escapeNoise.subarray(e * dims, (e + 1) * dims), i * dims));
  return { layout: "compact", coefficients: tile.noise.coefficients.slice(start * k, stop * k), k, dims,
    basis: { basis, offset, scale, escapes: chunkEscapes, escapeNoise: chunkEscapeNoise } };
}

/** A chunk's float32 noise (chunkNoise's record): {values, perSample (1 or n_samples), dims}. */
export function chunkRows(noise) {
  if (noise.layout !== "compact") return { values: noise.values, perSample: noise.perSample, dims: noise.dims };
  return { values: expandCoefficients(noise.coefficients, noise.k, noise.basis), perSample: 1, dims: noise.dims };
}

/** The float32 noise of a tile's pixels start..stop: {values, perSample (1 or n_samples), dims}. */
export function tileRows(tile, bundle, start, stop) {
  return chunkRows(chunkNoise(tile, bundle, start, stop));
}

async function parseTile(i, data, tensors, header) {
  const [x0, y0, width, height] = checkedRect(i, data);
  const name = data.tensor;
  if (typeof name !== "string") throw new UserError(`bundle: tile ${i} tensor ${reprCut(name ?? null, 40)} is missing`);
  const what = `bundle: tile ${i}`;
  let noise;
  if (header.layout === "compact") {
    const basis = tileTensor(tensors, `${name}_basis`, what), offset = tileTensor(tensors, `${name}_offset`, what);
    const scale = checkedFloat(data.scale ?? null, `${what} scale`, FLOAT32_TINY, FLOAT32_MAX);
    const escapes = tileTensor(tensors, `${name}_escapes`, what), escapeNoise = tileTensor(tensors, `${name}_escape_noise`, what);
    const packed = tileTensor(tensors, name, what, "uint8", 1);
    const coefficients = await unpackCoefficients(packed.values, [height, width, header.coefficients], header.dtype, what);
    noise = { kind: "compact", coefficients, shape: [height, width, header.coefficients], dtype: header.dtype,
      basis: { basis, offset, scale, escapes, escapeNoise } };
  } else {
    noise = { kind: "vector", tensor: tileTensor(tensors, name, what) };
  }
  const view = data.view ?? null;
  const camera = cameraFromDict(data.camera ?? null);
  const sampling = samplingFromDict(data.sampling ?? null);
  return { rect: [x0, y0, width, height], camera, sampling, noise,
    view: view === null ? null : checkedInt(view, `bundle: tile ${i} view`, 0, MAX_CAMERAS),
    network: data.network === undefined || data.network === null ? null : checkedText(data.network, `bundle: tile ${i} network`) };
}

function allFinite(values) {
  if (values instanceof Uint16Array) return values.every((half) => (half & 0x7c00) !== 0x7c00); // float16's bits
  for (let i = 0; i < values.length; i++) if (!Number.isFinite(values[i])) return false;
  return true;
}

function sameShape(a, b) { return a.length === b.length && a.every((v, i) => v === b[i]); }

function validateTile(i, tile, bundle) {
  const [x0, y0, w, h] = tile.rect;
  if (tile.network !== null && !NETWORKS.includes(tile.network)) {
    throw new UserError(`bundle: tile ${i} names network ${reprCut(tile.network, 40)} (expected one of ${repr(tuple(...NETWORKS))})`);
  }
  if (x0 + w > bundle.width || y0 + h > bundle.height) {
    throw new UserError(`bundle: tile ${i} rectangle ${repr(tuple(...tile.rect))} lies outside the ${bundle.width}x${bundle.height} image`);
  }
  if (tile.camera.width !== w || tile.camera.height !== h) {
    throw new UserError(`bundle: tile ${i} camera is ${tile.camera.width}x${tile.camera.height}, its rectangle ${w}x${h}`);
  }
  if (bundle.layout !== "sample" && tile.sampling.nSamples > MAX_RAY_LAYOUT_SAMPLES) {
    throw new UserError(`bundle: tile ${i} asks for ${tile.sampling.nSamples} samples per ray; the ${bundle.layout} layout allows at most ${MAX_RAY_LAYOUT_SAMPLES}`);
  }
  const perVector = bundle.layout === "compact" ? bundle.coefficients : bundle.noiseDims;
  const shape = bundle.layout === "sample" ? [h, w, tile.sampling.nSamples, perVector] : [h, w, perVector];
  if (tile.noise.kind === "compact") {
    const basis = tile.noise.basis, dims = bundle.noiseDims, k = bundle.coefficients;
    const escapes = basis.escapes;
    if (escapes.shape.length !== 1 || escapes.dtype !== "int32") {
      throw new UserError(`bundle: tile ${i} escapes are ${escapes.dtype} ${repr(tuple(...escapes.shape))}, expected int32 (e,)`);
    }
    const e = escapes.values;
    if (e.length && (e[0] < 0 || e[e.length - 1] >= w * h || e.some((v, j) => j > 0 && v <= e[j - 1]))) {
      throw new UserError(`bundle: tile ${i} escapes must be strictly increasing pixel indices inside the tile`);
    }
    for (const [what, value, want, dtype] of [["basis", basis.basis, [dims, k], "float32"], ["offset", basis.offset, [dims], "float32"],
      ["escape noise", basis.escapeNoise, [e.length, dims], "float16"]]) {
      if (!sameShape(value.shape, want) || value.dtype !== dtype) {
        throw new UserError(`bundle: tile ${i} ${what} is ${value.dtype} ${repr(tuple(...value.shape))}, expected ${dtype} ${repr(tuple(...want))}`);
      }
      if (!allFinite(value.values)) throw new UserError(`bundle: tile ${i} ${what} holds NaN or Inf`);
    }
  } else {
    const stored = tile.noise.tensor;
    if (!sameShape(stored.shape, shape) || stored.dtype !== bundle.dtype) {
      throw new UserError(`bundle: tile ${i} noise is ${stored.dtype} ${repr(tuple(...stored.shape))}, expected ${bundle.dtype} ${repr(tuple(...shape))}`);
    }
    if (!allFinite(stored.values)) throw new UserError(`bundle: tile ${i} noise holds NaN or Inf`);
  }
}

function validate(bundle) {
  if (bundle.tiles.length === 0) throw new UserError(`bundle: empty secret (${bundle.width}x${bundle.height}, 0 tiles)`);
  bundle.tiles.forEach((tile, i) => validateTile(i, tile, bundle));
  if (bundle.tiles.reduce((n, t) => n + t.rect[2] * t.rect[3], 0) !== bundle.width * bundle.height) {
    throw new UserError(`bundle: the tiles' areas do not add up to the ${bundle.width}x${bundle.height} secret`);
  }
  const covered = new Uint8Array(bundle.width * bundle.height);
  for (const [x0, y0, w, h] of bundle.tiles.map((t) => t.rect)) {
    for (let y = y0; y < y0 + h; y++) {
      for (let x = x0; x < x0 + w; x++) {
        if (covered[y * bundle.width + x]) throw new UserError("bundle: tile rectangles overlap");
      }
    }
    for (let y = y0; y < y0 + h; y++) covered.fill(1, y * bundle.width + x0, y * bundle.width + x0 + w);
  }
}

/** load_bundle: read and validate a bundle's bytes; anything malformed is one UserError. */
export async function loadBundle(data, source = "secret.bundle") {
  const file = readSafetensors(data, source);
  const raw = file.metadata && typeof file.metadata === "object" ? file.metadata[METADATA_KEY] : undefined;
  if (typeof raw !== "string") throw new UserError(`not a noisenerf bundle (no '${METADATA_KEY}' metadata): ${source}`);
  const meta = parseJson(raw, "bundle metadata", source);
  const tensors = new Map();
  for (const [name, info] of file.tensors) {
    if (!SAFETENSORS_DTYPES.includes(info.dtype)) {
      throw new UserError(`bundle tensor ${repr(name)} is ${info.dtype}; noise is stored as ${SAFETENSORS_DTYPES.join(" or ")}: ${source}`);
    }
    tensors.set(name, decodeTensor(info.dtype, info.shape, info.bytes));
  }
  if (!isObject(meta)) throw new UserError(`bundle metadata must be a JSON object: ${source}`);
  const version = checkedFormat(meta, source);
  const secret = meta.secret, noise = meta.noise;
  if (!isObject(secret) || !isObject(noise)) throw new UserError("bundle: metadata needs 'secret' and 'noise' objects");
  const [width, height] = checkedImageSize(secret.width ?? null, secret.height ?? null, "bundle: secret");
  const header = noiseHeader(noise, READABLE_FORMATS[version]);
  const tileData = checkedList(meta.tiles ?? null, "bundle: tiles", null, MAX_TILES);
  const areas = tileData.map((tile, i) => checkedRect(i, tile)).reduce((n, r) => n + r[2] * r[3], 0);
  if (header.layout === "compact" && areas !== width * height) {
    throw new UserError(`bundle: the tiles' areas do not add up to the ${width}x${height} secret`);
  }
  if (header.layout === "compact") {
    const streams = tileData.map((tile) => (typeof tile.tensor === "string" ? tensors.get(tile.tensor) : undefined));
    const packed = streams.reduce((n, stream) => n + (stream === undefined ? 0 : stream.values.byteLength), 0);
    checkedExpansion(packed, areas * header.coefficients * (header.dtype === "int16" ? 2 : 1), "bundle");
  }
  const fingerprint = checkedText(meta.model_fingerprint ?? null, "bundle: model_fingerprint");
  const sha256 = checkedText(secret.sha256 ?? null, "bundle: sha256");
  const tiles = [];
  for (let i = 0; i < tileData.length; i++) tiles.push(await parseTile(i, tileData[i], tensors, header));
  const bundle = { modelFingerprint: fingerprint, width, height, secretSha256: sha256, layout: header.layout,
    noiseDims: header.dims, dtype: header.dtype, tiles, coefficients: header.coefficients,
    payload: meta.payload === undefined || meta.payload === null ? null : checkedPayload(meta.payload) };
  validate(bundle);
  for (const tile of bundle.tiles) {
    if (tile.noise.kind === "vector") tile.noise.values = tile.noise.tensor.values;
    else tile.noise.basis = { basis: tile.noise.basis.basis.values, offset: tile.noise.basis.offset.values,
      scale: tile.noise.basis.scale, escapes: tile.noise.basis.escapes.values, escapeNoise: widened(tile.noise.basis.escapeNoise.values) };
  }
  return bundle;
}
