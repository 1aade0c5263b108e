// Mirrors runtime/bundle.py: the safetensors bundle (header JSON + tensors, dtypes F16/F32/U8/I32 only), its
// metadata checked with the same messages and caps before anything is allocated (formats 1–5), each tile's noise
// read, checked and cut into chunks by its layout (src/layouts.js).
//
// The order of checks is runtime/bundle.py's (its docstring numbers them), so that both refuse any input with the
// same code and params:
//   1. the file (the page holds its bytes: nothing to check);
//   2. framing, from the first 8 bytes and the size alone: a header length 0 < n <= min(MAX_HEADER_BYTES, size - 8)
//      (bundle.not_safetensors): a file of zeros or random bytes is refused here, whatever its size;
//   3. the header: UTF-8 JSON as parse_json reads it, an object, its "__metadata__" (where present) an object
//      (bundle.not_safetensors);
//   4. "__metadata__"["noisenerf_bundle"] a string (bundle.not_noisenerf);
//   5. that string parsed as JSON (json.invalid, json.too_deep);
//   6. every tensor's dtype, in the header's order, one of F16 F32 U8 I32 (bundle.tensor_dtype);
//   7. the safetensors structure, as the safetensors library checks it (bundle.not_safetensors): JSON it reads (no
//      NaN, Infinity or out-of-range numbers, no lone surrogates, no byte order mark), "__metadata__"'s values
//      strings, each tensor's shape and data_offsets whole numbers, the offsets tiling the data exactly, each the
//      size its shape states;
//   7½. where the metadata states a mask (readBundleFile): the mask object (mask.malformed); then (bundleOf) the
//      model's mask secret given (bundle.masked), the tensors unmasked (src/masking.js);
//   8. the metadata: an object, format (format 5 masked, earlier ones not: bundle.mask_format), secret and noise, the secret's size, the noise header, tiles a list, every
//      tile's rect, the layout's streams against what they state, fingerprint, digest; then tile by tile: rect,
//      tensor name, the layout's tensors (compact: [branch escapes,] basis, offset, scale, escapes, escape noise, band
//      rows, the stream, its decoding: the stream must end exactly where the tensor does), camera, sampling, view,
//      network; then the payload;
//   9. the whole (validate): empty, tile by tile (network, inside the secret, camera, samples, the layout's noise
//      checks), the areas, overlaps.

import { UserError, PyFloat, cut, show } from "./errors.js";
import { isJsonObject as isObject, parseJson } from "./json.js";
import { LAYOUTS, chunkRows, layoutNamed } from "./layouts.js";
import {
  MAX_CAMERAS, MAX_HEADER_BYTES, MAX_IMAGE_SIDE, MAX_NOISE_DIMS, MAX_TILES, checkedImageSize, checkedInt, checkedList,
  num,
} from "./limits.js";
import { cameraFromDict } from "./camera.js";
import { samplingFromDict } from "./sampling.js";
import { checkedMask, maskKey, xorMasked } from "./masking.js";
import { checkedMarker } from "./payload.js";
import { splitSafetensors } from "./sealing.js";

export const NOISENERF_VERSION = "0.1.0"; // noisenerf.__version__ of the Python runtime this port mirrors
export const METADATA_KEY = "noisenerf_bundle";
// format -> the layouts it may hold (format 3: compact tiles add branch escapes, src/layouts.js)
// and format 5 is format 4 masked with the model, src/masking.js)
const READABLE_FORMATS = {
  1: ["ray", "sample"], 2: ["ray", "sample", "compact"], 3: ["ray", "sample", "compact"], 4: ["ray", "sample", "compact"],
  5: ["ray", "sample", "compact"],
};
const MASKED_FROM = 5;
const NEWEST_FORMAT = Math.max(...Object.keys(READABLE_FORMATS).map(Number));
const SAFETENSORS_DTYPES = ["F16", "F32", "U8", "I32"];
const NUMPY_NAMES = { F16: "float16", F32: "float32", U8: "uint8", I32: "int32" };
const ITEM_SIZE = { F16: 2n, F32: 4n, U8: 1n, I32: 4n };
const USIZE_END = 2n ** 64n; // safetensors reads shapes and offsets as Rust's usize
export const NETWORKS = ["coarse", "fine"];

/** A tensor as read: {dtype (numpy name), shape, values (typed array; float16 kept as its bits, a Uint16Array, and
 * widened a chunk at a time as runtime/ does: a float16 view's noise is not held twice as large)}. */
function decodeTensor(dtype, shape, bytes) {
  const copy = bytes.slice();
  const count = copy.length / Number(ITEM_SIZE[dtype]);
  const Kind = { F32: Float32Array, I32: Int32Array, U8: Uint8Array, F16: Uint16Array }[dtype];
  return { dtype: NUMPY_NAMES[dtype], shape, values: new Kind(copy.buffer, 0, count) };
}

const notSafetensors = (source, why = null) => new UserError(
  `not a readable safetensors bundle: ${source}${why === null ? "" : ` (${why})`}`, { code: "bundle.not_safetensors" });

/** Checks 2 and 3: the header length from the first 8 bytes and the size alone (checked_framing), then the header,
 * parsed as Python's parse_json reads it (src/sealing.js splitSafetensors, as Python's split_safetensors). -> the
 * header object. */
function safetensorsHeader(data, source) {
  const size = data.length >= 8 ? new DataView(data.buffer, data.byteOffset, 8).getBigUint64(0, true) : 0n;
  if (!(size > 0n && size <= BigInt(Math.min(data.length - 8, MAX_HEADER_BYTES)))) throw notSafetensors(source);
  return splitSafetensors(data, source).header;
}

const LONE_SURROGATE = /\p{Cs}/u; // a surrogate code unit not in a pair

/** Whether every number in a parsed JSON value is one the safetensors library's JSON reads (a finite float) and every
 * string and key is valid Unicode (no lone surrogate from a \u escape). */
function readableJson(value) {
  const stack = [value];
  while (stack.length) {
    const item = stack.pop();
    if (item instanceof PyFloat) {
      if (!Number.isFinite(item.value)) return false;
    } else if (typeof item === "string") {
      if (LONE_SURROGATE.test(item)) return false;
    } else if (Array.isArray(item)) stack.push(...item);
    else if (item !== null && typeof item === "object") {
      for (const [key, child] of Object.entries(item)) {
        if (LONE_SURROGATE.test(key)) return false;
        stack.push(child);
      }
    }
  }
  return true;
}

/** A parsed JSON value as Rust's usize (a whole number in [0, 2^64)) -> BigInt, or null. */
const usize = (value) => ((typeof value === "number" && Number.isInteger(value)) || typeof value === "bigint") &&
  BigInt(value) >= 0n && BigInt(value) < USIZE_END ? BigInt(value) : null;

/** Check 7: the tensors as the safetensors library reads them (every dtype is one of SAFETENSORS_DTYPES by now)
 * -> Map name -> {dtype, shape, bytes}. */
function safetensorsTensors(data, header, source) {
  const size = Number(new DataView(data.buffer, data.byteOffset, 8).getBigUint64(0, true));
  const metadata = Object.hasOwn(header, "__metadata__") ? header.__metadata__ : {};
  if ((data[8] === 0xef && data[9] === 0xbb && data[10] === 0xbf) || !readableJson(header)) {
    throw notSafetensors(source, "a header the safetensors library cannot read");
  }
  if (!Object.values(metadata).every((value) => typeof value === "string")) {
    throw notSafetensors(source, "a metadata value is not a string");
  }
  const entries = [];
  for (const [name, info] of Object.entries(header)) {
    if (name === "__metadata__") continue;
    const shape = Array.isArray(info.shape) ? info.shape.map(usize) : null;
    const offsets = Array.isArray(info.data_offsets) && info.data_offsets.length === 2 ? info.data_offsets.map(usize) : null;
    if (shape === null || shape.includes(null) || offsets === null || offsets.includes(null)) {
      throw notSafetensors(source, `tensor ${show(name)} is not described by dtype, shape and data_offsets`);
    }
    entries.push({ name, dtype: info.dtype, shape, begin: offsets[0], end: offsets[1] });
  }
  entries.sort((a, b) => (a.begin !== b.begin ? (a.begin < b.begin ? -1 : 1) : a.end < b.end ? -1 : a.end > b.end ? 1 : 0));
  const body = data.subarray(8 + size);
  let end = 0n;
  const tensors = new Map();
  for (const { name, dtype, shape, begin, end: stop } of entries) {
    const bytes = shape.reduce((n, d) => n * d, ITEM_SIZE[dtype]);
    if (begin !== end || stop < begin || stop - begin !== bytes) throw notSafetensors(source, `tensor ${show(name)} has wrong data offsets`);
    end = stop;
    tensors.set(name, { dtype, shape: shape.map(Number), bytes: body.subarray(Number(begin), Number(stop)) });
  }
  if (end !== BigInt(body.length)) throw notSafetensors(source, "the tensors do not fill the data");
  return tensors;
}

/** checked_text: a short JSON string (fingerprints, digests, names; at most 256 code points, as Python counts);
 * `refusal`: { code, ...params }. */
function checkedText(value, what, { code, ...params }) {
  if (typeof value !== "string" || [...value].length > 256) {
    throw new UserError(`${what} must be a string of at most 256 characters`, { code, most: 256, ...params });
  }
  return value;
}

function checkedFormat(meta, source) {
  const version = meta.format_version;
  const key = typeof version === "number" ? version : version instanceof PyFloat ? version.value : null;
  if (typeof version === "boolean" || !(key in READABLE_FORMATS)) {
    const number = num(version);
    throw new UserError(`${source} is bundle format ${show(version ?? null, 20)}; noisenerf ${NOISENERF_VERSION} reads formats 1 to ${NEWEST_FORMAT}` +
      ((typeof version === "number" || typeof version === "bigint") && number > NEWEST_FORMAT ? "; a newer noisenerf is needed" : ""),
    { code: "bundle.format", ...(Number.isFinite(number) ? { format: version } : {}), oldest: 1, newest: NEWEST_FORMAT });
  }
  return key;
}

function validateNoiseHeader(name, dtype, dims, coefficients, layouts = Object.keys(LAYOUTS)) {
  const layout = layoutNamed(name, layouts);
  if (!layout.dtypes.includes(dtype)) {
    throw new UserError(`bundle: unknown noise dtype ${show(dtype, 40)} for the ${layout.name} layout (expected one of ${layout.dtypes.join(", ")})`,
      { code: "bundle.noise_dtype", dtype: cut(dtype), layout: layout.name, expected: layout.dtypes });
  }
}

function noiseHeader(noise, layouts, version) {
  const layout = layoutNamed(checkedText(noise.layout, "bundle: noise layout", { code: "bundle.noise_layout" }), layouts);
  const dims = checkedInt(noise.dims, "bundle: noise dims", 1, MAX_NOISE_DIMS, { code: "bundle.noise_dims" });
  const dtype = checkedText(noise.dtype, "bundle: noise dtype", { code: "bundle.noise_dtype" });
  const coefficients = layout.readHeader(noise, dims, version);
  validateNoiseHeader(layout.name, dtype, dims, coefficients, layouts);
  return { layout: layout.name, dims, dtype, coefficients };
}

function checkedRect(i, data) {
  if (!isObject(data)) throw new UserError(`bundle: tile ${i} must be a JSON object`, { code: "bundle.tile_not_object", tile: i });
  const rect = checkedList(data.rect, `bundle: tile ${i} rect`, 4, undefined, { code: "bundle.tile_rect", tile: i });
  const x0 = checkedInt(rect[0], `bundle: tile ${i} rect origin`, 0, MAX_IMAGE_SIDE, { code: "bundle.tile_rect", tile: i });
  const y0 = checkedInt(rect[1], `bundle: tile ${i} rect origin`, 0, MAX_IMAGE_SIDE, { code: "bundle.tile_rect", tile: i });
  return [x0, y0, ...checkedImageSize(rect[2], rect[3], `bundle: tile ${i} rect`, { code: "bundle.tile_rect", tile: i })];
}

/** tile_tensor: a named tensor of tile number `tile` that must exist (with this dtype and rank, when given). */
function tileTensor(tensors, name, tile, dtype = null, ndim = null) {
  if (!tensors.has(name)) {
    throw new UserError(`bundle: tile ${tile} tensor ${show(name)} is missing`, { code: "bundle.tensor_missing", tile, tensor: cut(name) });
  }
  const value = tensors.get(name);
  if ((dtype !== null && value.dtype !== dtype) || (ndim !== null && value.shape.length !== ndim)) {
    throw new UserError(`bundle: tile ${tile} tensor ${show(name)} is ${value.dtype} [${value.shape}]`,
      { code: "bundle.tensor_shape", tile, tensor: cut(name), dtype: value.dtype, shape: value.shape });
  }
  return value;
}

/** A tile's noise for its pixels start..stop, on its own (its layout's `chunk`: a record chunkRows expands). */
export function chunkNoise(tile, bundle, start, stop) {
  return LAYOUTS[bundle.layout].chunk(tile, bundle, start, stop);
}

export { chunkRows };

/** The float32 noise of a tile's pixels start..stop: {values, perSample (1 or n_samples), dims}. */
export function tileRows(tile, bundle, start, stop) {
  return chunkRows(chunkNoise(tile, bundle, start, stop));
}

async function parseTile(i, data, tensors, header) {
  const [x0, y0, width, height] = checkedRect(i, data);
  const name = data.tensor;
  if (typeof name !== "string") throw new UserError(`bundle: tile ${i} names no tensor`, { code: "bundle.tile_no_tensor", tile: i });
  const noise = await LAYOUTS[header.layout].readTile(name, data, (key, dtype = null, ndim = null) => tileTensor(tensors, key, i, dtype, ndim),
    [height, width, header.coefficients], header.dtype, i, header.format);
  const view = data.view ?? null;
  const camera = cameraFromDict(data.camera ?? null);
  const sampling = samplingFromDict(data.sampling ?? null);
  return { rect: [x0, y0, width, height], camera, sampling, noise,
    view: view === null ? null : checkedInt(view, `bundle: tile ${i} view`, 0, MAX_CAMERAS, { code: "bundle.tile_view", tile: i }),
    network: data.network === undefined || data.network === null ? null
      : checkedText(data.network, `bundle: tile ${i} network`, { code: "bundle.tile_network", tile: i }) };
}

function validateTile(i, tile, bundle) {
  const [x0, y0, w, h] = tile.rect;
  if (tile.network !== null && !NETWORKS.includes(tile.network)) {
    throw new UserError(`bundle: tile ${i} names network ${show(tile.network, 40)} (expected one of ${NETWORKS.join(", ")})`,
      { code: "bundle.tile_network", tile: i, network: cut(tile.network), expected: NETWORKS });
  }
  if (x0 + w > bundle.width || y0 + h > bundle.height) {
    throw new UserError(`bundle: tile ${i} rectangle [${tile.rect}] lies outside the ${bundle.width}x${bundle.height} image`,
      { code: "bundle.tile_outside", tile: i, rect: tile.rect, width: bundle.width, height: bundle.height });
  }
  if (tile.camera.width !== w || tile.camera.height !== h) {
    throw new UserError(`bundle: tile ${i} camera is ${tile.camera.width}x${tile.camera.height}, its rectangle ${w}x${h}`,
      { code: "bundle.tile_camera", tile: i, camera: [tile.camera.width, tile.camera.height], size: [w, h] });
  }
  const layout = LAYOUTS[bundle.layout];
  if (tile.sampling.nSamples > layout.maxSamples) {
    throw new UserError(`bundle: tile ${i} asks for ${tile.sampling.nSamples} samples per ray; the ${bundle.layout} layout allows at most ${layout.maxSamples}`,
      { code: "bundle.tile_samples", tile: i, samples: tile.sampling.nSamples, layout: bundle.layout, most: layout.maxSamples });
  }
  const perVector = bundle.coefficients === null ? bundle.noiseDims : bundle.coefficients;
  const shape = layout.storedShape(h, w, tile.sampling.nSamples, perVector);
  layout.checkNoise(i, tile.noise, w * h, bundle.noiseDims, bundle.coefficients, shape, bundle.dtype);
}

function validate(bundle) {
  if (bundle.tiles.length === 0) {
    throw new UserError(`bundle: empty secret (${bundle.width}x${bundle.height}, 0 tiles)`,
      { code: "bundle.empty", width: bundle.width, height: bundle.height, tiles: 0 });
  }
  bundle.tiles.forEach((tile, i) => validateTile(i, tile, bundle));
  if (bundle.tiles.reduce((n, t) => n + t.rect[2] * t.rect[3], 0) !== bundle.width * bundle.height) {
    throw new UserError(`bundle: the tiles' areas do not add up to the ${bundle.width}x${bundle.height} secret`,
      { code: "bundle.tile_areas", width: bundle.width, height: bundle.height });
  }
  const covered = new Uint8Array(bundle.width * bundle.height);
  for (const [x0, y0, w, h] of bundle.tiles.map((t) => t.rect)) {
    for (let y = y0; y < y0 + h; y++) {
      for (let x = x0; x < x0 + w; x++) {
        if (covered[y * bundle.width + x]) throw new UserError("bundle: tile rectangles overlap", { code: "bundle.tiles_overlap" });
      }
    }
    for (let y = y0; y < y0 + h; y++) covered.fill(1, y * bundle.width + x0, y * bundle.width + x0 + w);
  }
}

/** read_bundle_file: checks 1 to 7½ on a bundle's bytes -> {source, meta, tensors (name -> {dtype, shape, bytes} as
 * stored), salt (a masked bundle's, else null)}: what a reveal knows of a masked bundle before its model is open. */
export function readBundleFile(data, source = "secret.bundle") {
  const file = safetensorsHeader(data, source);
  const metadata = Object.hasOwn(file, "__metadata__") ? file.__metadata__ : {};
  const raw = Object.hasOwn(metadata, METADATA_KEY) ? metadata[METADATA_KEY] : undefined;
  if (typeof raw !== "string") {
    throw new UserError(`not a noisenerf bundle (no '${METADATA_KEY}' metadata): ${source}`, { code: "bundle.not_noisenerf" });
  }
  const meta = parseJson(raw, "bundle metadata", source);
  for (const [name, info] of Object.entries(file)) {
    const dtype = isObject(info) && Object.hasOwn(info, "dtype") ? info.dtype : null;
    if (name !== "__metadata__" && !SAFETENSORS_DTYPES.includes(dtype)) {
      throw new UserError(`bundle tensor ${show(name)} is ${show(dtype, 20)}; noise is stored as ${SAFETENSORS_DTYPES.join(" or ")}: ${source}`,
        { code: "bundle.tensor_dtype", tensor: cut(name), dtype: typeof dtype === "string" ? cut(dtype) : null });
    }
  }
  const tensors = safetensorsTensors(data, file, source);
  const masked = isObject(meta) && meta.mask !== undefined && meta.mask !== null;
  return { source, meta, tensors, salt: masked ? checkedMask(meta.mask) : null };
}

/** BundleFile.model_fingerprint: the fingerprint a bundle's file names, checked. */
export const fileFingerprint = (file) => checkedText((isObject(file.meta) ? file.meta.model_fingerprint : null) ?? null,
  "bundle: model_fingerprint", { code: "bundle.model_fingerprint" });

/** BundleFile.payload_marker: the payload marker a bundle's file states, checked; null for an image. */
export const filePayloadMarker = (file) => (isObject(file.meta) ? payloadMarkerOf(file.meta) : null);

const payloadMarkerOf = (meta) => (meta.payload === undefined || meta.payload === null ? null : checkedMarker(meta.payload));

/** BundleFile.bundle: checks 8 and 9, on the tensors unmasked with the model's mask secret where the bundle is masked. */
export async function bundleOf(file, maskSecret = null) {
  const { source, meta, salt } = file;
  if (salt !== null && maskSecret === null) {
    throw new UserError(`${source}: this bundle is masked with its model; it reads only with the model`, { code: "bundle.masked" });
  }
  const key = salt === null ? null : maskKey(maskSecret, salt);
  const tensors = new Map();
  for (const [name, info] of file.tensors) {
    tensors.set(name, decodeTensor(info.dtype, info.shape, key === null ? info.bytes : xorMasked(info.bytes, key, name)));
  }
  if (!isObject(meta)) throw new UserError(`bundle metadata must be a JSON object: ${source}`, { code: "bundle.metadata_not_object" });
  const version = checkedFormat(meta, source);
  if ((version >= MASKED_FROM) !== (salt !== null)) {
    throw new UserError(`bundle: format ${version} bundles are ${version >= MASKED_FROM ? "" : "not "}masked`,
      { code: "bundle.mask_format", format: version });
  }
  const secret = meta.secret, noise = meta.noise;
  if (!isObject(secret) || !isObject(noise)) {
    throw new UserError("bundle: metadata needs 'secret' and 'noise' objects", { code: "bundle.no_secret_or_noise" });
  }
  const [width, height] = checkedImageSize(secret.width ?? null, secret.height ?? null, "bundle: secret", { code: "bundle.secret_size" });
  const header = { ...noiseHeader(noise, READABLE_FORMATS[version], version), format: version };
  const tileData = checkedList(meta.tiles ?? null, "bundle: tiles", null, MAX_TILES, { code: "bundle.tiles" });
  const areas = tileData.map((tile, i) => checkedRect(i, tile)).reduce((n, r) => n + r[2] * r[3], 0);
  const layout = LAYOUTS[header.layout];
  layout.checkStreams(tileData.map((tile) => (typeof tile.tensor === "string" ? tensors.get(tile.tensor) : undefined)),
    [width, height], areas, header.coefficients, header.dtype);
  const fingerprint = checkedText(meta.model_fingerprint ?? null, "bundle: model_fingerprint", { code: "bundle.model_fingerprint" });
  const sha256 = checkedText(secret.sha256 ?? null, "bundle: sha256", { code: "bundle.secret_sha256" });
  const tiles = [];
  for (let i = 0; i < tileData.length; i++) tiles.push(await parseTile(i, tileData[i], tensors, header));
  const bundle = { modelFingerprint: fingerprint, width, height, secretSha256: sha256, layout: header.layout,
    noiseDims: header.dims, dtype: header.dtype, tiles, coefficients: header.coefficients,
    payloadMarker: payloadMarkerOf(meta) };
  validate(bundle);
  for (const tile of bundle.tiles) layout.loaded(tile.noise);
  return bundle;
}

/** load_bundle: read and validate a bundle's bytes (a masked one with its model's mask secret); anything malformed
 * is one UserError. */
export async function loadBundle(data, source = "secret.bundle", maskSecret = null) {
  return bundleOf(readBundleFile(data, source), maskSecret);
}
