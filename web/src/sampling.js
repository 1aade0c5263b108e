// Mirrors runtime/sampling.py: sample positions (np.linspace in float64, then float32), o + t·d, intervals with
// the last one LAST_DELTA, all in float32 as numpy computes them.

import { UserError } from "./errors.js";
import { MAX_SAMPLES_PER_RAY, checkedFloat, checkedInt } from "./limits.js";

const f32 = Math.fround;
export const LAST_DELTA = 1e10;

/** SamplingConfig (checked) from metadata. */
export function samplingFromDict(data) {
  const keys = data && typeof data === "object" && !Array.isArray(data) ? Object.keys(data).sort() : null;
  if (!keys || keys.join() !== "far,n_samples,near") throw new UserError("sampling must be an object with near, far and n_samples", { code: "sampling.not_object" });
  return samplingConfig(checkedFloat(data.near, "sampling near", -Infinity, Infinity, { code: "sampling.near" }),
    checkedFloat(data.far, "sampling far", -Infinity, Infinity, { code: "sampling.far" }),
    checkedInt(data.n_samples, "sampling n_samples", 1, MAX_SAMPLES_PER_RAY, { code: "sampling.n_samples" }));
}

export function samplingConfig(near, far, nSamples) {
  if (!(Number.isFinite(near) && Number.isFinite(far) && near >= 0 && near < far)) {
    throw new UserError(`sampling needs 0 <= near < far, got near=${near}, far=${far}`, { code: "sampling.bad_range", near, far });
  }
  if (!(nSamples >= 1 && nSamples <= MAX_SAMPLES_PER_RAY)) {
    throw new UserError(`sampling needs 1 to ${MAX_SAMPLES_PER_RAY} samples per ray, got ${nSamples}`,
      { code: "sampling.bad_count", n_samples: nSamples, most: MAX_SAMPLES_PER_RAY });
  }
  return { near, far, nSamples };
}

/** sample_positions: (n_samples,) float32, near and far included (numpy's linspace). */
export function samplePositions(config) {
  const { near, far, nSamples } = config;
  if (nSamples === 1) return Float32Array.of(near);
  const t = new Float32Array(nSamples);
  const step = (far - near) / (nSamples - 1);
  for (let i = 0; i < nSamples; i++) t[i] = i * step + near;
  t[nSamples - 1] = far;
  return t;
}

/** sample_along for rays start..stop of a batch: points (m, S, 3) and deltas (m, S), float32. */
export function sampleAlong(rays, start, stop, tVals) {
  const m = stop - start, S = tVals.length;
  const points = new Float32Array(m * S * 3), deltas = new Float32Array(m * S);
  const last = f32(LAST_DELTA);
  const steps = new Float32Array(S);
  for (let s = 0; s < S - 1; s++) steps[s] = f32(tVals[s + 1] - tVals[s]);
  steps[S - 1] = last;
  for (let r = 0; r < m; r++) {
    const k = 3 * (start + r);
    const ox = rays.origins[k], oy = rays.origins[k + 1], oz = rays.origins[k + 2];
    const dx = rays.directions[k], dy = rays.directions[k + 1], dz = rays.directions[k + 2];
    const norm = f32(Math.sqrt(f32(f32(f32(dx * dx) + f32(dy * dy)) + f32(dz * dz))));
    for (let s = 0; s < S; s++) {
      const t = tVals[s], at = (r * S + s) * 3;
      points[at] = f32(ox + f32(t * dx));
      points[at + 1] = f32(oy + f32(t * dy));
      points[at + 2] = f32(oz + f32(t * dz));
      deltas[r * S + s] = f32(steps[s] * norm);
    }
  }
  return { points, deltas };
}
