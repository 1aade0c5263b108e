// Mirrors runtime/fields/hashgrid.py: the `hashgrid` field kind, an Instant-NGP field with tiny-cuda-nn's hash-grid
// and SH conventions, node for node and constant for constant. Position: x normalised into the aabb and clamped to
// [0, 1]³; per level a scale, the cell of scale·x + 0.5, its 8 corners' rows (dense levels: the lower corner's
// index plus a constant per corner; hashed levels: the XOR of one primed coordinate per axis), their features
// trilinearly interpolated. Direction: real spherical harmonics up to `sh_degree`, one matrix over the monomials of
// degree ≤ 3. Noise is added to [features ‖ SH]; density exp(min(raw, 30)) from a ReLU MLP, colour sigmoid from
// another. Opset 18 (BitwiseXor, BitwiseAnd).
//
// Float32 constants are numpy's values to the bit (Math.fround wherever numpy rounds); the level scales are double
// products rounded once to float32 (level_scales), so every machine and this port agree. The interpolation
// (interpolatedFeatures, with its cell offset), the level layout (layoutLevels), the SH (sphericalHarmonics, of any
// directions, rows optionally negated) and the two MLPs (checkedMlps, fieldMlps) are shared with the nerfacto kind
// (src/fields/nerfacto.js), as runtime/fields/hashgrid.py shares them.

import { UserError } from "../errors.js";
import {
  MAX_FIELD_DEPTH, MAX_FIELD_WIDTH, MAX_HASH_FEATURES, MAX_HASH_LEVELS, MAX_HASH_RESOLUTION, MAX_LOG2_TABLE,
  MAX_TABLE_VALUES, checkedFloat, checkedInt, checkedList,
} from "../limits.js";
import { hasExactly, segment } from "./index.js";

const KEYS = ["kind", "levels", "features", "log2_table", "base_resolution", "per_level_scale", "density_hidden",
  "geo_features", "sh_degree", "colour_hidden", "colour_layers", "aabb"];
const PRIMES = [1, 2654435761, 805459861];
export const DENSITY_EXPONENT_CAP = 30.0;
const MAX_SH_DEGREE = 4;
const DEGREE2 = [[0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]; // xx xy xz yy yz zz
const DEGREE3 = [[0, 0, 0, 1, 1, 2, 3, 3, 4, 5], [0, 1, 2, 1, 2, 2, 1, 2, 2, 2]]; // xxx xxy xxz xyy xyz xzz yyy yyz yzz zzz
const MONOMIALS = 19;
const f32 = Math.fround;
// a constant of these values (nested rows flattened, numpy's C order)
export const int64 = (builder, name, shape, values) => builder.constant(name, "int64", shape, values.flat());
export const float32 = (builder, name, shape, values) => builder.constant(name, "float32", shape, values.flat());

/** The real spherical harmonics of degree 4 (tiny-cuda-nn's order and signs) over the 19 monomials and a constant
 * term: SH(d) = M·m(d) + c, float64 products rounded to float32. -> rows of 19, 16 constants. */
export function shMatrix() {
  const matrix = Array.from({ length: 16 }, () => new Array(MONOMIALS).fill(0)), constant = new Array(16).fill(0);
  const [x, y, z, xx, xy, xz, yy, yz, zz, xxx, xxy, xxz, xyy, xyz, xzz, yyy, yyz, yzz, zzz] = Array.from({ length: MONOMIALS }, (_, i) => i);
  constant[0] = 0.28209479177387814;
  [matrix[1][y], matrix[2][z], matrix[3][x]] = [-0.48860251190291987, 0.48860251190291987, -0.48860251190291987];
  [matrix[4][xy], matrix[5][yz], matrix[7][xz]] = [1.0925484305920792, -1.0925484305920792, -1.0925484305920792];
  [matrix[6][zz], constant[6]] = [0.94617469575755997, -0.31539156525251999];
  [matrix[8][xx], matrix[8][yy]] = [0.54627421529603959, -0.54627421529603959];
  [matrix[9][xxy], matrix[9][yyy]] = [-3 * 0.59004358992664352, 0.59004358992664352];
  matrix[10][xyz] = 2.8906114426405538;
  [matrix[11][y], matrix[11][yzz]] = [0.45704579946446572, -5 * 0.45704579946446572];
  [matrix[12][zzz], matrix[12][z]] = [5 * 0.3731763325901154, -3 * 0.3731763325901154];
  [matrix[13][x], matrix[13][xzz]] = [0.45704579946446572, -5 * 0.45704579946446572];
  [matrix[14][xxz], matrix[14][yyz]] = [1.4453057213202769, -1.4453057213202769];
  [matrix[15][xxx], matrix[15][xyy]] = [-0.59004358992664352, 3 * 0.59004358992664352];
  return [matrix.map((row) => row.map(f32)), constant.map(f32)];
}

/** level_scales: scale_l = N_min·b^l − 1, b^l by repeated double products, rounded once to float32. */
function levelScales(levels, baseResolution, perLevelScale) {
  const scales = [];
  for (let l = 0, power = 1.0; l < levels; l++, power *= perLevelScale) scales.push(f32(baseResolution * power - 1.0));
  return scales;
}

/** grid_levels: tiny-cuda-nn's level layout of scales N_min·b^l − 1 (levelScales). */
export function gridLevels(levels, log2Table, baseResolution, perLevelScale) {
  return layoutLevels(levelScales(levels, baseResolution, perLevelScale), log2Table);
}

/** layout_levels: the tables of levels at these float32 scales, per level l: scale, vertices a side ceil(scale) + 1,
 * rows min(res³ rounded up to 8, 2^log2_table), first row, dense (1) where res³ fits the rows; or, `allHashed`
 * (nerfstudio's torch grid), 2^log2_table hashed rows every level. */
export function layoutLevels(scale, log2Table, allHashed = false) {
  const resolution = scale.map((s) => Math.ceil(s) + 1);
  const table = 2n ** BigInt(log2Table);
  const cells = resolution.map((r) => BigInt(r) ** 3n); // up to 2^60: exact as int64 is
  const rows = cells.map((c) => Number(allHashed || (c + 7n) / 8n * 8n >= table ? table : (c + 7n) / 8n * 8n));
  const offset = rows.map((_, l) => rows.slice(0, l).reduce((a, b) => a + b, 0));
  const dense = cells.map((c, l) => (!allHashed && c <= BigInt(rows[l]) ? 1 : 0));
  return { scale, resolution, rows, offset, dense, totalRows: rows.reduce((a, b) => a + b, 0) };
}

const configLevels = (config) => gridLevels(config.levels, config.log2_table, config.base_resolution, config.per_level_scale);

/** The 8 corners of a cell, corner i taking +1 on axis d where bit d of i is set. -> 8 rows of 3. */
const cornerOffsets = () => Array.from({ length: 8 }, (_, i) => [0, 1, 2].map((d) => (i >> d) & 1));

export const HASHGRID = {
  name: "hashgrid",
  opset: 18,

  checked(config, what) {
    if (!hasExactly(config, KEYS)) {
      throw new UserError(`the ${what} network's architecture must have exactly ${[...KEYS].sort().join(", ")}`,
        { code: "field.keys", network: what, kind: this.name });
    }
    const int = (key, low, high, code) => checkedInt(config[key], `${what} ${key}`, low, high, { code });
    const checked = {
      kind: this.name,
      levels: int("levels", 1, MAX_HASH_LEVELS, "field.levels"),
      features: int("features", 1, MAX_HASH_FEATURES, "field.features"),
      log2_table: int("log2_table", 3, MAX_LOG2_TABLE, "field.log2_table"),
      base_resolution: int("base_resolution", 1, MAX_HASH_RESOLUTION, "field.base_resolution"),
      per_level_scale: checkedFloat(config.per_level_scale, `${what} per_level_scale`, 1.0, 8.0, { code: "field.per_level_scale" }),
      ...checkedMlps(config, what),
      aabb: checkedList(config.aabb, "aabb", 6, undefined, { code: "field.aabb" })
        .map((v) => checkedFloat(v, `${what} aabb`, -1e9, 1e9, { code: "field.aabb" })),
    };
    if (![0, 1, 2].every((a) => checked.aabb[a] < checked.aabb[a + 3])) {
      throw new UserError(`the ${what} network's aabb must have min < max on every axis`, { code: "field.aabb_order", network: what });
    }
    const finest = checked.per_level_scale ** (checked.levels - 1) * checked.base_resolution;
    if (!Number.isFinite(finest) || finest > MAX_HASH_RESOLUTION) {
      throw new UserError(`the ${what} network's finest level has ${finest.toPrecision(6)} vertices a side, more than ${MAX_HASH_RESOLUTION}`,
        { code: "field.finest_resolution", network: what, levels: checked.levels, base_resolution: checked.base_resolution,
          per_level_scale: checked.per_level_scale, most: MAX_HASH_RESOLUTION });
    }
    const values = configLevels(checked).totalRows * checked.features;
    if (values > MAX_TABLE_VALUES) {
      throw new UserError(`the ${what} network's tables hold ${values} values, more than ${MAX_TABLE_VALUES}`,
        { code: "field.table_values", network: what, values, most: MAX_TABLE_VALUES });
    }
    return checked;
  },

  segments(config) {
    return [segment("position", config.levels * config.features), segment("direction", config.sh_degree ** 2)];
  },

  build(builder, prefix, config, rgb, sigma) {
    const features = gridFeatures(builder, prefix, config);
    const density = fieldMlps(builder, prefix, config, this.segments(config), features,
      sphericalHarmonics(builder, config.sh_degree), rgb);
    const cap = float32(builder, "density.exponent_cap", [1], [DENSITY_EXPONENT_CAP]);
    const capped = builder.add("Min", [density, cap], `${prefix}.capped_density`);
    builder.add("Squeeze", [builder.add("Exp", [capped], `${prefix}.sigma`), int64(builder, "axes.1", [1], [1])], sigma);
  },
};

/** checked_mlps: the widths of a hash-grid field's two MLPs and its SH degree, within the caps. */
export function checkedMlps(config, what) {
  const int = (key, low, high, code) => checkedInt(config[key], `${what} ${key}`, low, high, { code });
  const width = (key, low = 1) => int(key, low, MAX_FIELD_WIDTH, "field.width");
  return { density_hidden: width("density_hidden"), geo_features: width("geo_features", 0),
    sh_degree: int("sh_degree", 1, MAX_SH_DEGREE, "field.sh_degree"), colour_hidden: width("colour_hidden"),
    colour_layers: int("colour_layers", 1, MAX_FIELD_DEPTH, "field.colour_layers") };
}

/** field_mlps: noise on [grid features ‖ SH], the density MLP to [raw density ‖ geometric feature], the colour MLP
 * on [noisy SH ‖ geometric feature] to the sigmoid `rgb` output. -> the raw density (n, 1). */
export function fieldMlps(builder, prefix, config, [position, direction], features, sh, rgb) {
  const [grid, noisySh] = builder.noisyPair(features, sh, () => (
    int64(builder, `${prefix}.split.noise`, [2], [position.dims, direction.dims])));
  const hidden = builder.add("Relu", [builder.linear(prefix, "density_linears.0", grid, position.dims,
    config.density_hidden)], `${prefix}.density_hidden`);
  const trunk = builder.linear(prefix, "density_linears.1", hidden, config.density_hidden, 1 + config.geo_features);
  let density, h;
  if (config.geo_features) {
    const split = int64(builder, `${prefix}.split.trunk`, [2], [1, config.geo_features]);
    const [raw, geo] = builder.split(trunk, split, [`${prefix}.raw_density`, `${prefix}.geo`]);
    density = raw;
    h = builder.add("Concat", [noisySh, geo], `${prefix}.head`, { axis: 1 });
  } else [density, h] = [trunk, noisySh];
  let fanIn = direction.dims + config.geo_features;
  for (let i = 0; i < config.colour_layers; i++) {
    h = builder.add("Relu", [builder.linear(prefix, `colour_linears.${i}`, h, fanIn, config.colour_hidden)], `${prefix}.colour${i}`);
    fanIn = config.colour_hidden;
  }
  const rawRgb = builder.linear(prefix, `colour_linears.${config.colour_layers}`, h, fanIn, 3);
  builder.add("Sigmoid", [rawRgb], rgb);
  return density;
}

/** corner_grid: the 8 corners' combinations of per-axis pairs (n, L, 3, 2) (entry 0: the cell's lower vertex, 1:
 * its upper), axis d broadcast along its own dimension of (n, L, 2, 2, 2), corner i = 4·b_z + 2·b_y + b_x. -> the
 * three (n, L, ·, ·, ·) terms. */
function cornerGrid(builder, name, perAxis) {
  const terms = builder.split(perAxis, int64(builder, "split.3x1", [3], [1, 1, 1]), [`${name}.x`, `${name}.y`, `${name}.z`], 2);
  return [["x", [0, 0, 1, 1, 2]], ["y", [0, 0, 1, 2, 1]], ["z", [0, 0, 2, 1, 1]]].map(([axis, shape], d) => builder.add("Reshape",
    [terms[d], int64(builder, `shape.axis${d}`, [5], shape)], `${name}.${axis}5`));
}

/** The constant that reshapes (n, L, 2, 2, 2) corners to (n, L, 8). */
const cornersShape = (builder) => int64(builder, "shape.corners", [3], [0, 0, 8]);

/** dense_index: rows of the 8 corners on dense levels `span` ([first, end)): the lower corner's x + y·res + z·res²,
 * plus each corner's constant offset, modulo the level's rows. lower: (n, l, 3) int64 -> (n, l, 8). */
function denseIndex(builder, name, lower, levels, [first, end]) {
  const strides = levels.resolution.slice(first, end).map((r) => [1, r, r * r]);
  const base = builder.add("ReduceSum", [builder.add("Mul", [lower, int64(builder, `${name}.strides`, [end - first, 3], strides)],
    `${name}.strided`), int64(builder, "axes.2", [1], [2])], `${name}.base`, { keepdims: 1 });
  const cornerStrides = int64(builder, `${name}.corner_strides`, [end - first, 8], strides.map((stride) => cornerOffsets().map(
    (bits) => bits.reduce((sum, bit, d) => sum + bit * stride[d], 0))));
  return builder.add("Mod", [builder.add("Add", [base, cornerStrides], `${name}.unwrapped`),
    int64(builder, `${name}.rows`, [end - first, 1], levels.rows.slice(first, end))], `${name}.index`);
}

/** hashed_index: rows of the 8 corners on hashed levels: (x·1 ⊕ y·2654435761 ⊕ z·805459861) & (T − 1), each axis's
 * two primed vertices computed once. lower: (n, l, 3) int64 -> (n, l, 8). */
function hashedIndex(builder, name, lower, log2Table) {
  const vertices = builder.add("Add", [builder.add("Unsqueeze", [lower, int64(builder, "axes.3", [1], [3])], `${name}.lower4`),
    int64(builder, "grid.pair", [2], [0, 1])], `${name}.vertices`);
  const primed = builder.add("Mul", [vertices, int64(builder, "grid.primes", [3, 1], PRIMES)], `${name}.primed`); // (n, l, 3, 2)
  const [hx, hy, hz] = cornerGrid(builder, name, primed);
  return builder.add("Reshape", [builder.add("BitwiseAnd", [builder.add("BitwiseXor", [builder.add("BitwiseXor", [hx, hy],
    `${name}.hxy`), hz], `${name}.hxyz`), int64(builder, `${name}.mask`, [1], [2 ** log2Table - 1])], `${name}.masked`),
  cornersShape(builder)], `${name}.index`);
}

/** grid_axes: the axis constants a grid's nodes use, added before the grid's own constants (the file's order). */
export const gridAxes = (builder) => Object.fromEntries([1, 2, 3].map((k) => [k, int64(builder, `axes.${k}`, [1], [k])]));

/** grid_features: the interpolated hash-grid features of `points` in the scene box -> (n, L·F), level-major. */
function gridFeatures(builder, prefix, config) {
  const name = `${prefix}.grid`, axes = gridAxes(builder);
  const lo = config.aabb.slice(0, 3).map(f32), hi = config.aabb.slice(3).map(f32);
  const unit = builder.add("Div", [builder.add("Sub", ["points", float32(builder, `${prefix}.aabb.lo`, [3], lo)], `${name}.shifted`),
    float32(builder, `${prefix}.aabb.extent`, [3], hi.map((v, i) => f32(v - lo[i])))], `${name}.unit`);
  const inside = builder.add("Min", [builder.add("Max", [unit, float32(builder, "float.0", [1], [0])], `${name}.above`),
    float32(builder, "float.1", [1], [1])], `${name}.inside`);
  return interpolatedFeatures(builder, name, `${prefix}.table`, inside, configLevels(config), config.features,
    config.log2_table, axes, 0.5);
}

/** interpolated_features: trilinearly interpolated features of unit-cube points `unit` (n, 3) from the weight `table`
 * laid out by `levels` -> (n, L·F), level-major. The cell is that of scale_l·x + cellOffset (tiny-cuda-nn's 0.5;
 * nerfstudio's torch grid: 0). The corners are built from per-axis pairs (a dense index is the lower corner's plus a
 * constant per corner; a hash the XOR of one primed coordinate per axis). */
export function interpolatedFeatures(builder, name, table, unit, levels, features, log2Table, axes, cellOffset) {
  const L = levels.rows.length;
  const scaled = builder.add("Mul", [builder.add("Unsqueeze", [unit, axes[1]], `${name}.x`),
    float32(builder, `${name}.scale`, [L, 1], levels.scale)], `${name}.scaled`);
  const position = !cellOffset ? scaled : builder.add("Add", [scaled, float32(builder, "float.0.5", [1], [cellOffset])],
    `${name}.position`);
  const cell = builder.add("Floor", [position], `${name}.cell`); // (n, L, 3)
  const fraction = builder.add("Unsqueeze", [builder.add("Sub", [position, cell], `${name}.fraction`), axes[3]],
    `${name}.fraction4`); // (n, L, 3, 1)
  const lower = builder.add("Cast", [cell], `${name}.lower`, { to: 7 });
  const denseLevels = levels.dense.reduce((a, b) => a + b, 0); // a prefix: resolutions grow with the level
  const hashedLevels = L - denseLevels;
  let [denseLower, hashedLower] = [lower, lower];
  if (denseLevels && hashedLevels) {
    [denseLower, hashedLower] = builder.split(lower, int64(builder, `${name}.split.levels`, [2], [denseLevels, hashedLevels]),
      [`${name}.dense.lower`, `${name}.hashed.lower`], 1);
  }
  const indices = [...(denseLevels ? [denseIndex(builder, `${name}.dense`, denseLower, levels, [0, denseLevels])] : []),
    ...(hashedLevels ? [hashedIndex(builder, `${name}.hashed`, hashedLower, log2Table)] : [])];
  const joined = indices.length === 1 ? indices[0] : builder.add("Concat", indices, `${name}.level_index`, { axis: 1 });
  const index = builder.add("Add", [joined, int64(builder, `${name}.offset`, [L, 1], levels.offset)], `${name}.index`);
  builder.weights.set(table, [levels.totalRows, features]);
  const values = builder.add("Gather", [table, index], `${name}.values`, { axis: 0 }); // (n, L, 8, F)
  const factors = builder.add("Concat", [builder.add("Sub", [float32(builder, "float.1", [1], [1]), fraction], `${name}.rest`),
    fraction], `${name}.factors`, { axis: 3 }); // (n, L, 3, 2)
  const [wx, wy, wz] = cornerGrid(builder, `${name}.weight`, factors);
  const weights = builder.add("Reshape", [builder.add("Mul", [builder.add("Mul", [wx, wy], `${name}.wxy`), wz],
    `${name}.weights5`), cornersShape(builder)], `${name}.weights`); // (n, L, 8)
  const summed = builder.add("ReduceSum", [builder.add("Mul", [builder.add("Unsqueeze", [weights, axes[3]], `${name}.weights4`),
    values], `${name}.weighted`), axes[2]], `${name}.summed`, { keepdims: 0 }); // (n, L, F)
  return builder.add("Reshape", [summed, int64(builder, "shape.flat", [2], [0, -1])], `${name}.features`);
}

/** spherical_harmonics: SH of `directions` (n, 3) up to `degree` -> (n, degree²): shMatrix over the monomials, by
 * one Gemm; `signs` (16 of ±1) multiplies its rows (nerfstudio's torch SH, src/fields/nerfacto.js). */
export function sphericalHarmonics(builder, degree, directions = "viewdirs", signs = null) {
  const prefix = directions === "viewdirs" ? "sh" : `${directions}.sh`;
  const name = `${prefix}.${degree}`, monomials = `${prefix}.monomials`;
  if (builder.computed(name)) return name;
  if (!builder.computed(monomials)) { // shared by every degree
    const gather = (x, index, out) => builder.add("Gather", [x, int64(builder, `sh.index.${out}`, [index.length], index)],
      `${prefix}.${out}`, { axis: 1 });
    const degree2 = builder.add("Mul", [gather(directions, DEGREE2[0], "a2"), gather(directions, DEGREE2[1], "b2")], `${prefix}.deg2`);
    const degree3 = builder.add("Mul", [gather(degree2, DEGREE3[0], "a3"), gather(directions, DEGREE3[1], "b3")], `${prefix}.deg3`);
    builder.add("Concat", [directions, degree2, degree3], monomials, { axis: 1 });
  }
  let [matrix, constant] = shMatrix();
  if (signs !== null) { // float32 times ±1: exact (0 becomes −0, as in numpy)
    [matrix, constant] = [matrix.map((row, i) => row.map((v) => v * signs[i])), constant.map((v, i) => v * signs[i])];
  }
  const rows = degree ** 2;
  return builder.add("Gemm", [monomials, float32(builder, `${prefix}.matrix.${degree}`, [rows, MONOMIALS], matrix.slice(0, rows)),
    float32(builder, `${prefix}.constant.${degree}`, [rows], constant.slice(0, rows))], name, { transB: 1 });
}
