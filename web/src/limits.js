// Mirrors runtime/limits.py: caps on every number a file may dictate, checked before anything is allocated (the
// hide's own caps and MAX_XZ_MEMORY, which xz-decompress's decoder enforces itself: src/bundle.js, are not here).

import { UserError, PyFloat, reprCut, formatG, repr } from "./errors.js";

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

const isInt = (v) => (typeof v === "number" && Number.isInteger(v)) || typeof v === "bigint";

/** checked_int: a JSON integer in [low, high]. */
export function checkedInt(value, what, low, high) {
  if (!isInt(value)) throw new UserError(`${what} must be an integer, got ${reprCut(value, 40)}`);
  if (!(value >= low && value <= high)) throw new UserError(`${what} must be between ${low} and ${high}, got ${formatG(value)}`);
  return Number(value);
}

// Python prints the bounds as given: a float (0.0, 1e-06, 1000000000.0, inf) as a number here, an int bound (the
// nerfacto kind's MAX_HASH_RESOLUTION - 2) as a BigInt
function boundText(x) {
  if (typeof x === "bigint") return String(x);
  return Number.isFinite(x) ? repr(new PyFloat(x)) : (x > 0 ? "inf" : "-inf");
}

/** checked_float: a finite number in [low, high] (an int or a PyFloat; a bound is a float, or an int as a BigInt). */
export function checkedFloat(value, what, low = -Infinity, high = Infinity) {
  if (!(isInt(value) || value instanceof PyFloat)) throw new UserError(`${what} must be a number, got ${reprCut(value, 40)}`);
  const number = value instanceof PyFloat ? value.value : Number(value);
  if (!Number.isFinite(number) || !(number >= low && number <= high)) {
    throw new UserError(`${what} must be a finite number in [${boundText(low)}, ${boundText(high)}], got ${reprCut(value, 40)}`);
  }
  return number;
}

export function checkedList(value, what, length = null, most = MAX_CAMERAS) {
  if (!Array.isArray(value)) throw new UserError(`${what} must be a list, got ${pyTypeName(value)}`);
  if ((length !== null && value.length !== length) || value.length > most) {
    throw new UserError(`${what} must hold ${length !== null ? length : `at most ${most}`} items, got ${value.length}`);
  }
  return value;
}

export function pyTypeName(value) {
  if (value === null || value === undefined) return "NoneType";
  if (typeof value === "boolean") return "bool";
  if (isInt(value)) return "int";
  if (value instanceof PyFloat) return "float";
  if (typeof value === "string") return "str";
  if (Array.isArray(value)) return "list";
  return "dict";
}

export function checkedImageSize(width, height, what) {
  width = checkedInt(width, `${what} width`, 1, MAX_IMAGE_SIDE);
  height = checkedInt(height, `${what} height`, 1, MAX_IMAGE_SIDE);
  if (width * height > MAX_IMAGE_PIXELS) throw new UserError(`${what} is ${width}x${height}, more than the ${MAX_IMAGE_PIXELS} pixels noisenerf renders`);
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
      + `state (at most ${MAX_XZ_RATIO} times their size)`);
  }
}
