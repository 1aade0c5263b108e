// Mirrors runtime/compositing.py (paper eq. 2): σ·Δ capped at MAX_OPTICAL_DEPTH, transmittance
// exp(−exclusive cumsum), weights T·(1 − exp(−σΔ)), Ĉ = Σ w c + (1 − Σ w)·background; and runtime/images.py's
// to_uint8 (round half up). float32 throughout; numpy's sums are reproduced in its order (pairwiseSum).
// exp and expm1 are Math's (float64) rounded to float32, numpy's are its float32 SIMD exp and libm's expm1f:
// they may differ in the last bit (measured by the golden colours in web/test).

const f32 = Math.fround;
export const MAX_OPTICAL_DEPTH = 1e4;
const CAP = f32(MAX_OPTICAL_DEPTH);

/** numpy's float32 add.reduce over a contiguous run (pairwise_sum: 8 accumulators per 128-block). */
export function pairwiseSum(a, start, n, stride = 1) {
  if (n < 8) {
    let res = 0; // numpy starts from -0.0 for float, same value for sums here
    for (let i = 0; i < n; i++) res = f32(res + a[start + i * stride]);
    return n === 0 ? 0 : res;
  }
  if (n <= 128) {
    const r = new Array(8);
    for (let j = 0; j < 8; j++) r[j] = a[start + j * stride];
    let i;
    for (i = 8; i < n - (n % 8); i += 8) {
      for (let j = 0; j < 8; j++) r[j] = f32(r[j] + a[start + (i + j) * stride]);
    }
    let res = f32(f32(f32(r[0] + r[1]) + f32(r[2] + r[3])) + f32(f32(r[4] + r[5]) + f32(r[6] + r[7])));
    for (; i < n; i++) res = f32(res + a[start + i * stride]);
    return res;
  }
  let n2 = Math.floor(n / 2);
  n2 -= n2 % 8;
  return f32(pairwiseSum(a, start, n2, stride) + pairwiseSum(a, start + n2 * stride, n - n2, stride));
}

export function opticalDepth(sigma, delta) {
  return Math.min(f32(sigma * delta), CAP);
}

/** render_weights then composite, for m rays of S samples: sigmas, deltas (m·S), rgbs (m·S·3) -> colours (m·3). */
export function compositeRays(sigmas, rgbs, deltas, m, S, background) {
  const colors = new Float32Array(m * 3);
  const depths = new Float32Array(S), weights = new Float32Array(S);
  const bg = background.map(f32);
  for (let r = 0; r < m; r++) {
    let cumulative = 0;
    for (let s = 0; s < S; s++) depths[s] = opticalDepth(sigmas[r * S + s], deltas[r * S + s]);
    for (let s = 0; s < S; s++) {
      const T = f32(Math.exp(-cumulative));
      weights[s] = f32(T * f32(-Math.expm1(-depths[s])));
      cumulative = f32(cumulative + depths[s]);
    }
    const opacity = pairwiseSum(weights, 0, S);
    const rest = f32(1.0 - opacity);
    for (let c = 0; c < 3; c++) {
      let color = 0;
      for (let s = 0; s < S; s++) color = f32(color + f32(weights[s] * rgbs[(r * S + s) * 3 + c]));
      colors[r * 3 + c] = f32(color + f32(rest * bg[c]));
    }
  }
  return colors;
}

/** to_uint8: [0, 1] floats to 8-bit by rounding half up. */
export function toUint8(image) {
  const out = new Uint8Array(image.length);
  for (let i = 0; i < image.length; i++) {
    const v = Math.floor(f32(f32(image[i] * 255.0) + 0.5));
    out[i] = v < 0 ? 0 : v > 255 ? 255 : v;
  }
  return out;
}
