// Mirrors runtime/fields/mlp.py: the `mlp` field kind, the standard NeRF MLP (nerf-pytorch's, layer for layer).
// γ(v) = [v, sin(2⁰v), cos(2⁰v), …] per distinct encoding (shared by coarse and fine networks whose frequencies
// agree), noise added to [γ(x) ‖ γ(d)] and split again, Gemm(transB=1) layers with ReLU and the skip Concat,
// sigmoid colour, ReLU density. Noise segments: position γ(x), direction γ(d) (absent without view directions).

import { UserError } from "../errors.js";
import { MAX_FIELD_DEPTH, MAX_FIELD_WIDTH, MAX_FREQUENCIES, checkedInt, checkedList } from "../limits.js";
import { hasExactly, segment } from "./index.js";

/** encoding_dims (runtime/encoding.py): width of γ for a 3-vector with the raw input included. */
export const encodingDims = (nFreqs) => 3 + 6 * nFreqs;

const KEYS = ["depth", "width", "skips", "xyz_freqs", "dir_freqs", "use_viewdirs"];

/** γ(x) of an (n, 3) value -> (n, 3 + 6·nFreqs), computed once per (input, frequencies). */
function encoding(builder, x, nFreqs) {
  const name = `gamma.${x}.${nFreqs}`;
  if (builder.computed(name)) return name;
  const axis1 = builder.constant("axes.1", "int64", [1], [1]);
  const axis2 = builder.constant("axes.2", "int64", [1], [2]);
  const freqs = builder.constant(`freqs.${nFreqs}`, "float32", [nFreqs, 1], Array.from({ length: nFreqs }, (_, i) => 2 ** i));
  const scaled = builder.add("Mul", [builder.add("Unsqueeze", [x, axis1], `${name}.x`), freqs], `${name}.scaled`);
  const sin = builder.add("Unsqueeze", [builder.add("Sin", [scaled], `${name}.sin`), axis2], `${name}.sin4`);
  const cos = builder.add("Unsqueeze", [builder.add("Cos", [scaled], `${name}.cos`), axis2], `${name}.cos4`);
  const bands = builder.add("Concat", [sin, cos], `${name}.bands4`, { axis: 2 });
  const flat = builder.add("Reshape", [bands, builder.constant("shape.flat", "int64", [2], [0, -1])], `${name}.bands`);
  return builder.add("Concat", [x, flat], name, { axis: 1 });
}

/** γ(x) + noise, or [γ(x) ‖ γ(d)] + noise split back into its γ(x) and γ(d) parts (the latter null without view
 * directions), computed once per frequencies. */
function noisyInputs(builder, config) {
  const xyz = encoding(builder, "points", config.xyz_freqs);
  if (!config.use_viewdirs) {
    const name = `${xyz}+noise`;
    return [builder.computed(name) ? name : builder.add("Add", [xyz, "noise"], name), null];
  }
  const dirs = encoding(builder, "viewdirs", config.dir_freqs);
  return builder.noisyPair(xyz, dirs, () => builder.constant(`split.${config.xyz_freqs}.${config.dir_freqs}`, "int64", [2],
    [encodingDims(config.xyz_freqs), encodingDims(config.dir_freqs)]));
}

export const MLP = {
  name: "mlp",
  opset: 17,

  /** train.scene.field.FieldConfig's fields, exactly, within the caps. */
  checked(config, what) {
    if (!hasExactly(config, KEYS)) {
      throw new UserError(`the ${what} network's architecture must have exactly depth, width, skips, xyz_freqs, ` +
        "dir_freqs and use_viewdirs", { code: "field.keys", network: what, kind: this.name });
    }
    const depth = checkedInt(config.depth, `${what} depth`, 1, MAX_FIELD_DEPTH, { code: "field.depth" });
    const skips = checkedList(config.skips, "skips", null, depth, { code: "field.skips" })
      .map((skip) => checkedInt(skip, `${what} skip`, 0, depth - 1, { code: "field.skips" }));
    if (typeof config.use_viewdirs !== "boolean") {
      throw new UserError(`the ${what} network's use_viewdirs must be true or false`, { code: "field.use_viewdirs", network: what });
    }
    const width = checkedInt(config.width, `${what} width`, 2, MAX_FIELD_WIDTH, { code: "field.width" });
    const freqs = {};
    for (const key of ["xyz_freqs", "dir_freqs"]) {
      freqs[key] = checkedInt(config[key], `${what} ${key}`, 0, MAX_FREQUENCIES, { code: "field.frequencies" });
    }
    return { depth, width, skips: [...new Set(skips)].sort((a, b) => a - b), use_viewdirs: config.use_viewdirs, ...freqs };
  },

  segments(config) {
    const position = segment("position", encodingDims(config.xyz_freqs));
    return config.use_viewdirs ? [position, segment("direction", encodingDims(config.dir_freqs))] : [position];
  },

  /** One NeRF MLP (train.scene.field.NeRFField, layer for layer). */
  build(builder, prefix, config, rgb, sigma) {
    const [xyz, dirs] = noisyInputs(builder, config);
    const xyzDims = encodingDims(config.xyz_freqs), width = config.width;
    let h = xyz, fanIn = xyzDims;
    for (let i = 0; i < config.depth; i++) {
      h = builder.add("Relu", [builder.linear(prefix, `pts_linears.${i}`, h, fanIn, width)], `${prefix}.h${i}`);
      fanIn = width;
      if (config.skips.includes(i)) {
        h = builder.add("Concat", [xyz, h], `${prefix}.skip${i}`, { axis: 1 });
        fanIn = width + xyzDims;
      }
    }
    let rawRgb, density;
    if (config.use_viewdirs) {
      density = builder.linear(prefix, "alpha_linear", h, width, 1);
      const feature = builder.linear(prefix, "feature_linear", h, width, width);
      const branch = builder.add("Concat", [feature, dirs], `${prefix}.branch`, { axis: 1 });
      const hidden = builder.linear(prefix, "views_linears.0", branch, width + encodingDims(config.dir_freqs), Math.floor(width / 2));
      rawRgb = builder.linear(prefix, "rgb_linear", builder.add("Relu", [hidden], `${prefix}.views`), Math.floor(width / 2), 3);
    } else {
      const raw = builder.linear(prefix, "output_linear", h, width, 4);
      const sizes = builder.constant("split.rgb_density", "int64", [2], [3, 1]);
      [rawRgb, density] = builder.split(raw, sizes, [`${prefix}.raw_rgb`, `${prefix}.raw_density`]);
    }
    builder.add("Sigmoid", [rawRgb], rgb);
    builder.add("Squeeze", [builder.add("Relu", [density], `${prefix}.sigma`), builder.constant("axes.1", "int64", [1], [1])], sigma);
  },
};
