// float32 arithmetic numpy's BLAS (OpenBLAS's sgemm on FMA hardware) performs: a fused multiply-add rounded once
// to float32. JavaScript has no fma; a float32 product is exact in float64, and the sum is rounded to odd in
// float64 (two-sum error folded into the last bit), which makes the one rounding to float32 correct.

const buffer = new DataView(new ArrayBuffer(8));

function nextToward(x, direction) { // the float64 next to x toward the sign of direction
  buffer.setFloat64(0, x);
  let bits = buffer.getBigUint64(0);
  if (x === 0) return direction > 0 ? Number.MIN_VALUE : -Number.MIN_VALUE;
  bits += (x > 0) === (direction > 0) ? 1n : -1n;
  buffer.setBigUint64(0, bits);
  return buffer.getFloat64(0);
}

/** fmaf(a, b, c) for float32 a, b, c: a·b + c rounded once to float32. */
export function fmaf32(a, b, c) {
  const p = a * b; // exact: 24 + 24 bits
  const s = p + c;
  const bb = s - p;
  const err = (p - (s - bb)) + (c - bb); // two-sum: s + err == p + c exactly
  if (err === 0 || !Number.isFinite(s)) return Math.fround(s);
  buffer.setFloat64(0, s);
  const odd = (buffer.getUint32(4) & 1) === 1;
  return Math.fround(odd ? s : nextToward(s, err));
}
