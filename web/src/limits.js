// Mirrors runtime/limits.py: caps on every number a file may dictate, checked before anything is allocated (the
// hide's own caps and MAX_XZ_MEMORY, which xz-decompress's decoder enforces itself: src/bundle.js, are not here).

import { UserError, PyFloat, show } from "./errors.js";

export const MAX_IMAGE_SIDE = 16384;
export const MAX_IMAGE_PIXELS = 8192 * 8192;
export const MAX_SAMPLES_PER_RAY = 1024;
export const MAX_RAY_LAYOUT_SAMPLES = 256;
export const MAX_COMPACT_COEFFICIENTS = 8;
export const MAX_XZ_RATIO = 64;
export const FREE_XZ_BYTES = 1 << 20;
export const MAX_TILES = Math.floor(MAX_IMAGE_PIXELS / 16 ** 2);
export const MAX_NOISE_DIMS = 4096;
export const MAX_FIELD_DEPTH = 64;
export const MAX_FIELD_WIDTH = 4096;
export const MAX_FREQUENCIES = 32;
export const MAX_HASH_LEVELS = 32;
export const MAX_HASH_FEATURES = 8;
export const MAX_LOG2_TABLE = 24;
export const MAX_TABLE_VALUES = 2 ** 28;
export const MAX_PROPOSAL_NETWORKS = 4;
export const MAX_HASH_RESOLUTION = 2 ** 20;
export const MAX_GRID_RESOLUTION = 512;
export const MAX_CAMERAS = 100_000;
export const MAX_JSON_DEPTH = 32;
export const MAX_HEADER_BYTES = 100_000_000; // a bundle's safetensors header (the safetensors library's own cap)
export const MAX_MODEL_FIELDS = 2 ** 18; // protobuf fields a model's parse walks in all

const isInt = (v) => (typeof v === "number" && Number.isInteger(v)) || typeof v === "bigint";


/** These numbers (ints, BigInts, PyFloats) as a refusal's params, those that are not finite floats left out. */
export function finiteParams(numbers) {
  return Object.fromEntries(Object.entries(numbers).filter(([, v]) => Number.isFinite(v instanceof PyFloat ? v.value : Number(v))));
}

/** An integer for a message: as it is, or past 16 digits in the form 1.23456e+400. */
function approximately(value) {
  const text = String(value), digits = text.replace("-", "");
  return digits.length <= 16 ? text : `${text.startsWith("-") ? "-" : ""}${digits[0]}.${digits.slice(1, 6)}e+${digits.length - 1}`;
}

/** A JSON value quoted for a message: a float as a float (16.0, NaN), anything else as show() quotes it. */
function quoted(value) {
  if (value instanceof PyFloat) return Number.isInteger(value.value) ? value.value.toFixed(1) : String(value.value);
  return show(value, 40);
}

/** What a JSON value is, for a message. */
function kindOf(value) {
  if (value === null || value === undefined) return "null";
  if (isInt(value) || value instanceof PyFloat) return "a number";
  if (typeof value === "object") return "an object";
  return `a ${typeof value}`;
}

/** checked_int: a JSON integer in [low, high]. `refusal`: { code, ...params } of the field (as runtime/ names
 * it), raised with the bounds (and the value, when out of them). */
export function checkedInt(value, what, low, high, { code = null, ...params } = {}) {
  if (!isInt(value)) throw new UserError(`${what} must be an integer, got ${quoted(value)}`, { code, ...finiteParams({ low, high }), ...params });
  if (!(value >= low && value <= high)) {
    throw new UserError(`${what} must be between ${low} and ${high}, got ${approximately(value)}`,
      { code, ...finiteParams({ value, low, high }), ...params });
  }
  return Number(value);
}

/** checked_float: a finite number in [low, high] (an int or a PyFloat; a bound is a number, or an int as a BigInt).
 * `refusal` as checkedInt's; a value or bound that is not finite is left out of the params. */
export function checkedFloat(value, what, low = -Infinity, high = Infinity, { code = null, ...params } = {}) {
  if (!(isInt(value) || value instanceof PyFloat)) {
    throw new UserError(`${what} must be a number, got ${quoted(value)}`, { code, ...finiteParams({ low, high }), ...params });
  }
  const number = value instanceof PyFloat ? value.value : Number(value);
  if (!Number.isFinite(number) || !(number >= low && number <= high)) {
    throw new UserError(`${what} must be a finite number in [${low}, ${high}], got ${quoted(value)}`,
      { code, ...finiteParams({ value, low, high }), ...params });
  }
  return number;
}

/** checked_list: a JSON list of `length` items (or at most `most`). `refusal` as checkedInt's. */
export function checkedList(value, what, length = null, most = MAX_CAMERAS, { code = null, ...params } = {}) {
  if (!Array.isArray(value)) throw new UserError(`${what} must be a list, got ${kindOf(value)}`, { code, ...params });
  if ((length !== null && value.length !== length) || value.length > most) {
    throw new UserError(`${what} must hold ${length !== null ? length : `at most ${most}`} items, got ${value.length}`,
      { code, count: value.length, ...(length !== null ? { length } : { most }), ...params });
  }
  return value;
}

/** checked_image_size: (width, height) within MAX_IMAGE_SIDE and MAX_IMAGE_PIXELS. `refusal` as checkedInt's, for
 * each side (side: "width" or "height") and for the pixels together. */
export function checkedImageSize(width, height, what, { code = null, ...params } = {}) {
  width = checkedInt(width, `${what} width`, 1, MAX_IMAGE_SIDE, { code, side: "width", ...params });
  height = checkedInt(height, `${what} height`, 1, MAX_IMAGE_SIDE, { code, side: "height", ...params });
  if (width * height > MAX_IMAGE_PIXELS) {
    throw new UserError(`${what} is ${width}x${height}, more than the ${MAX_IMAGE_PIXELS} pixels noisenerf renders`,
      { code, width, height, most: MAX_IMAGE_PIXELS, ...params });
  }
  return [width, height];
}

/** A JSON number (int or PyFloat) as a JS number, or undefined. */
export function num(value) {
  return value instanceof PyFloat ? value.value : isInt(value) ? Number(value) : undefined;
}

/** checked_expansion: compressed streams of `packed` bytes may state at most MAX_XZ_RATIO times that (or FREE_XZ_BYTES). */
export function checkedExpansion(packed, stated, what) {
  if (stated > Math.max(FREE_XZ_BYTES, MAX_XZ_RATIO * packed)) {
    throw new UserError(`${what}: ${packed} bytes of compressed coefficients cannot hold the ${stated} bytes the tiles `
      + `state (at most ${MAX_XZ_RATIO} times their size)`, { code: "compact.xz_ratio", packed, stated, ratio: MAX_XZ_RATIO });
  }
}
