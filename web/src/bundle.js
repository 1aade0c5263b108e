// Mirrors runtime/bundle.py: the safetensors bundle (header JSON + tensors, dtypes F16/F32/U8/I32 only), its
// metadata checked with the same messages and caps before anything is allocated (formats 1–3), each tile's noise
// read, checked and cut into chunks by its layout (src/layouts.js).

import { UserError, repr, reprCut, tuple, PyFloat } from "./errors.js";
import { isJsonObject as isObject, parseJson } from "./json.js";
import { LAYOUTS, chunkRows, layoutNamed } from "./layouts.js";
import {
  MAX_CAMERAS, MAX_IMAGE_SIDE, MAX_NOISE_DIMS, MAX_TILES, checkedImageSize, checkedInt, checkedList,
} from "./limits.js";
import { cameraFromDict } from "./camera.js";
import { samplingFromDict } from "./sampling.js";
import { checkedPayload } from "./payload.js";

export const NOISENERF_VERSION = "0.1.0"; // noisenerf.__version__ of the Python runtime this port mirrors
export const METADATA_KEY = "noisenerf_bundle";
// format -> the layouts it may hold (format 3: compact tiles add branch escapes, src/layouts.js)
const READABLE_FORMATS = { 1: ["ray", "sample"], 2: ["ray", "sample", "compact"], 3: ["ray", "sample", "compact"] };
const NEWEST_FORMAT = Math.max(...Object.keys(READABLE_FORMATS).map(Number));
const SAFETENSORS_DTYPES = ["F16", "F32", "U8", "I32"];
const NUMPY_NAMES = { F16: "float16", F32: "float32", U8: "uint8", I32: "int32" };
const ITEM_SIZE = { F16: 2, F32: 4, U8: 1, I32: 4, I8: 1, I16: 2, BOOL: 1, F64: 8, I64: 8, U16: 2, U32: 4, U64: 8, BF16: 2 };
export const NETWORKS = ["coarse", "fine"];

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
    throw new UserError(`${source} is bundle format ${reprCut(version === undefined ? null : version, 20)}; noisenerf ${NOISENERF_VERSION} reads formats 1 to ${NEWEST_FORMAT}` +
      (typeof version === "number" && Number.isInteger(version) && version > NEWEST_FORMAT ? "; a newer noisenerf is needed" : ""));
  }
  return key;
}

function validateNoiseHeader(name, dtype, dims, coefficients, layouts = Object.keys(LAYOUTS)) {
  const layout = layoutNamed(name, layouts);
  if (!layout.dtypes.includes(dtype)) {
    throw new UserError(`bundle: unknown noise dtype ${reprCut(dtype, 40)} for the ${layout.name} layout (expected one of ${repr(tuple(...layout.dtypes))})`);
  }
}

function noiseHeader(noise, layouts) {
  const layout = layoutNamed(checkedText(noise.layout, "bundle: noise layout"), layouts);
  const dims = checkedInt(noise.dims, "bundle: noise dims", 1, MAX_NOISE_DIMS);
  const dtype = checkedText(noise.dtype, "bundle: noise dtype");
  const coefficients = layout.readHeader(noise, dims);
  validateNoiseHeader(layout.name, dtype, dims, coefficients, layouts);
  return { layout: layout.name, dims, dtype, coefficients };
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
  if (typeof name !== "string") throw new UserError(`bundle: tile ${i} tensor ${reprCut(name ?? null, 40)} is missing`);
  const what = `bundle: tile ${i}`;
  const noise = await LAYOUTS[header.layout].readTile(name, data, (key, dtype = null, ndim = null) => tileTensor(tensors, key, what, dtype, ndim),
    [height, width, header.coefficients], header.dtype, what, header.format);
  const view = data.view ?? null;
  const camera = cameraFromDict(data.camera ?? null);
  const sampling = samplingFromDict(data.sampling ?? null);
  return { rect: [x0, y0, width, height], camera, sampling, noise,
    view: view === null ? null : checkedInt(view, `bundle: tile ${i} view`, 0, MAX_CAMERAS),
    network: data.network === undefined || data.network === null ? null : checkedText(data.network, `bundle: tile ${i} network`) };
}

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
  const layout = LAYOUTS[bundle.layout];
  if (tile.sampling.nSamples > layout.maxSamples) {
    throw new UserError(`bundle: tile ${i} asks for ${tile.sampling.nSamples} samples per ray; the ${bundle.layout} layout allows at most ${layout.maxSamples}`);
  }
  const perVector = bundle.coefficients === null ? bundle.noiseDims : bundle.coefficients;
  const shape = layout.storedShape(h, w, tile.sampling.nSamples, perVector);
  layout.checkNoise(`bundle: tile ${i}`, tile.noise, w * h, bundle.noiseDims, bundle.coefficients, shape, bundle.dtype);
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
  const header = { ...noiseHeader(noise, READABLE_FORMATS[version]), format: version };
  const tileData = checkedList(meta.tiles ?? null, "bundle: tiles", null, MAX_TILES);
  const areas = tileData.map((tile, i) => checkedRect(i, tile)).reduce((n, r) => n + r[2] * r[3], 0);
  const layout = LAYOUTS[header.layout];
  layout.checkStreams(tileData.map((tile) => (typeof tile.tensor === "string" ? tensors.get(tile.tensor) : undefined)),
    [width, height], areas, header.coefficients, header.dtype);
  const fingerprint = checkedText(meta.model_fingerprint ?? null, "bundle: model_fingerprint");
  const sha256 = checkedText(secret.sha256 ?? null, "bundle: sha256");
  const tiles = [];
  for (let i = 0; i < tileData.length; i++) tiles.push(await parseTile(i, tileData[i], tensors, header));
  const bundle = { modelFingerprint: fingerprint, width, height, secretSha256: sha256, layout: header.layout,
    noiseDims: header.dims, dtype: header.dtype, tiles, coefficients: header.coefficients,
    payload: meta.payload === undefined || meta.payload === null ? null : checkedPayload(meta.payload) };
  validate(bundle);
  for (const tile of bundle.tiles) layout.loaded(tile.noise);
  return bundle;
}
