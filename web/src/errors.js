// Mirrors runtime/errors.py (UserError) and the few Python reprs the refusal messages print, so that every
// refusal reads exactly as `noisenerf-reveal` prints it.

export class UserError extends Error {
  constructor(message) {
    super(message);
    this.name = "UserError";
  }
}

/** A Python tuple, for reprs: tuple(1, "a") prints as (1, 'a'). */
export function tuple(...items) {
  const t = items.slice();
  t.isTuple = true;
  return t;
}

// str.isprintable's complement: control, format, surrogate, private-use, unassigned and separator characters
// (the space excepted), which repr() escapes
const NOT_PRINTABLE = /^[\p{Cc}\p{Cf}\p{Cs}\p{Co}\p{Cn}\p{Z}]$/u;
const escaped = (c) => (c < 0x100 ? "\\x" + c.toString(16).padStart(2, "0")
  : c < 0x10000 ? "\\u" + c.toString(16).padStart(4, "0") : "\\U" + c.toString(16).padStart(8, "0"));

/** repr() of a Python str. */
export function reprStr(s) {
  const quote = s.includes("'") && !s.includes('"') ? '"' : "'";
  let out = quote;
  for (const ch of s) {
    const c = ch.codePointAt(0);
    if (ch === "\\") out += "\\\\";
    else if (ch === quote) out += "\\" + quote;
    else if (ch === "\n") out += "\\n";
    else if (ch === "\r") out += "\\r";
    else if (ch === "\t") out += "\\t";
    else if (ch !== " " && NOT_PRINTABLE.test(ch)) out += escaped(c);
    else out += ch;
  }
  return out + quote;
}

/** repr() of a Python float (shortest round trip, Python's exponent rules). */
export function reprFloat(x) {
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

/** repr() of a JSON-like Python value: null, booleans, numbers (ints are integral JS numbers or BigInts unless
 * wrapped with pyFloat), strings, lists, tuples, objects (dicts). */
export function repr(value) {
  if (value === null || value === undefined) return "None";
  if (value === true) return "True";
  if (value === false) return "False";
  if (typeof value === "bigint") return value.toString();
  if (typeof value === "number") return Number.isInteger(value) && !Object.is(value, -0) && Math.abs(value) < 1e16 ? String(value) : reprFloat(value);
  if (value instanceof PyFloat) return reprFloat(value.value);
  if (typeof value === "string") return reprStr(value);
  if (Array.isArray(value)) {
    const inner = value.map(repr).join(", ");
    if (value.isTuple) return value.length === 1 ? `(${inner},)` : `(${inner})`;
    return `[${inner}]`;
  }
  if (typeof value === "object") {
    return `{${Object.entries(value).map(([k, v]) => `${reprStr(k)}: ${repr(v)}`).join(", ")}}`;
  }
  return String(value);
}

/** A float that prints as a Python float even when integral (1.0). */
export class PyFloat {
  constructor(value) { this.value = value; }
}

/** Python's f"{value!r:.N}": the repr cut to N characters. */
export function reprCut(value, n) {
  return [...repr(value)].slice(0, n).join("");
}

/** Python's format(value, ".6g") for a number. */
export function formatG(value, precision = 6) {
  if (typeof value === "bigint") value = Number(value);
  if (!Number.isFinite(value)) return Number.isNaN(value) ? "nan" : value > 0 ? "inf" : "-inf";
  if (value === 0) return Object.is(value, -0) ? "-0" : "0";
  const exp = Number(value.toExponential(precision - 1).split("e")[1]);
  if (exp < -4 || exp >= precision) {
    let [m, e] = value.toExponential(precision - 1).split("e");
    if (m.includes(".")) m = m.replace(/0+$/, "").replace(/\.$/, "");
    const n = Number(e);
    return `${m}e${n < 0 ? "-" : "+"}${String(Math.abs(n)).padStart(2, "0")}`;
  }
  let s = value.toFixed(Math.max(0, precision - 1 - exp));
  if (s.includes(".")) s = s.replace(/0+$/, "").replace(/\.$/, "");
  return s;
}
