// Mirrors runtime/fields/nerfacto.py: the `nerfacto` field kind, nerfstudio's nerfacto field and its proposal
// networks as nerfstudio renders them, node for node and constant for constant. Position: nerfstudio's L∞ scene
// contraction, then u = (x + 2)/4, points off the open unit cube moved to 0 with σ = 0 (the selector); u feeds a hash
// grid (src/fields/hashgrid.js) of the run's implementation: `tcnn` (cell of scale·u + 0.5, dense levels where they
// fit) or `torch` (cell of scale·u, every level hashed), the float32 scales stored per level. Direction: SH of degree
// ≤ 4 in tiny-cuda-nn's convention (`tcnn`), or nerfstudio's torch SH, the polynomial at (d + 1)/2 with the odd-m
// rows negated (`torch`). σ = density_scale·exp(min(raw, 30))·selector; colour as the hash grid's. Proposal networks:
// their own grid on the same u and a ReLU MLP to one raw density, σ as above, outputs sigma_proposal0, … (no noise);
// none for nerfstudio's instant-ngp, whose sampler is nerfacc's occupancy grid.
//
// Float32 constants are numpy's to the bit: the scales, JSON floats, are rounded through float32 (Math.fround) as the
// Python check rounds them, density.scale is float32(density_scale), the torch SH's signs multiply the float32 matrix.

import { UserError, cut } from "../errors.js";
import {
  MAX_FIELD_WIDTH, MAX_GRID_RESOLUTION, MAX_HASH_FEATURES, MAX_HASH_LEVELS, MAX_HASH_RESOLUTION, MAX_LOG2_TABLE, MAX_PROPOSAL_NETWORKS,
  MAX_SAMPLES_PER_RAY, MAX_TABLE_VALUES, checkedFloat, checkedInt, checkedList,
} from "../limits.js";
import { proposalOutput } from "../graph.js";
import { hasExactly, segment } from "./index.js";
import {
  DENSITY_EXPONENT_CAP, checkedMlps, fieldMlps, float32, gridAxes, int64, interpolatedFeatures, layoutLevels,
  sphericalHarmonics,
} from "./hashgrid.js";

const IMPLEMENTATIONS = ["tcnn", "torch"];
const KEYS = ["kind", "implementation", "features", "log2_table", "scales", "density_hidden", "geo_features", "sh_degree",
  "colour_hidden", "colour_layers", "density_scale", "proposals", "sampler"];
const PROPOSAL_KEYS = ["features", "log2_table", "scales", "hidden"];
const SAMPLER_KEYS = ["proposal_samples", "samples", "histogram_padding", "near", "far"];
const GRID_SAMPLER_KEYS = ["step", "cone_angle", "near", "far", "levels", "resolution", "aabb", "occupancy"];
const MAX_GRID_LEVELS = 8; // nerfacc's cascades (nerfstudio's instant-ngp: 4)
// nerfstudio's torch SH (nerfstudio.utils.spherical_harmonics) against tiny-cuda-nn's: odd-m rows negated
const TORCH_SH_SIGNS = [1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1];
const f32 = Math.fround;
const exactly = (keys) => [...keys].sort().join(", ");

/** grid_layout: the level layout of a grid of this implementation at these (float32) scales. */
export const gridLayout = (implementation, scales, log2Table) => layoutLevels(scales, log2Table, implementation === "torch");

const cellOffset = (implementation) => (implementation === "tcnn" ? 0.5 : 0.0);

/** checked_grid: a grid's features, log2_table and float32 scales (one per level), within the caps. */
function checkedGrid(config, implementation, what) {
  const scales = checkedList(config.scales, `${what} scales`, null, MAX_HASH_LEVELS, { code: "field.scales" });
  if (!scales.length) throw new UserError(`the ${what}'s grid needs at least one level`, { code: "field.no_levels", network: what });
  const lowest = implementation === "torch" ? 1.0 : 0.0;
  const values = scales.map((v) => f32(checkedFloat(v, `${what} scales`, lowest, BigInt(MAX_HASH_RESOLUTION - 2),
    { code: "field.scales" })));
  if (values.some((finer, l) => l > 0 && finer < values[l - 1])) {
    throw new UserError(`the ${what}'s scales must not decrease from level to level`, // dense levels come first
      { code: "field.scales_decrease", network: what });
  }
  return { features: checkedInt(config.features, `${what} features`, 1, MAX_HASH_FEATURES, { code: "field.features" }),
    log2_table: checkedInt(config.log2_table, `${what} log2_table`, 3, MAX_LOG2_TABLE, { code: "field.log2_table" }),
    scales: values };
}

function checkedProposal(config, implementation, what) {
  if (!hasExactly(config, PROPOSAL_KEYS)) {
    throw new UserError(`the ${what} must have exactly ${exactly(PROPOSAL_KEYS)}`, { code: "field.proposal_keys", network: what });
  }
  return { ...checkedGrid(config, implementation, what),
    hidden: checkedInt(config.hidden, `${what} hidden`, 1, MAX_FIELD_WIDTH, { code: "field.width" }) };
}

/** checked_sampler: samples per proposal stage (one per network), the field's samples, the PDF's histogram padding,
 * the ray interval of ordinary renders. */
function checkedSampler(config, proposals, what) {
  if (!hasExactly(config, SAMPLER_KEYS)) {
    throw new UserError(`the ${what} network's sampler must have exactly ${exactly(SAMPLER_KEYS)}`,
      { code: "field.sampler_keys", network: what });
  }
  const stages = checkedList(config.proposal_samples, `${what} proposal_samples`, proposals, undefined,
    { code: "field.proposal_samples" });
  const near = checkedFloat(config.near, `${what} sampler near`, 0.0, 1e9, { code: "field.sampler_near" });
  const far = checkedFloat(config.far, `${what} sampler far`, 0.0, 1e9, { code: "field.sampler_far" });
  if (!(near < far)) {
    throw new UserError(`the ${what} network's sampler needs near < far, got ${near}, ${far}`,
      { code: "field.near_far", network: what, near, far });
  }
  return {
    proposal_samples: stages.map((n) => checkedInt(n, `${what} proposal_samples`, 1, MAX_SAMPLES_PER_RAY,
      { code: "field.proposal_samples" })),
    samples: checkedInt(config.samples, `${what} sampler samples`, 1, MAX_SAMPLES_PER_RAY, { code: "field.sampler_samples" }),
    histogram_padding: checkedFloat(config.histogram_padding, `${what} histogram_padding`, 0.0, 1.0,
      { code: "field.histogram_padding" }),
    near, far,
  };
}

/** checked_grid_sampler: nerfstudio's instant-ngp sampler (nerfacc's occupancy grid, rendered by the Python runtime's
 * runtime/grid_marching.py): step, cone angle, ray interval, levels, cells per side, scene box, occupancy (one bit per
 * cell, base64), its size checked without decoding it. */
function checkedGridSampler(config, what) {
  if (!hasExactly(config, GRID_SAMPLER_KEYS)) {
    throw new UserError(`the ${what} network's grid sampler must have exactly ${exactly(GRID_SAMPLER_KEYS)}`,
      { code: "field.sampler_keys", network: what });
  }
  const near = checkedFloat(config.near, `${what} sampler near`, 0.0, 1e9, { code: "field.sampler_near" });
  const far = checkedFloat(config.far, `${what} sampler far`, 0.0, 1e9, { code: "field.sampler_far" });
  if (!(near < far)) {
    throw new UserError(`the ${what} network's sampler needs near < far, got ${near}, ${far}`,
      { code: "field.near_far", network: what, near, far });
  }
  const levels = checkedInt(config.levels, `${what} grid levels`, 1, MAX_GRID_LEVELS, { code: "field.grid_levels" });
  const resolution = checkedInt(config.resolution, `${what} grid resolution`, 1, MAX_GRID_RESOLUTION,
    { code: "field.grid_resolution" });
  const aabb = checkedList(config.aabb, `${what} grid aabb`, 6, undefined, { code: "field.grid_aabb" })
    .map((v) => checkedFloat(v, `${what} grid aabb`, -1e9, 1e9, { code: "field.grid_aabb" }));
  if (![0, 1, 2].every((i) => aabb[i] < aabb[i + 3])) {
    throw new UserError(`the ${what} network's grid aabb must have min < max on every axis`, { code: "field.grid_aabb", network: what });
  }
  if (levels * resolution ** 3 > MAX_GRID_RESOLUTION ** 3) {
    throw new UserError(`the ${what} network's grid holds ${levels} x ${resolution}^3 cells, more than ${MAX_GRID_RESOLUTION}^3`,
      { code: "field.grid_cells", network: what });
  }
  const needed = Math.ceil(levels * resolution ** 3 / 8);
  const text = config.occupancy;
  const valid = typeof text === "string" && text.length === 4 * Math.ceil(needed / 3) && /^[A-Za-z0-9+/]*={0,2}$/.test(text)
    && (text.length / 4) * 3 - (text.endsWith("==") ? 2 : text.endsWith("=") ? 1 : 0) === needed;
  if (!valid) {
    throw new UserError(`the ${what} network's grid occupancy must be ${needed} bytes in base64 (levels x resolution^3 bits)`,
      { code: "field.grid_occupancy", network: what, needed });
  }
  return {
    step: checkedFloat(config.step, `${what} sampler step`, 1e-9, 1e9, { code: "field.sampler_step" }),
    cone_angle: checkedFloat(config.cone_angle, `${what} cone angle`, 0.0, 1.0, { code: "field.cone_angle" }),
    near, far, levels, resolution, aabb, occupancy: text,
  };
}

/** contracted_unit: nerfstudio's L∞ scene contraction of `points`, then (x + 2)/4, points off the open unit cube at 0.
 * -> [the grid input (n, 3), the selector (n, 1) float, 1 inside]. */
function contractedUnit(builder, prefix) {
  const name = `${prefix}.contraction`;
  const norm = builder.add("ReduceMax", [builder.add("Abs", ["points"], `${name}.abs`), int64(builder, "axes.1", [1], [1])],
    `${name}.norm`, { keepdims: 1 });
  const [one, two] = [1, 2].map((v) => float32(builder, `float.${v}`, [1], [v]));
  const outer = builder.add("Mul", [builder.add("Sub", [two, builder.add("Div", [one, norm], `${name}.inverse`)], `${name}.radius`),
    builder.add("Div", ["points", norm], `${name}.direction`)], `${name}.outer`);
  const contracted = builder.add("Where", [builder.add("Less", [norm, one], `${name}.inner`), "points", outer], `${name}.contracted`);
  const unit = builder.add("Div", [builder.add("Add", [contracted, two], `${name}.shifted`), float32(builder, "float.4", [1], [4])],
    `${name}.unit`);
  const within = builder.add("And", [builder.add("Greater", [unit, float32(builder, "float.0", [1], [0])], `${name}.above`),
    builder.add("Less", [unit, one], `${name}.below`)], `${name}.within`);
  const selector = builder.add("ReduceMin", [builder.add("Cast", [within], `${name}.within_float`, { to: 1 }),
    int64(builder, "axes.1", [1], [1])], `${name}.selector`, { keepdims: 1 });
  return [builder.add("Mul", [unit, selector], `${name}.selected`), selector];
}

/** field_sh: the direction encoding of the run's implementation. */
function fieldSh(builder, config) {
  if (config.implementation === "tcnn") return sphericalHarmonics(builder, config.sh_degree);
  const two = float32(builder, "float.2", [1], [2]);
  const halved = builder.add("Div", [builder.add("Add", ["viewdirs", float32(builder, "float.1", [1], [1])], "viewdirs.plus1"),
    two], "viewdirs.halved");
  return sphericalHarmonics(builder, config.sh_degree, halved, TORCH_SH_SIGNS);
}

/** activated_density: σ = density_scale·exp(min(raw, cap))·selector, squeezed to (n,). */
function activatedDensity(builder, prefix, config, raw, selector, output) {
  const cap = float32(builder, "density.exponent_cap", [1], [DENSITY_EXPONENT_CAP]);
  const exp = builder.add("Exp", [builder.add("Min", [raw, cap], `${prefix}.capped_density`)], `${prefix}.exp_density`);
  const scaled = builder.add("Mul", [float32(builder, "density.scale", [1], [f32(config.density_scale)]), exp],
    `${prefix}.scaled_density`);
  builder.add("Squeeze", [builder.add("Mul", [scaled, selector], `${prefix}.sigma`), int64(builder, "axes.1", [1], [1])], output);
}

/** A grid of the run's implementation on the contracted points -> (n, L·F). */
const gridOn = (builder, name, unit, implementation, grid, axes) => interpolatedFeatures(builder, `${name}.grid`,
  `${name}.table`, unit, gridLayout(implementation, grid.scales, grid.log2_table), grid.features, grid.log2_table, axes,
  cellOffset(implementation));

export const NERFACTO = {
  name: "nerfacto",
  opset: 18,

  checked(config, what) {
    if (!hasExactly(config, KEYS)) {
      throw new UserError(`the ${what} network's architecture must have exactly ${exactly(KEYS)}`,
        { code: "field.keys", network: what, kind: this.name });
    }
    const implementation = config.implementation;
    if (typeof implementation !== "string" || !IMPLEMENTATIONS.includes(implementation)) {
      throw new UserError(`the ${what} network's implementation must be one of ${IMPLEMENTATIONS.join(", ")}`,
        { code: "field.implementation", network: what,
          implementation: typeof implementation === "string" ? cut(implementation) : null });
    }
    const checked = { kind: this.name, implementation, ...checkedGrid(config, implementation, `${what} network`),
      ...checkedMlps(config, what),
      density_scale: checkedFloat(config.density_scale, `${what} density_scale`, 1e-12, 1e12, { code: "field.density_scale" }) };
    const proposals = checkedList(config.proposals, `${what} proposals`, null, MAX_PROPOSAL_NETWORKS, { code: "field.proposals" });
    checked.proposals = proposals.map((proposal, i) => checkedProposal(proposal, implementation, `${what} proposal network ${i}`));
    checked.sampler = proposals.length ? checkedSampler(config.sampler, proposals.length, what)
      : checkedGridSampler(config.sampler, what);
    const values = [checked, ...checked.proposals].reduce((sum, grid) => (
      sum + gridLayout(implementation, grid.scales, grid.log2_table).totalRows * grid.features), 0);
    if (values > MAX_TABLE_VALUES) {
      throw new UserError(`the ${what} network's tables hold ${values} values, more than ${MAX_TABLE_VALUES}`,
        { code: "field.table_values", network: what, values, most: MAX_TABLE_VALUES });
    }
    return checked;
  },

  segments(config) {
    return [segment("position", config.scales.length * config.features), segment("direction", config.sh_degree ** 2)];
  },

  /** The sampler of ordinary renders: one proposal stage per proposal network (outputs sigma_proposal0, …); null for
   * nerfstudio's instant-ngp (no proposal networks: its sampler is nerfacc's occupancy grid). */
  proposalSampler(config) {
    return Array.isArray(config.proposals) && !config.proposals.length ? null : config.sampler;
  },

  build(builder, prefix, config, rgb, sigma) {
    const axes = gridAxes(builder);
    const [unit, selector] = contractedUnit(builder, prefix);
    const features = gridOn(builder, prefix, unit, config.implementation, config, axes);
    const density = fieldMlps(builder, prefix, config, this.segments(config), features, fieldSh(builder, config), rgb);
    activatedDensity(builder, prefix, config, density, selector, sigma);
    for (const [i, proposal] of config.proposals.entries()) {
      const name = `${prefix}.proposals.${i}`;
      const grid = gridOn(builder, name, unit, config.implementation, proposal, axes);
      const dims = proposal.scales.length * proposal.features;
      const hidden = builder.add("Relu", [builder.linear(name, "linears.0", grid, dims, proposal.hidden)], `${name}.hidden`);
      const raw = builder.linear(name, "linears.1", hidden, proposal.hidden, 1);
      activatedDensity(builder, name, config, raw, selector, proposalOutput(i));
    }
  },
};
