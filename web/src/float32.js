// float32 arithmetic numpy's BLAS (OpenBLAS's sgemm on FMA hardware) performs: a fused multiply-add rounded once
// to float32. JavaScript has no fma; a float32 product is exact in float64, and the float64 sum s is off the
// exact sum by err (two-sum). Rounding s to float32 is then correct unless s lies exactly halfway between two
// float32 values, where err says which side the exact sum is on.

/** fmaf(a, b, c) for float32 a, b, c: a·b + c rounded once to float32. */
export function fmaf32(a, b, c) {
  const p = a * b; // exact: 24 + 24 bits
  const s = p + c;
  const r = Math.fround(s);
  if (r === s) return r; // also ±Infinity; NaN falls through to the next test
  const other = 2 * s - r; // r's float32 neighbour across s, if s is their midpoint
  if (Math.fround(other) !== other) return r; // s is no midpoint: r is the exact sum's nearest float32
  const bb = s - p;
  const err = (p - (s - bb)) + (c - bb); // two-sum: s + err == p + c exactly
  if (err === 0) return r; // the exact sum is the midpoint: Math.fround broke the tie to even, as fmaf does
  return (err > 0) === (other > r) ? other : r;
}
