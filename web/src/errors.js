// Mirrors runtime/errors.py: a refusal is a UserError with the stable `code` and the `params` Python raises for
// the same input (the two languages are tied by those, not by their messages' spelling).

/** A parameter as a JSON value: a float parsed as PyFloat as its number, a BigInt as a number. */
function plain(value) {
  if (value instanceof PyFloat) return value.value;
  if (typeof value === "bigint") return Number(value);
  if (Array.isArray(value)) return value.map(plain);
  if (value !== null && typeof value === "object") {
    return Object.fromEntries(Object.entries(value).map(([k, v]) => [k, plain(v)]));
  }
  return value;
}

export class UserError extends Error {
  /** `refusal`: { code, ...params } (code "area.what", as runtime/ raises it). */
  constructor(message, { code = null, ...params } = {}) {
    super(message);
    this.name = "UserError";
    this.code = code;
    this.params = plain(params);
  }

  /** The same refusal (code and params) with another message, e.g. the file it came from in front. */
  reworded(message) {
    return new UserError(message, { code: this.code, ...this.params });
  }
}

/** An error as a message a worker posts (structured cloning keeps an Error's message, not its code and params):
 * {message, refusal: {code, params} for a UserError, else null}. */
export const postedError = (error) => ({ message: String(error?.message ?? error),
  refusal: error instanceof UserError ? { code: error.code, params: error.params } : null });

/** The error a postedError describes, rebuilt on the other side. */
export const receivedError = ({ message, refusal }) => (refusal
  ? new UserError(message, { ...refusal.params, code: refusal.code }) : new Error(message));

/** A string read from a file as a refusal's param: its first n code points (Python's value[:n]). */
export const cut = (text, n = 60) => [...text].slice(0, n).join("");

/** A value quoted in a message, cut to `n` characters: strings and structures as JSON, floats as numbers. */
export function show(value, n = 60) {
  let text;
  try {
    text = JSON.stringify(plain(value)) ?? String(value);
  } catch {
    text = String(value);
  }
  return cut(text, n);
}

/** A JSON number written with a fraction or exponent (16.0, 1e3): a float, as Python parses it, told from an
 * integer (16), since the checks refuse a float where an integer is due (json.js, limits.js). */
export class PyFloat {
  constructor(value) { this.value = value; }
}
