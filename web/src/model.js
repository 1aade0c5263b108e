// Mirrors runtime/model.py (ModelMetadata with its checks and caps, load_model's order, check_bundle) and
// runtime/fingerprint.py (SHA-256 over the sorted weights `name|<f4|[shape]|` + little-endian bytes, then
// json.dumps(architecture, sort_keys=True)).

import { sha256 } from "@noble/hashes/sha2.js";
import { bytesToHex } from "@noble/hashes/utils.js";
import { UserError, PyFloat, cut, show } from "./errors.js";
import { isJsonObject as isObject, parseJson, dumpsSorted } from "./json.js";
import { parseModel } from "./onnx.js";
import { checkGraph } from "./graph.js";
import { fieldGraph } from "./fields/index.js";
import { MAX_CAMERAS, MAX_GRID_RESOLUTION, MAX_NOISE_DIMS, checkedFloat, checkedInt, checkedList } from "./limits.js";
import { cameraFromDict, ndcFromDict } from "./camera.js";
import { samplingFromDict } from "./sampling.js";

export const MODEL_FORMAT_VERSION = 2;
const METADATA_KEY = "noisenerf", VERSION_KEY = "noisenerf_format_version";
const MAX_HIERARCHY_SAMPLES = 1024; // runtime/pdf.py

/** Malformed metadata (Python's KeyError, TypeError and ValueError in from_metadata_props), with the code and params
 * of the refusal it becomes. */
class Malformed extends Error {
  constructor(why, code = "model.metadata_malformed", params = {}) {
    super(why);
    this.code = code;
    this.params = params;
  }
}

/** Python's truth of a JSON value (`data.get("ndc")`: an empty object, list or string, 0 and 0.0 are false). */
const truthy = (value) => !(value === null || value === undefined || value === false || value === 0 || value === 0n ||
  value === "" || (value instanceof PyFloat && value.value === 0) || (Array.isArray(value) && !value.length) ||
  (isObject(value) && !Object.keys(value).length));

/** RenderConfig.from_dict, reading the keys in Python's order. */
function renderConfigFromDict(data) {
  if (!isObject(data)) throw new UserError("malformed render config: expected an object", { code: "render.not_object" });
  const need = (key) => {
    if (!Object.hasOwn(data, key)) throw new UserError(`malformed render config: missing "${key}"`, { code: "render.missing_key", key });
    return data[key];
  };
  const background = checkedList(need("background"), "render background", 3, undefined, { code: "render.background" });
  const sampling = samplingFromDict(need("sampling"));
  return {
    sampling,
    background: background.map((v) => checkedFloat(v, "render background", 0.0, 1.0, { code: "render.background" })),
    ndc: truthy(data.ndc) ? ndcFromDict(data.ndc) : null,
    pixelCenter: checkedFloat(need("pixel_center"), "render pixel_center", 0.0, 1.0, { code: "render.pixel_center" }),
    earlyStop: checkedFloat(Object.hasOwn(data, "early_stop") ? data.early_stop : new PyFloat(1e-4), "render early_stop",
      0.0, 1.0, { code: "render.early_stop" }),
  };
}

/** Hierarchy(**data): exactly n_coarse and n_importance (other keys are malformed metadata), whole numbers in range. */
function hierarchyFromDict(data) {
  if (!isObject(data) || Object.keys(data).length !== 2 || !Object.hasOwn(data, "n_coarse") || !Object.hasOwn(data, "n_importance")) {
    throw new Malformed("hierarchy must be an object of n_coarse and n_importance");
  }
  const { n_coarse: nCoarse, n_importance: nImportance } = data;
  const counts = [nCoarse, nImportance];
  if (!counts.every((n) => typeof n === "number" && Number.isInteger(n)) ||
      !(nCoarse >= 3 && nCoarse <= MAX_HIERARCHY_SAMPLES && nImportance >= 1 && nImportance <= MAX_HIERARCHY_SAMPLES)) {
    throw new UserError(`hierarchical sampling needs whole numbers 3 <= n_coarse <= ${MAX_HIERARCHY_SAMPLES} and ` +
      `1 <= n_importance <= ${MAX_HIERARCHY_SAMPLES}, got ${show(counts)}`, { code: "sampling.bad_hierarchy", most: MAX_HIERARCHY_SAMPLES });
  }
  return { nCoarse, nImportance };
}

/** grid_from_dict's checks (the cube itself is not needed here). */
function checkGrid(data) {
  if (!isObject(data) || typeof data.occupancy !== "string") {
    throw new UserError("grid must be an object with aabb, resolution and occupancy", { code: "model.grid_malformed" });
  }
  const resolution = checkedInt(data.resolution ?? null, "grid resolution", 1, MAX_GRID_RESOLUTION, { code: "model.grid_resolution" });
  const aabb = checkedList(data.aabb ?? null, "grid aabb", 6, undefined, { code: "model.grid_aabb" })
    .map((v) => checkedFloat(v, "grid aabb", -1e9, 1e9, { code: "model.grid_aabb" }));
  if (![0, 1, 2].every((a) => aabb[a] < aabb[a + 3])) {
    throw new UserError(`grid aabb must have min < max on every axis, got ${show(aabb)}`, { code: "model.grid_aabb_order", aabb });
  }
  if (!/^[A-Za-z0-9+/]*={0,2}$/.test(data.occupancy) || data.occupancy.length % 4) throw new Malformed("occupancy is not base64");
  const bytes = (data.occupancy.length / 4) * 3 - (data.occupancy.match(/=*$/)[0].length);
  const needed = Math.floor((resolution ** 3 + 7) / 8);
  if (bytes !== needed) {
    throw new Malformed(`occupancy holds ${bytes} bytes, a ${resolution}^3 grid needs ${needed}`, "model.occupancy_size",
      { bytes, resolution, needed });
  }
  return { aabb, resolution };
}

/** ModelMetadata.from_metadata_props, reading the metadata in Python's order. */
export function metadataFromProps(props, source) {
  if (!props.has(METADATA_KEY) || !props.has(VERSION_KEY)) {
    throw new UserError(`${source} is not a noisenerf model (no "${METADATA_KEY}" metadata)`, { code: "model.not_noisenerf" });
  }
  const version = props.get(VERSION_KEY);
  if (version !== String(MODEL_FORMAT_VERSION)) {
    throw new UserError(`${source} has model format version ${show(version)}; this noisenerf reads ` +
      `version ${MODEL_FORMAT_VERSION} (export the scene again with \`noisenerf export\`)`,
    { code: "model.format_version", version: cut(version) });
  }
  const data = parseJson(props.get(METADATA_KEY), `${source}: noisenerf metadata`);
  const need = (object, key) => {
    if (!isObject(object)) throw new Malformed(`expected an object holding "${key}"`);
    if (!Object.hasOwn(object, key)) throw new Malformed(`missing "${key}"`);
    return object[key];
  };
  try {
    const formatVersion = isObject(data) ? need(data, "format_version") : null;
    const number = formatVersion instanceof PyFloat ? formatVersion.value
      : typeof formatVersion === "number" || typeof formatVersion === "bigint" ? Number(formatVersion) : NaN;
    if (!isObject(data) || number !== MODEL_FORMAT_VERSION) {
      throw new Malformed(`format_version disagrees with ${VERSION_KEY}`, "model.metadata_version");
    }
    const coarse = need(need(data, "architecture"), "coarse");
    if (!isObject(coarse)) throw new Malformed("the coarse architecture is not an object");
    const architecture = { coarse: { ...coarse }, fine: need(data.architecture, "fine") };
    const hierarchy = need(data, "hierarchy") !== null ? hierarchyFromDict(data.hierarchy) : null;
    if ((architecture.fine === null) !== (hierarchy === null)) {
      throw new Malformed("a fine network and hierarchical sampling go together", "model.fine_hierarchy");
    }
    const cameras = checkedList(need(data, "cameras"), "cameras", null, MAX_CAMERAS, { code: "model.cameras" });
    const fingerprint = need(data, "fingerprint");
    const noiseDims = checkedInt(need(data, "noise_dims"), "noise_dims", 1, MAX_NOISE_DIMS, { code: "model.noise_dims_range" });
    const renderConfig = renderConfigFromDict(need(data, "render"));
    const parsedCameras = cameras.map(cameraFromDict);
    checkGrid(need(data, "grid"));
    return { fingerprint: typeof fingerprint === "string" ? fingerprint : JSON.stringify(fingerprint), architecture,
      noiseDims, renderConfig, hierarchy, cameras: parsedCameras };
  } catch (error) {
    if (error instanceof Malformed) {
      throw new UserError(`${source}: malformed noisenerf metadata (${error.message})`, { code: error.code, ...error.params });
    }
    if (error instanceof UserError) throw error.reworded(`${source}: ${error.message}`);
    throw error;
  }
}

const MASK_SECRET_PREFIX = new TextEncoder().encode("noisenerf bundle mask secret\0");

/** weights_digests: weights (name -> {shape, values Float32Array}) and the architecture -> {fingerprint, maskSecret}:
 * SHA-256 over them, and SHA-256 over MASK_SECRET_PREFIX then the same bytes (what unmasks its bundles). */
export function weightsDigests(weights, architecture) {
  const fingerprint = sha256.create(), mask = sha256.create().update(MASK_SECRET_PREFIX);
  const encoder = new TextEncoder();
  const update = (bytes) => { fingerprint.update(bytes); mask.update(bytes); };
  for (const name of [...weights.keys()].sort()) {
    const { shape, values } = weights.get(name);
    update(encoder.encode(`${name}|<f4|[${shape.join(", ")}]|`));
    update(new Uint8Array(values.buffer, values.byteOffset, values.byteLength)); // little-endian hosts only
  }
  update(encoder.encode(dumpsSorted(architecture)));
  return { fingerprint: bytesToHex(fingerprint.digest()), maskSecret: mask.digest() };
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
    if (error instanceof UserError) throw error.reworded(`${source}: ${error.message}`);
    throw error;
  }
  const weights = checkGraph(file, expected, source);
  const digests = weightsDigests(weights, metadata.architecture);
  if (digests.fingerprint !== metadata.fingerprint) {
    throw new UserError(`${source}: its weights do not match its fingerprint ${shortFingerprint(metadata.fingerprint)} ` +
      "(the model was changed after export); export the scene again", { code: "model.weights_changed" });
  }
  return { file, metadata, networks: metadata.architecture.fine === null ? ["coarse"] : ["coarse", "fine"],
    maskSecret: digests.maskSecret };
}

/** check_fingerprint: refuse a bundle hidden in another model, one naming another `fingerprint`. */
export function checkFingerprint(model, fingerprint) {
  if (fingerprint !== model.metadata.fingerprint) {
    throw new UserError(`bundle was made for model ${shortFingerprint(fingerprint)}, this model is ` +
      shortFingerprint(model.metadata.fingerprint),
    { code: "model.other_model", bundle: fingerprint.slice(0, 12), model: model.metadata.fingerprint.slice(0, 12) });
  }
}

/** check_bundle: refuse a bundle hidden in another model, or with noise the field cannot take. */
export function checkBundle(model, bundle) {
  checkFingerprint(model, bundle.modelFingerprint);
  if (bundle.noiseDims !== model.metadata.noiseDims) {
    throw new UserError(`bundle noise has ${bundle.noiseDims} dims, this model takes ${model.metadata.noiseDims}`,
      { code: "model.noise_dims", bundle: bundle.noiseDims, model: model.metadata.noiseDims });
  }
}
