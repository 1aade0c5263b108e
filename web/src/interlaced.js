// Mirrors runtime/interlaced.py: a format 4 compact tile's stream holds each coefficient's zigzag difference from
// its interlaced prediction (roots every ROOT_SPACING pixels of every ROOT_SPACING-th row, each from the root to its
// left, the first of a row from the one above; then for spacings 8, 4, 2 an across pass, the floored mean of the
// decoded pixels d to the left and right, and a down pass, of those d above and below), each band of bandRows rows
// on its own. Integer arithmetic only.

const ROOT_SPACING = 8;

/** decode: zigzag codes (Int16Array/Int8Array, h·w·k row-major) in bands of bandRows rows -> the coefficients, a new
 * array of that type. */
export function decodeInterlaced(codes, height, width, k, bandRows) {
  const out = new codes.constructor(codes.length);
  for (let y = 0; y < height; y += bandRows) {
    const from = y * width * k, to = Math.min(y + bandRows, height) * width * k;
    decodeBand(codes.subarray(from, to), out.subarray(from, to), Math.min(bandRows, height - y), width, k);
  }
  return out;
}

/** decode_band: one band's codes -> its coefficients, written into `out` (same length and type). */
function decodeBand(codes, out, height, width, k) {
  const bits = codes instanceof Int16Array ? 16 : 8, shift = 32 - bits, mask = (1 << bits) - 1;
  const wrap = (v) => (v << shift) >> shift;
  const difference = (i) => { const u = codes[i] & mask; return (u >>> 1) ^ -(u & 1); };
  const at = (y, x) => (y * width + x) * k;
  for (let y = 0; y < height; y += ROOT_SPACING) {
    for (let x = 0; x < width; x += ROOT_SPACING) {
      const p = at(y, x), from = x > 0 ? at(y, x - ROOT_SPACING) : y > 0 ? at(y - ROOT_SPACING, 0) : -1;
      for (let c = 0; c < k; c++) out[p + c] = wrap((from < 0 ? 0 : out[from + c]) + difference(p + c));
    }
  }
  const fill = (y, x, before, after) => {
    const p = at(y, x);
    for (let c = 0; c < k; c++) out[p + c] = wrap(((out[before + c] + out[after + c]) >> 1) + difference(p + c));
  };
  for (let spacing = ROOT_SPACING; spacing > 1; spacing /= 2) {
    const d = spacing / 2;
    for (let y = 0; y < height; y += spacing) {
      for (let x = d; x < width; x += spacing) fill(y, x, at(y, x - d), x + d < width ? at(y, x + d) : at(y, x - d));
    }
    for (let y = d; y < height; y += spacing) {
      for (let x = 0; x < width; x += d) fill(y, x, at(y - d, x), y + d < height ? at(y + d, x) : at(y - d, x));
    }
  }
}
