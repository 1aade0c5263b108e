// Mirrors runtime/layouts.py: one object per noise layout (ray, sample, compact), owning its storage dtypes, the
// stored array's shape, the noise vectors a ray holds, the samples one vector may serve, its part of the bundle's
// noise header, how a tile's tensors are read and checked, how its compressed streams are checked, and how a chunk
// of its noise is cut out (`chunk`, a plain record a worker can be sent) and expanded (`rows`). bundle.js keeps the
// file format and asks the layout; no other module branches on a layout's name.

import xz from "xz-decompress";
import { UserError, cut, show } from "./errors.js";
import { decodeInterlaced } from "./interlaced.js";
import {
  MAX_COMPACT_COEFFICIENTS, MAX_RAY_LAYOUT_SAMPLES, MAX_SAMPLES_PER_RAY, checkedExpansion, checkedFloat, checkedInt,
} from "./limits.js";

const { XzReadableStream } = xz;
const f32 = Math.fround;
const FLOAT32_TINY = 1.1754943508222875e-38, FLOAT32_MAX = 3.4028234663852886e38;
const PLANES_CODEC = "xz-byte-planes", INTERLACED_CODEC = "xz-interlaced-residuals";
const INTERLACED_FROM = 4; // the bundle format from which compact tiles store interlaced differences
const BRANCH_ESCAPES_FROM = 3; // the bundle format from which compact tiles store branch escapes
/** codec_of: the coefficient codec a compact tile of bundle format `version` states and is read with. */
const codecOf = (version) => (version >= INTERLACED_FROM ? INTERLACED_CODEC : PLANES_CODEC);

/** IEEE half -> float. */
const HALF = new Float32Array(65536);
for (let h = 0; h < 65536; h++) {
  const sign = h & 0x8000 ? -1 : 1, exp = (h >> 10) & 0x1f, frac = h & 0x3ff;
  HALF[h] = exp === 0 ? sign * frac * 2 ** -24 : exp === 31 ? (frac ? NaN : sign * Infinity) : sign * (1 + frac / 1024) * 2 ** (exp - 15);
}

/** float16 values (their bits) -> Float32Array. */
export function widened(halves) {
  const values = new Float32Array(halves.length);
  for (let i = 0; i < halves.length; i++) values[i] = HALF[halves[i]];
  return values;
}

// xz-embedded's error codes (enum xz_ret). Its dictionaries stop at 64 MiB; the next size a stream can state, 96 MiB,
// is over runtime's MAX_XZ_MEMORY too.
const XZ_OK = 0, XZ_STREAM_END = 1, XZ_DATA_ERROR = 7, XZ_BUF_ERROR = 8;
const XZ_ERRORS = { 2: "unsupported integrity check", 3: "cannot allocate memory", 4: "dictionary over the decoder's memory",
  5: "not an xz stream", 6: "unsupported options", 7: "corrupt data" };

/** xz-decompress's WebAssembly build of xz-embedded (create_context, supply_input, get_next_output, destroy_context),
 * instantiated once as its XzReadableStream does. That stream decodes concatenated streams and skips the zero padding
 * between them (xz_dec_catrun), where runtime/ (Python's LZMADecompressor) reads exactly one stream: so the decoder is
 * driven here, call by call, to find where the first stream ends (firstStream). Pinned to xz-decompress 0.2.3, whose
 * context is {bufSize, xz_buf {in, in_pos, in_size, out, out_pos, out_size}, xz_dec}, 32-bit words. */
async function xzDecoder() {
  if (!XzReadableStream._moduleInstance) {
    await (XzReadableStream._moduleInstancePromise ||= XzReadableStream._getModuleInstance());
  }
  const decoder = XzReadableStream._moduleInstance.exports;
  if (!["create_context", "supply_input", "get_next_output", "destroy_context"].every((name) => typeof decoder[name] === "function")) {
    throw new Error("xz-decompress is not the version src/layouts.js drives (0.2.3)");
  }
  return decoder;
}

/** Where an xz stream starting at 0 may end in `packed`: after a stream footer's magic "YZ", at a multiple of 4 bytes,
 * 32 at least (header, index and footer). Every stream's true end is one; most bytes are none. -> the next after `from`. */
function nextStreamEnd(packed, from) {
  for (let p = Math.max(32, from + 4 - (from % 4)); p <= packed.length; p += 4) {
    if (packed[p - 2] === 0x59 && packed[p - 1] === 0x5a) return p;
  }
  return null;
}

const CHECK_SIZES = { 0: 0, 1: 4, 4: 8 }; // the integrity checks xz-embedded verifies (runtime/ refuses the others)

/** Where each LZMA chunk's range coder starts in the first stream of `packed`, its blocks and LZMA2 chunks followed by
 * their headers alone (each states its size), as far as they can be (a stream that cannot be followed further is one
 * the decoder refuses by then). liblzma (runtime/) refuses a chunk whose first range-coder byte is not 0; xz-embedded
 * reads past it, so the decoder is stopped at each of these places to check it (firstStream). -> ascending positions */
function rangeCoderStarts(packed) {
  const starts = [], n = packed.length, check = CHECK_SIZES[packed[7]];
  let at = 12;
  while (check !== undefined && at < n && packed[at] !== 0) { // a block header (0: the index)
    const size = (packed[at] + 1) * 4, flags = packed[at + 1];
    let field = at + 2;
    for (const present of [flags & 0x40, flags & 0x80]) { // compressed and uncompressed sizes, varints
      if (present) while (field < n && packed[field++] & 0x80);
    }
    if ((flags & 0x03) !== 0 || packed[field] !== 0x21 || packed[field + 1] !== 1 || field + 3 > at + size) break; // LZMA2 alone
    at += size;
    for (;;) { // LZMA2 chunks up to the end marker 0x00
      const control = packed[at];
      if (control === undefined) return starts;
      if (control === 0x00) { at += 1; break; }
      if (control === 0x01 || control === 0x02) at += 3 + ((packed[at + 1] << 8) | packed[at + 2]) + 1;
      else if (control >= 0x80) {
        const header = control >= 0xc0 ? 6 : 5;
        starts.push(at + header);
        at += header + ((packed[at + 3] << 8) | packed[at + 4]) + 1;
      } else return starts;
    }
    at += (4 - (at % 4)) % 4 + check; // block padding, then its check
  }
  return starts;
}

/** The first xz stream of `packed`, decoded as runtime/'s lzma.LZMADecompressor(FORMAT_XZ).decompress(packed,
 * max_length=limit) decodes it: -> {data: at most `limit` bytes, ended: whether the stream ended, and at `packed`'s
 * end, error: xz-embedded's code of an error inside the stream, else 0}. The decoder is given the bytes up to each
 * place the stream may end (nextStreamEnd) and then asked to finish: it says the stream ended only where it did (it
 * decodes the stream's own bytes alone, and so never reads past its end); output stops at `limit` bytes. */
function firstStream(decoder, packed, limit) {
  const context = decoder.create_context();
  let bytes, words;
  const views = () => {
    if (bytes?.buffer !== decoder.memory.buffer) {
      bytes = new Uint8Array(decoder.memory.buffer, context);
      words = new Uint32Array(decoder.memory.buffer, context);
    }
  };
  try {
    views();
    const bufSize = words[0], input = words[1] - context, output = words[4] - context;
    const data = new Uint8Array(limit + 1);
    const starts = rangeCoderStarts(packed);
    let total = 0, position = 0, end = nextStreamEnd(packed, 0), start = 0;
    const supply = (stop) => {
      views();
      bytes.set(packed.subarray(position, stop), input);
      decoder.supply_input(context, stop - position); // in_size 0: xz_dec_catrun is told the input has ended
      position = stop;
    };
    const run = (extra = 0) => { // one call: its code, and whether it filled the room it had
      views();
      const room = Math.min(bufSize, limit + extra - total);
      words[5] = 0;
      words[6] = room;
      const code = decoder.get_next_output(context);
      views();
      data.set(bytes.subarray(output, output + words[5]), total);
      total += words[5];
      return { code, produced: words[5], full: words[5] === room, consumed: words[2] === words[3] };
    };
    const result = (ended, error = 0) => ({ data: data.subarray(0, total), ended: ended && position === packed.length, error });
    // The output has reached the limit. liblzma reads a chunk's input a symbol ahead of xz-embedded, so a stream whose
    // input runs out (or goes wrong) right where its output passes the limit is corrupt to runtime/ (its decoder
    // fails in the call that fills the limit): one more symbol, on the input already given, tells.
    const atLimit = () => {
      const { code } = run(1);
      return result(false, code === XZ_OK || code === XZ_STREAM_END || code === XZ_BUF_ERROR ? 0 : code);
    };
    for (;;) {
      if (position === starts[start]) {
        if (packed[position] !== 0) return result(false, XZ_DATA_ERROR); // as liblzma refuses it
        start += 1;
      }
      const stop = Math.min(end ?? packed.length, starts[start] ?? packed.length, position + bufSize);
      if (stop > position) {
        supply(stop);
        for (;;) {
          const { code, full, consumed } = run();
          if (code !== XZ_OK) return result(false, code);
          if (total >= limit) return atLimit();
          if (consumed && !full) break;
        }
      }
      if (position === end) {
        supply(position);
        for (;;) {
          const { code, produced } = run();
          if (code === XZ_STREAM_END) return result(true);
          if (total >= limit) return atLimit();
          if (code !== XZ_OK && code !== XZ_BUF_ERROR) return result(false, code);
          if (produced === 0) break; // the stream goes on past here
        }
        end = nextStreamEnd(packed, position);
      }
      if (position === packed.length && end === null) return result(false);
    }
  } finally {
    decoder.destroy_context(context);
  }
}

/** unpack_coefficients: the xz stream of byte planes -> Int8Array/Int16Array (h·w·k, row-major (h, w, k)). tile: the
 * tile's number, for the refusal. As runtime/ refuses: corrupt within the stream (compact.xz_corrupt), or not exactly
 * one stream holding exactly the stated bytes, nothing after it (compact.xz_size). */
export async function unpackCoefficients(packed, shape, dtype, what, tile = null) {
  const [height, width, k] = shape;
  const item = dtype === "int16" ? 2 : 1;
  const expected = height * width * k * item;
  const { data, ended, error } = firstStream(await xzDecoder(), packed, expected + 1);
  if (error !== 0 && error !== XZ_BUF_ERROR) {
    throw new UserError(`${what}: compressed coefficients are corrupt (${XZ_ERRORS[error] ?? "corrupt data"})`,
      { code: "compact.xz_corrupt", tile });
  }
  if (error !== 0 || !ended || data.length !== expected) {
    throw new UserError(`${what}: compressed coefficients do not hold exactly ${height}x${width}x${k} ${dtype} values`,
      { code: "compact.xz_size", tile, shape: [height, width, k], dtype });
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
 * Summed in float32 over k = 0..K-1, numpy's order; numpy's BLAS may fuse the multiply-adds where this does not,
 * which moves noise by float32 rounding and no revealed 8-bit value (web/test measures both). */
export function expandCoefficients(coefficients, k, basis) {
  const dims = basis.offset.length, m = coefficients.length / k;
  const out = new Float32Array(m * dims);
  const scale = f32(basis.scale), matrix = basis.basis, offset = basis.offset;
  // A zero basis entry adds +0 to a sum that is never −0, so leaving it out changes nothing; a compact tile's
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
      let dot = f32(params[column[t]] * value[t]) + 0; // −0 made +0, as a sum from zero makes it
      for (t++; t < from[i + 1]; t++) dot = f32(dot + f32(params[column[t]] * value[t]));
      out[at + live[i]] = f32(offset[live[i]] + dot);
    }
  }
  const escapes = basis.escapes;
  for (let e = 0; e < escapes.length; e++) out.set(basis.escapeNoise.subarray(e * dims, (e + 1) * dims), escapes[e] * dims);
  const branchEscapes = basis.branchEscapes, width = basis.branchWidth, lead = dims - width;
  for (let b = 0; b < branchEscapes.length; b++) {
    out.set(offset.subarray(0, lead), branchEscapes[b] * dims);
    out.set(basis.branchEscapeNoise.subarray(b * width, (b + 1) * width), branchEscapes[b] * dims + lead);
  }
  return out;
}


function allFinite(values) {
  if (values instanceof Uint16Array) return values.every((half) => (half & 0x7c00) !== 0x7c00); // float16's bits
  for (let i = 0; i < values.length; i++) if (!Number.isFinite(values[i])) return false;
  return true;
}

function sameShape(a, b) { return a.length === b.length && a.every((v, i) => v === b[i]); }

/** What every layout answers (runtime/layouts.py NoiseLayout); ray is exactly this. */
const VECTOR = {
  maxSamples: MAX_RAY_LAYOUT_SAMPLES,
  vectorsPerRay: () => 1,
  storedShape: (h, w, nSamples, perVector) => [h, w, perVector],
  readHeader(noise) {
    if (noise.coefficients !== undefined && noise.coefficients !== null) {
      throw new UserError("bundle: coefficients per pixel are given for, and only for, the compact layout",
        { code: "bundle.coefficients_layout", layout: this.name });
    }
    return null;
  },
  checkStreams() {},
  async readTile(name, data, tensor) { return { tensor: tensor(name) }; },
  /** Tile number `tile`'s noise against its stated shape and dtype, finite. */
  checkNoise(tile, noise, pixels, dims, k, shape, dtype) {
    const stored = noise.tensor;
    if (!sameShape(stored.shape, shape) || stored.dtype !== dtype) {
      throw new UserError(`bundle: tile ${tile} noise is ${stored.dtype} [${stored.shape}], expected ${dtype} [${shape}]`,
        { code: "bundle.tile_noise_shape", tile, dtype: stored.dtype, shape: stored.shape, expected_dtype: dtype, expected_shape: shape });
    }
    if (!allFinite(stored.values)) {
      throw new UserError(`bundle: tile ${tile} noise holds NaN or Inf`, { code: "bundle.tile_noise_not_finite", tile });
    }
  },
  /** The checked noise as a render reads it. */
  loaded(noise) { noise.values = noise.tensor.values; },
  /** A tile's noise for its pixels start..stop, on its own: only those pixels' stored values (copies, so that a
   * worker is sent them alone). -> a record `rows` expands. */
  chunk(tile, bundle, start, stop) {
    const dims = bundle.noiseDims, per = this.vectorsPerRay(tile.sampling.nSamples);
    const stored = tile.noise.values.subarray(start * per * dims, stop * per * dims);
    return { layout: this.name, values: stored instanceof Uint16Array ? widened(stored) : stored.slice(), perSample: per, dims };
  },
  /** A chunk's float32 noise: {values, perSample (1 or n_samples), dims}. */
  rows(chunk) { return { values: chunk.values, perSample: chunk.perSample, dims: chunk.dims }; },
};

const COMPACT = {
  ...VECTOR,
  readHeader(noise, dims, version) {
    const k = checkedInt(noise.coefficients ?? null, "bundle: coefficients per pixel", 1, MAX_COMPACT_COEFFICIENTS,
      { code: "compact.coefficients" });
    const codec = noise.codec, expected = codecOf(version);
    if (codec !== expected) {
      throw new UserError(`bundle: unknown coefficient codec ${show(codec ?? null, 40)} (expected ${show(expected)})`,
        { code: "compact.codec", ...(typeof codec === "string" ? { codec: cut(codec) } : {}), expected });
    }
    const most = Math.min(dims, MAX_COMPACT_COEFFICIENTS);
    if (k > most) {
      throw new UserError(`bundle: ${k} coefficients per pixel, expected 1 to ${most}`,
        { code: "compact.coefficients", value: k, low: 1, high: most });
    }
    return k;
  },
  /** The tiles' areas against the secret, then their streams against what they state (before any is inflated). */
  checkStreams(streams, [width, height], tilePixels, k, dtype) {
    if (tilePixels !== width * height) {
      throw new UserError(`bundle: the tiles' areas do not add up to the ${width}x${height} secret`,
        { code: "bundle.tile_areas", width, height });
    }
    const packed = streams.reduce((n, stream) => n + (stream === undefined ? 0 : stream.values.byteLength), 0);
    checkedExpansion(packed, tilePixels * k * (dtype === "int16" ? 2 : 1), "bundle");
  },
  /** Tile number `tile`'s tensors, in runtime's order (a missing one is refused as there); branch escapes from
   * format 3 on (a format 2 tile has none). */
  async readTile(name, data, tensor, shape, dtype, tile, version) {
    const what = `bundle: tile ${tile}`;
    const branch = version >= BRANCH_ESCAPES_FROM
      ? { branchEscapes: tensor(`${name}_branch_escapes`), branchEscapeNoise: tensor(`${name}_branch_escape_noise`) }
      : { branchEscapes: { dtype: "int32", shape: [0], values: new Int32Array(0) },
        branchEscapeNoise: { dtype: "float16", shape: [0, 0], values: new Uint16Array(0) } };
    const basis = tensor(`${name}_basis`), offset = tensor(`${name}_offset`);
    const scale = checkedFloat(data.scale ?? null, `${what} scale`, FLOAT32_TINY, FLOAT32_MAX, { code: "compact.scale", tile });
    const escapes = tensor(`${name}_escapes`), escapeNoise = tensor(`${name}_escape_noise`);
    const interlaced = codecOf(version) === INTERLACED_CODEC;
    const bandRows = interlaced
      ? checkedInt(data.band_rows ?? null, `${what} band rows`, 1, shape[0], { code: "compact.band_rows", tile }) : null;
    const packed = tensor(name, "uint8", 1);
    const planes = await unpackCoefficients(packed.values, shape, dtype, what, tile);
    const coefficients = interlaced ? decodeInterlaced(planes, ...shape, bandRows) : planes;
    return { coefficients, shape, dtype, basis: { basis, offset, scale, escapes, escapeNoise, ...branch } };
  },
  /** The basis (dims, k), offset (dims,) float32, escape noise (e, dims) and branch escape noise (b, w), w ≤ dims,
   * float16, all finite; the escapes (e,) and branch escapes (b,) int32, each strictly increasing inside the tile,
   * none in both (the coefficients were decoded to their stated shape). */
  checkNoise(tile, noise, pixels, dims, k) {
    const what = `bundle: tile ${tile}`, basis = noise.basis;
    for (const [name, indices] of [["escapes", basis.escapes], ["branch escapes", basis.branchEscapes]]) {
      if (indices.shape.length !== 1 || indices.dtype !== "int32") {
        throw new UserError(`${what} ${name} are ${indices.dtype} [${indices.shape}], expected int32 with one dimension`,
          { code: "compact.escapes_type", tile, part: name, dtype: indices.dtype, shape: indices.shape });
      }
      const v = indices.values;
      if (v.length && (v[0] < 0 || v[v.length - 1] >= pixels || v.some((x, j) => j > 0 && x <= v[j - 1]))) {
        throw new UserError(`${what} ${name} must be strictly increasing pixel indices inside the tile`,
          { code: "compact.escapes_order", tile, part: name });
      }
    }
    const e = basis.escapes.values, escaped = new Set(e);
    if (basis.branchEscapes.values.some((p) => escaped.has(p))) {
      throw new UserError(`${what}: a pixel is both an escape and a branch escape`, { code: "compact.escape_twice", tile });
    }
    const branchShape = basis.branchEscapeNoise.shape, width = branchShape.length === 2 ? branchShape[1] : -1;
    if (!(width >= 0 && width <= dims)) {
      throw new UserError(`${what} branch escape noise is [${branchShape}], expected [b, w] with w ≤ ${dims}`,
        { code: "compact.branch_width", tile, shape: branchShape, dims });
    }
    for (const [name, value, want, dtype] of [["basis", basis.basis, [dims, k], "float32"], ["offset", basis.offset, [dims], "float32"],
      ["escape noise", basis.escapeNoise, [e.length, dims], "float16"],
      ["branch escape noise", basis.branchEscapeNoise, [basis.branchEscapes.values.length, width], "float16"]]) {
      if (!sameShape(value.shape, want) || value.dtype !== dtype) {
        throw new UserError(`${what} ${name} is ${value.dtype} [${value.shape}], expected ${dtype} [${want}]`,
          { code: "compact.tensor_shape", tile, part: name, dtype: value.dtype, shape: value.shape, expected_dtype: dtype,
            expected_shape: want });
      }
      if (!allFinite(value.values)) throw new UserError(`${what} ${name} holds NaN or Inf`, { code: "compact.not_finite", tile, part: name });
    }
  },
  loaded(noise) {
    const b = noise.basis;
    noise.basis = { basis: b.basis.values, offset: b.offset.values, scale: b.scale, escapes: b.escapes.values,
      escapeNoise: widened(b.escapeNoise.values), branchEscapes: b.branchEscapes.values,
      branchEscapeNoise: widened(b.branchEscapeNoise.values), branchWidth: b.branchEscapeNoise.shape[1] };
  },
  /** Escaped and branch-escaped pixels renumbered from the chunk's first. */
  chunk(tile, bundle, start, stop) {
    const dims = bundle.noiseDims, k = bundle.coefficients, basis = tile.noise.basis, width = basis.branchWidth;
    const [escapes, escapeNoise] = escapesIn(basis.escapes, basis.escapeNoise, dims, start, stop);
    const [branchEscapes, branchEscapeNoise] = escapesIn(basis.branchEscapes, basis.branchEscapeNoise, width, start, stop);
    return { layout: this.name, coefficients: tile.noise.coefficients.slice(start * k, stop * k), k, dims,
      basis: { basis: basis.basis, offset: basis.offset, scale: basis.scale, escapes, escapeNoise, branchEscapes,
        branchEscapeNoise, branchWidth: width } };
  },
  rows(chunk) { return { values: expandCoefficients(chunk.coefficients, chunk.k, chunk.basis), perSample: 1, dims: chunk.dims }; },
};

/** The pixels of `indices` (strictly increasing) in start..stop, renumbered from start, and their rows of `noise`
 * (width values each). -> [Int32Array, Float32Array]. */
function escapesIn(indices, noise, width, start, stop) {
  const inside = [];
  for (let e = 0; e < indices.length; e++) if (indices[e] >= start && indices[e] < stop) inside.push(e);
  const rows = new Float32Array(inside.length * width);
  inside.forEach((e, i) => rows.set(noise.subarray(e * width, (e + 1) * width), i * width));
  return [Int32Array.from(inside, (e) => indices[e] - start), rows];
}

export const LAYOUTS = {
  ray: { ...VECTOR, name: "ray", dtypes: ["float16", "float32"] },
  sample: { ...VECTOR, name: "sample", dtypes: ["float32", "float16"], maxSamples: MAX_SAMPLES_PER_RAY,
    vectorsPerRay: (nSamples) => nSamples, storedShape: (h, w, nSamples, perVector) => [h, w, nSamples, perVector] },
  compact: { ...COMPACT, name: "compact", dtypes: ["int16", "int8"] },
};

/** layout_named: the layout of this name, refusing one not among those allowed (a bundle format's). */
export function layoutNamed(name, among = Object.keys(LAYOUTS)) {
  if (!among.includes(name)) {
    throw new UserError(`bundle: unknown noise layout ${show(name, 40)} (expected one of ${among.join(", ")})`,
      { code: "bundle.noise_layout", layout: cut(name), expected: among });
  }
  return LAYOUTS[name];
}

/** A chunk record's float32 noise (its layout's `rows`). */
export function chunkRows(chunk) { return LAYOUTS[chunk.layout].rows(chunk); }
