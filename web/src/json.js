// Mirrors runtime/files.py parse_json (Python's json.loads, nesting at most MAX_JSON_DEPTH) and json.dumps with
// sort_keys=True (the fingerprint's canonical JSON). Python tells 16 from 16.0, so this parser does too: integer
// literals are JS numbers (BigInt beyond 2^53), every other number is a PyFloat; NaN and Infinity parse, as in
// Python, and are refused where a number is used (limits.js).

import { UserError, PyFloat } from "./errors.js";
import { MAX_JSON_DEPTH } from "./limits.js";

class JsonError extends Error {}

const NUMBER = /-?(?:0|[1-9]\d*)(\.\d+)?([eE][-+]?\d+)?/y;
const MAX_INT_DIGITS = 4300; // Python's int() refuses longer decimal strings, so its json.loads does

export function loads(textValue) {
  let i = 0;
  const s = textValue;
  const ws = () => { while (i < s.length && " \t\n\r".includes(s[i])) i++; };
  const fail = (what) => { throw new JsonError(`${what} at position ${i}`); };
  let depth = 0, deepest = 0; // the containers around the value being read, the most around any (Python's json_depth)
  function value() {
    ws();
    deepest = Math.max(deepest, depth);
    const c = s[i];
    if (c === "{") {
      i++; depth++;
      if (depth > MAX_JSON_DEPTH + 1) throw new RangeError("too deep");
      const obj = {};
      ws();
      if (s[i] === "}") { i++; depth--; return obj; }
      for (;;) {
        ws();
        if (s[i] !== '"') fail("expected a property name in double quotes");
        const key = string();
        ws();
        if (s[i] !== ":") fail("expected ':' after a property name");
        i++;
        Object.defineProperty(obj, key, { value: value(), enumerable: true, writable: true, configurable: true });
        ws();
        if (s[i] === ",") { i++; continue; }
        if (s[i] === "}") { i++; depth--; return obj; }
        fail("expected ',' or '}' after a property value");
      }
    }
    if (c === "[") {
      i++; depth++;
      if (depth > MAX_JSON_DEPTH + 1) throw new RangeError("too deep");
      const arr = [];
      ws();
      if (s[i] === "]") { i++; depth--; return arr; }
      for (;;) {
        arr.push(value());
        ws();
        if (s[i] === ",") { i++; continue; }
        if (s[i] === "]") { i++; depth--; return arr; }
        fail("expected ',' or ']' after an array element");
      }
    }
    if (c === '"') return string();
    for (const [word, v] of [["true", true], ["false", false], ["null", null], ["NaN", new PyFloat(NaN)],
      ["Infinity", new PyFloat(Infinity)], ["-Infinity", new PyFloat(-Infinity)]]) {
      if (s.startsWith(word, i)) { i += word.length; return v; }
    }
    NUMBER.lastIndex = i;
    const m = NUMBER.exec(s);
    if (!m) fail(i >= s.length ? "unexpected end of input" : "unexpected character");
    if (m[1] === undefined && m[2] === undefined && m[0].replace("-", "").length > MAX_INT_DIGITS) {
      fail(`integer of more than ${MAX_INT_DIGITS} digits`);
    }
    i += m[0].length;
    if (m[1] === undefined && m[2] === undefined) {
      const big = BigInt(m[0]);
      return big >= -BigInt(Number.MAX_SAFE_INTEGER) && big <= BigInt(Number.MAX_SAFE_INTEGER) ? Number(big) : big;
    }
    return new PyFloat(Number(m[0]));
  }
  function string() {
    i++;
    let out = "";
    for (;;) {
      if (i >= s.length) fail("unterminated string");
      const c = s[i];
      if (c === '"') { i++; return out; }
      if (c === "\\") {
        const e = s[i + 1];
        const map = { '"': '"', "\\": "\\", "/": "/", b: "\b", f: "\f", n: "\n", r: "\r", t: "\t" };
        if (e in map) { out += map[e]; i += 2; continue; }
        if (e === "u") {
          const hex = s.slice(i + 2, i + 6);
          if (!/^[0-9a-fA-F]{4}$/.test(hex)) fail("bad \\u escape in a string");
          out += String.fromCharCode(parseInt(hex, 16)); i += 6; continue;
        }
        fail("bad escape in a string");
      }
      if (c.charCodeAt(0) < 0x20) fail("control character in a string");
      out += c; i++;
    }
  }
  const result = value();
  ws();
  if (i !== s.length) fail("unexpected text after the JSON value");
  return { result, deepest };
}

/** isinstance(value, dict) of a value parsed here (a PyFloat is a float, not an object). */
export const isJsonObject = (value) => value !== null && typeof value === "object" && !Array.isArray(value) &&
  !(value instanceof PyFloat);

/** parse_json: JSON text (or UTF-8 bytes) someone else made -> value, one UserError when malformed (json.invalid)
 * or deep (json.too_deep). */
export function parseJson(input, what, source = "") {
  let data;
  try {
    const textValue = typeof input === "string" ? input : new TextDecoder("utf-8", { fatal: true }).decode(input);
    const { result, deepest } = loads(textValue);
    if (deepest > MAX_JSON_DEPTH) throw new RangeError("too deep");
    data = result;
  } catch (error) {
    if (error instanceof RangeError) {
      throw new UserError(`${what} is nested deeper than ${MAX_JSON_DEPTH} levels${source ? `: ${source}` : ""}`,
        { code: "json.too_deep", depth: MAX_JSON_DEPTH });
    }
    throw new UserError(`${what} is not valid JSON${source ? `: ${source}` : ""} (${error.message})`, { code: "json.invalid" });
  }
  return data;
}

function dumpString(s) {
  let out = '"';
  for (const ch of s) {
    const c = ch.codePointAt(0);
    if (ch === '"') out += '\\"';
    else if (ch === "\\") out += "\\\\";
    else if (ch === "\n") out += "\\n";
    else if (ch === "\r") out += "\\r";
    else if (ch === "\t") out += "\\t";
    else if (ch === "\b") out += "\\b";
    else if (ch === "\f") out += "\\f";
    else if (c < 0x20 || c > 0x7e) {
      if (c > 0xffff) {
        const v = c - 0x10000;
        out += `\\u${(0xd800 + (v >> 10)).toString(16).padStart(4, "0")}\\u${(0xdc00 + (v & 0x3ff)).toString(16).padStart(4, "0")}`;
      } else out += `\\u${c.toString(16).padStart(4, "0")}`;
    } else out += ch;
  }
  return out + '"';
}

// Python sorts strings by code point; JS's < compares UTF-16 code units (they differ past U+FFFF)
const codePoints = (s) => Array.from(s, (ch) => ch.codePointAt(0));
/** Python's order of two strings (sorted()), for Array.sort. */
export function pyCompare(a, b) {
  const x = codePoints(a), y = codePoints(b);
  for (let i = 0; i < Math.min(x.length, y.length); i++) if (x[i] !== y[i]) return x[i] - y[i];
  return x.length - y.length;
}

/** Python's json.dumps(value, sort_keys=True): ", " and ": " separators (or the given ones), ASCII escapes,
 * floats as repr. */
export function dumpsSorted(value, item = ", ", key = ": ") {
  const dump = (v) => dumpsSorted(v, item, key);
  if (value === null) return "null";
  if (value === true) return "true";
  if (value === false) return "false";
  if (typeof value === "bigint") return value.toString();
  if (typeof value === "number") return Number.isInteger(value) ? String(value) : floatJson(value);
  if (value instanceof PyFloat) return floatJson(value.value);
  if (typeof value === "string") return dumpString(value);
  if (Array.isArray(value)) return `[${value.map(dump).join(item)}]`;
  const keys = Object.keys(value).sort(pyCompare);
  return `{${keys.map((k) => `${dumpString(k)}${key}${dump(value[k])}`).join(item)}}`;
}

/** runtime/sealing.py canonical_json: sorted keys, no spaces, ASCII, as UTF-8 bytes. */
export function canonicalJson(value) {
  return new TextEncoder().encode(dumpsSorted(value, ",", ":"));
}

/** Python's == between two JSON values (1 == 1.0 == True; dicts by keys and values; lists by items). */
export function pyEqual(a, b) {
  const number = (v) => (v === true ? 1 : v === false ? 0 : v instanceof PyFloat ? v.value
    : typeof v === "number" || typeof v === "bigint" ? v : undefined);
  const [x, y] = [number(a), number(b)];
  if (x !== undefined || y !== undefined) return x !== undefined && y !== undefined && x == y; // eslint-disable-line eqeqeq
  if (a === null || b === null || typeof a === "string" || typeof b === "string") return a === b;
  if (Array.isArray(a) || Array.isArray(b)) {
    return Array.isArray(a) && Array.isArray(b) && a.length === b.length && a.every((v, i) => pyEqual(v, b[i]));
  }
  const ka = Object.keys(a), kb = Object.keys(b);
  return ka.length === kb.length && ka.every((k) => Object.hasOwn(b, k) && pyEqual(a[k], b[k]));
}

function floatJson(x) {
  if (Number.isNaN(x)) return "NaN";
  if (!Number.isFinite(x)) return x > 0 ? "Infinity" : "-Infinity";
  return reprFloat(x);
}

/** A float as Python's json.dumps writes it (its repr: shortest round trip, Python's exponent rules), which the
 * seal's canonical JSON must reproduce byte for byte. */
function reprFloat(x) {
  if (Number.isNaN(x)) return "nan";
  if (!Number.isFinite(x)) return x > 0 ? "inf" : "-inf";
  if (x === 0) return Object.is(x, -0) ? "-0.0" : "0.0";
  const [mantissa, exp] = x.toExponential().split("e");
  const e = Number(exp);
  const negative = mantissa.startsWith("-");
  const digits = mantissa.replace("-", "").replace(".", "");
  let body;
  if (e >= -4 && e < 16) {
    if (e >= 0) {
      const intPart = digits.length > e + 1 ? digits.slice(0, e + 1) : digits.padEnd(e + 1, "0");
      const frac = digits.length > e + 1 ? digits.slice(e + 1) : "0";
      body = `${intPart}.${frac}`;
    } else {
      body = `0.${"0".repeat(-e - 1)}${digits}`;
    }
  } else {
    const m = digits.length > 1 ? `${digits[0]}.${digits.slice(1)}` : digits;
    body = `${m}e${e < 0 ? "-" : "+"}${String(Math.abs(e)).padStart(2, "0")}`;
  }
  return (negative ? "-" : "") + body;
}
