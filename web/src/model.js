// Mirrors runtime/model.py (ModelMetadata with its checks and caps, load_model's order, check_bundle) and
// runtime/fingerprint.py (SHA-256 over the sorted weights `name|<f4|[shape]|` + little-endian bytes, then
// json.dumps(architecture, sort_keys=True)).

import { sha256 } from "@noble/hashes/sha2.js";
import { bytesToHex } from "@noble/hashes/utils.js";
import { UserError, repr, PyFloat } from "./errors.js";
import { isJsonObject as isObject, parseJson, dumpsSorted } from "./json.js";
import { parseModel } from "./onnx.js";
import { checkGraph } from "./graph.js";
import { fieldGraph } from "./fields/index.js";
import { MAX_CAMERAS, MAX_GRID_RESOLUTION, MAX_NOISE_DIMS, checkedFloat, checkedInt, checkedList } from "./limits.js";
import { cameraFromDict, ndcFromDict } from "./camera.js";
import { samplingFromDict } from "./sampling.js";

export const MODEL_FORMAT_VERSION = 2;
const METADATA_KEY = "noisenerf", VERSION_KEY = "noisenerf_format_version";
class Malformed extends Error {}

function renderConfigFromDict(data) {
  if (!isObject(data)) throw new UserError("malformed render config: expected an object");
  for (const key of ["background", "sampling", "pixel_center"]) {
    if (!Object.hasOwn(data, key)) throw new UserError(`malformed render config: missing '${key}'`);
  }
  const background = checkedList(data.background, "render background", 3);
  const sampling = samplingFromDict(data.sampling);
  return {
    sampling,
    background: background.map((v) => checkedFloat(v, "render background", 0.0, 1.0)),
    ndc: data.ndc ? ndcFromDict(data.ndc) : null,
    pixelCenter: checkedFloat(data.pixel_center, "render pixel_center", 0.0, 1.0),
    earlyStop: checkedFloat(data.early_stop ?? new PyFloat(1e-4), "render early_stop", 0.0, 1.0),
  };
}

function hierarchyFromDict(data) {
  if (!isObject(data)) throw new Malformed("TypeError('hierarchy')");
  const { n_coarse: nCoarse, n_importance: nImportance } = data;
  const counts = [nCoarse, nImportance];
  if (!counts.every((n) => typeof n === "number" && Number.isInteger(n)) || !(nCoarse >= 3 && nCoarse <= 1024 && nImportance >= 1 && nImportance <= 1024)) {
    throw new UserError(`hierarchical sampling needs whole numbers 3 <= n_coarse <= 1024 and 1 <= n_importance <= 1024, got (${counts.map(repr).join(", ")})`);
  }
  return { nCoarse, nImportance };
}

function checkGrid(data) {
  if (!isObject(data) || typeof data.occupancy !== "string") throw new UserError("grid must be an object with aabb, resolution and occupancy");
  const resolution = checkedInt(data.resolution ?? null, "grid resolution", 1, MAX_GRID_RESOLUTION);
  const aabb = checkedList(data.aabb ?? null, "grid aabb", 6).map((v) => checkedFloat(v, "grid aabb", -1e9, 1e9));
  if (![0, 1, 2].every((a) => aabb[a] < aabb[a + 3])) throw new UserError(`grid aabb must have min < max on every axis, got ${repr(aabb.map((v) => new PyFloat(v)))}`);
  if (!/^[A-Za-z0-9+/]*={0,2}$/.test(data.occupancy) || data.occupancy.length % 4) throw new Malformed("Error('Incorrect padding')");
  const bytes = (data.occupancy.length / 4) * 3 - (data.occupancy.match(/=*$/)[0].length);
  const cells = resolution ** 3;
  if (bytes !== Math.floor((cells + 7) / 8)) throw new Malformed(`ValueError('occupancy holds ${bytes} bytes, a ${resolution}^3 grid needs ${Math.floor((cells + 7) / 8)}')`);
  return { aabb, resolution };
}

/** ModelMetadata.from_metadata_props. */
export function metadataFromProps(props, source) {
  if (!props.has(METADATA_KEY) || !props.has(VERSION_KEY)) throw new UserError(`${source} is not a noisenerf model (no '${METADATA_KEY}' metadata)`);
  if (props.get(VERSION_KEY) !== String(MODEL_FORMAT_VERSION)) {
    throw new UserError(`${source} has model format version ${repr(props.get(VERSION_KEY))}; this noisenerf reads ` +
      `version ${MODEL_FORMAT_VERSION} (export the scene again with \`noisenerf export\`)`);
  }
  const data = parseJson(props.get(METADATA_KEY), `${source}: noisenerf metadata`);
  try {
    if (!isObject(data) || data.format_version !== MODEL_FORMAT_VERSION) throw new Malformed(`ValueError('format_version disagrees with ${VERSION_KEY}')`);
    for (const key of ["architecture", "hierarchy", "cameras", "fingerprint", "noise_dims", "render", "grid"]) {
      if (!Object.hasOwn(data, key)) throw new Malformed(`KeyError('${key}')`);
    }
    if (!isObject(data.architecture) || !isObject(data.architecture.coarse) || !Object.hasOwn(data.architecture, "fine")) {
      throw new Malformed("KeyError('architecture')");
    }
    const architecture = { coarse: { ...data.architecture.coarse }, fine: data.architecture.fine };
    const hierarchy = data.hierarchy !== null ? hierarchyFromDict(data.hierarchy) : null;
    if ((architecture.fine === null) !== (hierarchy === null)) throw new Malformed("ValueError('a fine network and hierarchical sampling go together')");
    const cameras = checkedList(data.cameras, "cameras", null, MAX_CAMERAS);
    const fingerprint = typeof data.fingerprint === "string" ? data.fingerprint : repr(data.fingerprint);
    const noiseDims = checkedInt(data.noise_dims, "noise_dims", 1, MAX_NOISE_DIMS);
    const renderConfig = renderConfigFromDict(data.render);
    const parsedCameras = cameras.map(cameraFromDict);
    checkGrid(data.grid);
    return { fingerprint, architecture, noiseDims, renderConfig, hierarchy, cameras: parsedCameras };
  } catch (error) {
    if (error instanceof Malformed) throw new UserError(`${source}: malformed noisenerf metadata (${error.message})`);
    if (error instanceof UserError) throw new UserError(`${source}: ${error.message}`);
    throw error;
  }
}

/** weights_fingerprint: weights (name -> {shape, values Float32Array}) and the architecture. */
export function weightsFingerprint(weights, architecture) {
  const digest = sha256.create();
  const encoder = new TextEncoder();
  for (const name of [...weights.keys()].sort()) {
    const { shape, values } = weights.get(name);
    digest.update(encoder.encode(`${name}|<f4|[${shape.join(", ")}]|`));
    digest.update(new Uint8Array(values.buffer, values.byteOffset, values.byteLength)); // little-endian hosts only
  }
  digest.update(encoder.encode(dumpsSorted(architecture)));
  return bytesToHex(digest.digest());
}

export const shortFingerprint = (fingerprint) => `${fingerprint.slice(0, 12)}…`;

/** load_model without the session: parse, metadata, graph == field_graph(architecture), weights -> fingerprint. */
export function checkModel(data, source = "model.onnx") {
  const file = parseModel(data, source);
  const metadata = metadataFromProps(file.metadataProps, source);
  let expected;
  try {
    expected = fieldGraph(metadata.architecture, metadata.noiseDims);
  } catch (error) {
    if (error instanceof UserError) throw new UserError(`${source}: ${error.message}`);
    throw error;
  }
  const weights = checkGraph(file, expected, source);
  if (weightsFingerprint(weights, metadata.architecture) !== metadata.fingerprint) {
    throw new UserError(`${source}: its weights do not match its fingerprint ${shortFingerprint(metadata.fingerprint)} ` +
      "(the model was changed after export); export the scene again");
  }
  return { file, metadata, networks: metadata.architecture.fine === null ? ["coarse"] : ["coarse", "fine"] };
}

/** check_bundle: refuse a bundle hidden in another model, or with noise the field cannot take. */
export function checkBundle(model, bundle) {
  if (bundle.modelFingerprint !== model.metadata.fingerprint) {
    throw new UserError(`bundle was made for model ${shortFingerprint(bundle.modelFingerprint)}, this model is ${shortFingerprint(model.metadata.fingerprint)}`);
  }
  if (bundle.noiseDims !== model.metadata.noiseDims) {
    throw new UserError(`bundle noise has ${bundle.noiseDims} dims, this model takes ${model.metadata.noiseDims}`);
  }
}
