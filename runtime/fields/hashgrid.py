"""The `hashgrid` field kind: an Instant-NGP field, with tiny-cuda-nn's hash-grid and SH conventions.

Position: x normalised into the scene box, [0, 1]³ (points outside take the box's nearest point), then
per level l of L: scale_l = N_min·b^l − 1 and resolution_l = ceil(scale_l) + 1 (float32; level_scales),
the cell of scale_l·x + 0.5, its 8 corners indexed densely (x + y·res +
z·res², modulo the level's rows) where res³ fits the table and by the XOR-of-primes hash (x·1 ⊕
y·2654435761 ⊕ z·805459861, masked to the table) where it does not, their F features trilinearly
interpolated (Müller et al. 2022, eq. 1–3). Direction: real spherical harmonics of the unit view
direction up to `sh_degree` (16 values at degree 4), written as one matrix over the monomials of
degree ≤ 3. Noise segments: position = the L·F interpolated features, direction = the SH values
(the paper's noise after the encoding, eq. 4–5). Density: a ReLU MLP on the noisy features gives
[raw density ‖ geometric feature]; σ = exp(min(raw, DENSITY_EXPONENT_CAP)). Colour: a ReLU MLP on
[noisy SH ‖ geometric feature], sigmoid. Torch twin: train.scene.hashgrid.HashGridField.

The graph needs opset 18 (BitwiseXor, BitwiseAnd on int64).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import FieldKind, Segment
from noisenerf.runtime.graph import GraphBuilder
from noisenerf.runtime.limits import (
    MAX_FIELD_DEPTH, MAX_FIELD_WIDTH, MAX_HASH_FEATURES, MAX_HASH_LEVELS, MAX_HASH_RESOLUTION, MAX_LOG2_TABLE,
    MAX_TABLE_VALUES, checked_float, checked_int, checked_list,
)

KEYS = {"kind", "levels", "features", "log2_table", "base_resolution", "per_level_scale", "density_hidden",
        "geo_features", "sh_degree", "colour_hidden", "colour_layers", "aabb"}
PRIMES = (1, 2654435761, 805459861)  # Instant-NGP's spatial hash, one per axis
# σ = exp(raw) saturates a single sample's opacity long before this (σ·Δ ≥ 30 for any Δ ≥ 1e-12); the cap
# keeps σ and σ·1e10 (the last interval) finite in float32 whatever noise a bundle adds
DENSITY_EXPONENT_CAP = 30.0
MAX_SH_DEGREE = 4
# the monomials of degree 1 to 3 of (x, y, z), in this order: x, y, z, then deg2 = d[A2]·d[B2], deg3 = deg2[A3]·d[B3]
DEGREE2 = ((0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2))  # xx xy xz yy yz zz
DEGREE3 = ((0, 0, 0, 1, 1, 2, 3, 3, 4, 5), (0, 1, 2, 1, 2, 2, 1, 2, 2, 2))  # xxx xxy xxz xyy xyz xzz yyy yyz yzz zzz
MONOMIALS = 19


def sh_matrix() -> tuple[np.ndarray, np.ndarray]:
    """The real spherical harmonics of degree 4 (16 values, tiny-cuda-nn's order and signs) as a matrix
    over the 19 monomials above and a constant term: SH(d) = M·m(d) + c. -> (16, 19), (16,) float32."""
    matrix, constant = np.zeros((16, MONOMIALS), np.float64), np.zeros(16, np.float64)
    x, y, z, xx, xy, xz, yy, yz, zz, xxx, xxy, xxz, xyy, xyz, xzz, yyy, yyz, yzz, zzz = range(MONOMIALS)
    constant[0] = 0.28209479177387814
    matrix[1, y], matrix[2, z], matrix[3, x] = -0.48860251190291987, 0.48860251190291987, -0.48860251190291987
    matrix[4, xy], matrix[5, yz], matrix[7, xz] = 1.0925484305920792, -1.0925484305920792, -1.0925484305920792
    matrix[6, zz], constant[6] = 0.94617469575755997, -0.31539156525251999
    matrix[8, xx], matrix[8, yy] = 0.54627421529603959, -0.54627421529603959
    matrix[9, xxy], matrix[9, yyy] = -3 * 0.59004358992664352, 0.59004358992664352
    matrix[10, xyz] = 2.8906114426405538
    matrix[11, y], matrix[11, yzz] = 0.45704579946446572, -5 * 0.45704579946446572
    matrix[12, zzz], matrix[12, z] = 5 * 0.3731763325901154, -3 * 0.3731763325901154
    matrix[13, x], matrix[13, xzz] = 0.45704579946446572, -5 * 0.45704579946446572
    matrix[14, xxz], matrix[14, yyz] = 1.4453057213202769, -1.4453057213202769
    matrix[15, xxx], matrix[15, xyy] = -0.59004358992664352, 3 * 0.59004358992664352
    return matrix.astype(np.float32), constant.astype(np.float32)


@dataclass(frozen=True, eq=False)
class GridLevels:
    """Per-level constants of a hash grid, (L,) each: float32 scale, int64 vertices per side, table rows,
    first row, dense (1) or hashed (0)."""

    scale: np.ndarray
    resolution: np.ndarray
    rows: np.ndarray
    offset: np.ndarray
    dense: np.ndarray

    @property
    def total_rows(self) -> int:
        return int(self.rows.sum())


def level_scales(levels: int, base_resolution: int, per_level_scale: float) -> np.ndarray:
    """scale_l = N_min·b^l − 1, b^l by repeated float64 products and the result rounded once to float32: the
    same bits on every machine and in the browser (float32 exp2/log2, tiny-cuda-nn's own formula, differ by an
    ulp between CPUs, and where N_min·b^l is near an integer that moves a level's resolution). -> (L,) float32."""
    power, scales = 1.0, []
    for _ in range(levels):
        scales.append(base_resolution * power - 1.0)
        power *= per_level_scale
    return np.array(scales, np.float64).astype(np.float32)


def grid_levels(levels: int, log2_table: int, base_resolution: int, per_level_scale: float) -> GridLevels:
    """tiny-cuda-nn's level layout of scales N_min·b^l − 1 (level_scales)."""
    return layout_levels(level_scales(levels, base_resolution, per_level_scale), log2_table)


def layout_levels(scale: np.ndarray, log2_table: int, all_hashed: bool = False) -> GridLevels:
    """The tables of levels at these float32 scales: tiny-cuda-nn's resolution ceil(scale) + 1 and rows
    min(res³ rounded up to 8, 2^log2_table), dense where res³ fits in them; or, `all_hashed` (nerfstudio's
    torch grid), 2^log2_table hashed rows every level."""
    resolution = np.ceil(scale).astype(np.int64) + 1
    cells = resolution ** 3
    table = 1 << log2_table
    rows = np.full_like(cells, table) if all_hashed else np.minimum((cells + 7) // 8 * 8, table)
    offset = np.concatenate([[0], np.cumsum(rows)[:-1]]).astype(np.int64)
    dense = np.zeros_like(cells) if all_hashed else (cells <= rows).astype(np.int64)
    return GridLevels(scale, resolution, rows.astype(np.int64), offset, dense)


def config_levels(config: dict) -> GridLevels:
    return grid_levels(config["levels"], config["log2_table"], config["base_resolution"], config["per_level_scale"])


def corner_offsets() -> np.ndarray:
    """The 8 corners of a cell, corner i taking +1 on axis d where bit d of i is set. -> (8, 3) int64."""
    return np.array([[(i >> d) & 1 for d in range(3)] for i in range(8)], np.int64)


class HashGridKind(FieldKind):
    name = "hashgrid"
    opset = 18

    def checked(self, config, what: str) -> dict:
        if not isinstance(config, dict) or set(config) != KEYS:
            raise UserError(f"the {what} network's architecture must have exactly {', '.join(sorted(KEYS))}",
                            code="field.keys", network=what, kind=self.name)
        checked = {
            "kind": self.name,
            "levels": checked_int(config["levels"], f"{what} levels", 1, MAX_HASH_LEVELS, code="field.levels"),
            "features": checked_int(config["features"], f"{what} features", 1, MAX_HASH_FEATURES,
                                    code="field.features"),
            "log2_table": checked_int(config["log2_table"], f"{what} log2_table", 3, MAX_LOG2_TABLE,
                                      code="field.log2_table"),
            "base_resolution": checked_int(config["base_resolution"], f"{what} base_resolution", 1, MAX_HASH_RESOLUTION,
                                             code="field.base_resolution"),
            "per_level_scale": checked_float(config["per_level_scale"], f"{what} per_level_scale", 1.0, 8.0,
                                             code="field.per_level_scale"),
            **checked_mlps(config, what),
            "aabb": [checked_float(v, f"{what} aabb", -1e9, 1e9, code="field.aabb")
                     for v in checked_list(config["aabb"], "aabb", length=6, code="field.aabb")],
        }
        if not all(lo < hi for lo, hi in zip(checked["aabb"][:3], checked["aabb"][3:])):
            raise UserError(f"the {what} network's aabb must have min < max on every axis", code="field.aabb_order",
                            network=what)
        finest = (checked["per_level_scale"] ** (checked["levels"] - 1)) * checked["base_resolution"]
        if not math.isfinite(finest) or finest > MAX_HASH_RESOLUTION:
            raise UserError(f"the {what} network's finest level has {finest:.6g} vertices a side, more than "
                            f"{MAX_HASH_RESOLUTION}", code="field.finest_resolution", network=what,
                            levels=checked["levels"], base_resolution=checked["base_resolution"],
                            per_level_scale=checked["per_level_scale"], most=MAX_HASH_RESOLUTION)
        levels = config_levels(checked)
        if levels.total_rows * checked["features"] > MAX_TABLE_VALUES:
            raise UserError(f"the {what} network's tables hold {levels.total_rows * checked['features']} values, more "
                            f"than {MAX_TABLE_VALUES}", code="field.table_values", network=what,
                            values=levels.total_rows * checked["features"], most=MAX_TABLE_VALUES)
        return checked

    def segments(self, config: dict) -> tuple[Segment, ...]:
        return Segment("position", config["levels"] * config["features"]), Segment("direction", config["sh_degree"] ** 2)

    def build(self, builder: GraphBuilder, prefix: str, config: dict, rgb: str, sigma: str) -> None:
        features = grid_features(builder, prefix, config)
        density = field_mlps(builder, prefix, config, self.segments(config), features,
                             spherical_harmonics(builder, config["sh_degree"]), rgb)
        cap = builder.constant("density.exponent_cap", np.array([DENSITY_EXPONENT_CAP], np.float32))
        capped = builder.add("Min", (density, cap), f"{prefix}.capped_density")
        builder.add("Squeeze", (builder.add("Exp", (capped,), f"{prefix}.sigma"),
                                builder.constant("axes.1", np.array([1], np.int64))), sigma)


def checked_mlps(config: dict, what: str) -> dict:
    """The widths of a hash-grid field's two MLPs and its SH degree, within the caps."""
    width = lambda key, low=1: checked_int(config[key], f"{what} {key}", low, MAX_FIELD_WIDTH,  # noqa: E731
                                           code="field.width")
    return {"density_hidden": width("density_hidden"), "geo_features": width("geo_features", 0),
            "sh_degree": checked_int(config["sh_degree"], f"{what} sh_degree", 1, MAX_SH_DEGREE,
                                     code="field.sh_degree"),
            "colour_hidden": width("colour_hidden"),
            "colour_layers": checked_int(config["colour_layers"], f"{what} colour_layers", 1, MAX_FIELD_DEPTH,
                                           code="field.colour_layers")}


def field_mlps(builder: GraphBuilder, prefix: str, config: dict, segments: tuple[Segment, Segment], features: str,
               sh: str, rgb: str) -> str:
    """Noise on [grid features ‖ SH], the density MLP to [raw density ‖ geometric feature], the colour MLP
    on [noisy SH ‖ geometric feature] to the sigmoid `rgb` output. -> the raw density (n, 1)."""
    position, direction = segments
    grid, sh = builder.noisy_pair(features, sh, lambda: (
        builder.constant(f"{prefix}.split.noise", np.array([position.dims, direction.dims], np.int64))))
    hidden = builder.add("Relu", (builder.linear(prefix, "density_linears.0", grid, position.dims,
                                                 config["density_hidden"]),), f"{prefix}.density_hidden")
    trunk = builder.linear(prefix, "density_linears.1", hidden, config["density_hidden"], 1 + config["geo_features"])
    if config["geo_features"]:
        split = builder.constant(f"{prefix}.split.trunk", np.array([1, config["geo_features"]], np.int64))
        density, geo = builder.split(trunk, split, (f"{prefix}.raw_density", f"{prefix}.geo"))
        h = builder.add("Concat", (sh, geo), f"{prefix}.head", axis=1)
    else:
        density, h = trunk, sh
    fan_in = direction.dims + config["geo_features"]
    for i in range(config["colour_layers"]):
        h = builder.add("Relu", (builder.linear(prefix, f"colour_linears.{i}", h, fan_in, config["colour_hidden"]),),
                        f"{prefix}.colour{i}")
        fan_in = config["colour_hidden"]
    raw_rgb = builder.linear(prefix, f"colour_linears.{config['colour_layers']}", h, fan_in, 3)
    builder.add("Sigmoid", (raw_rgb,), rgb)
    return density


def corner_grid(builder: GraphBuilder, name: str, per_axis: str) -> str:
    """The 8 corners' combinations of per-axis pairs (n, L, 3, 2) (entry 0: the cell's lower vertex, 1: its
    upper), axis d broadcast along its own dimension of (n, L, 2, 2, 2) so that corner i = 4·b_z + 2·b_y
    + b_x (bit d of i: the upper vertex on axis d). -> the three (n, L, ·, ·, ·) terms."""
    x, y, z = builder.split(per_axis, builder.constant("split.3x1", np.ones(3, np.int64)),
                            (f"{name}.x", f"{name}.y", f"{name}.z"), axis=2)
    return tuple(builder.add("Reshape", (term, builder.constant(f"shape.axis{d}", np.array(shape, np.int64))),
                             f"{name}.{axis}5") for d, (term, axis, shape) in enumerate(
        ((x, "x", (0, 0, 1, 1, 2)), (y, "y", (0, 0, 1, 2, 1)), (z, "z", (0, 0, 2, 1, 1)))))


def corners_shape(builder: GraphBuilder) -> str:
    """The constant that reshapes (n, L, 2, 2, 2) corners to (n, L, 8)."""
    return builder.constant("shape.corners", np.array([0, 0, 8], np.int64))


def dense_index(builder: GraphBuilder, name: str, lower: str, levels: GridLevels, span: slice) -> str:
    """Rows of the 8 corners on dense levels: the lower corner's x + y·res + z·res², plus each corner's
    constant offset, modulo the level's rows (the wraparound). lower: (n, l, 3) int64 -> (n, l, 8)."""
    strides = np.stack([np.ones_like(levels.resolution), levels.resolution, levels.resolution ** 2], 1)[span]
    base = builder.add("ReduceSum", (builder.add("Mul", (lower, builder.constant(f"{name}.strides", strides)),
                                                 f"{name}.strided"), builder.constant("axes.2", np.array([2], np.int64))),
                       f"{name}.base", keepdims=1)
    corner_strides = builder.constant(f"{name}.corner_strides", (corner_offsets() @ strides.T).T)  # (l, 8)
    return builder.add("Mod", (builder.add("Add", (base, corner_strides), f"{name}.unwrapped"),
                               builder.constant(f"{name}.rows", levels.rows[span, None])), f"{name}.index")


def hashed_index(builder: GraphBuilder, name: str, lower: str, log2_table: int) -> str:
    """Rows of the 8 corners on hashed levels: (x·1 ⊕ y·2654435761 ⊕ z·805459861) & (T − 1), each axis's
    two primed vertices computed once. lower: (n, l, 3) int64 -> (n, l, 8)."""
    vertices = builder.add("Add", (builder.add("Unsqueeze", (lower, builder.constant("axes.3", np.array([3], np.int64))),
                                               f"{name}.lower4"),
                                   builder.constant("grid.pair", np.array([0, 1], np.int64))), f"{name}.vertices")
    primed = builder.add("Mul", (vertices, builder.constant("grid.primes", np.array(PRIMES, np.int64)[:, None])),
                         f"{name}.primed")  # (n, l, 3, 2)
    hx, hy, hz = corner_grid(builder, name, primed)
    return builder.add("Reshape", (builder.add("BitwiseAnd", (builder.add("BitwiseXor", (builder.add(
        "BitwiseXor", (hx, hy), f"{name}.hxy"), hz), f"{name}.hxyz"), builder.constant(
        f"{name}.mask", np.array([(1 << log2_table) - 1], np.int64))), f"{name}.masked"), corners_shape(builder)),
        f"{name}.index")


def grid_axes(builder: GraphBuilder) -> dict[int, str]:
    """The axis constants a grid's nodes use, added before the grid's own constants (the file's order)."""
    return {k: builder.constant(f"axes.{k}", np.array([k], np.int64)) for k in (1, 2, 3)}


def grid_features(builder: GraphBuilder, prefix: str, config: dict) -> str:
    """The interpolated hash-grid features of `points` in the scene box -> (n, L·F), level-major."""
    name, axes = f"{prefix}.grid", grid_axes(builder)
    lo, hi = np.asarray(config["aabb"][:3], np.float32), np.asarray(config["aabb"][3:], np.float32)
    unit = builder.add("Div", (builder.add("Sub", ("points", builder.constant(f"{prefix}.aabb.lo", lo)), f"{name}.shifted"),
                               builder.constant(f"{prefix}.aabb.extent", hi - lo)), f"{name}.unit")
    inside = builder.add("Min", (builder.add("Max", (unit, builder.constant("float.0", np.zeros(1, np.float32))),
                                             f"{name}.above"), builder.constant("float.1", np.ones(1, np.float32))),
                         f"{name}.inside")
    return interpolated_features(builder, name, f"{prefix}.table", inside, config_levels(config), config["features"],
                                 config["log2_table"], axes, cell_offset=0.5)


def interpolated_features(builder: GraphBuilder, name: str, table: str, unit: str, levels: GridLevels, features: int,
                          log2_table: int, axes: dict[int, str], cell_offset: float) -> str:
    """Trilinearly interpolated features of unit-cube points `unit` (n, 3) from the weight `table` laid out
    by `levels` -> (n, L·F), level-major. The cell is that of scale_l·x + cell_offset (tiny-cuda-nn's 0.5;
    nerfstudio's torch grid: 0). The corners are built from per-axis pairs (a dense index is the lower
    corner's plus a constant per corner; a hash is the XOR of one primed coordinate per axis), so the
    integer work is per axis, not per corner and axis."""
    scaled = builder.add("Mul", (builder.add("Unsqueeze", (unit, axes[1]), f"{name}.x"),
                                 builder.constant(f"{name}.scale", levels.scale[:, None])), f"{name}.scaled")
    position = scaled if not cell_offset else builder.add(
        "Add", (scaled, builder.constant("float.0.5", np.array([cell_offset], np.float32))), f"{name}.position")
    cell = builder.add("Floor", (position,), f"{name}.cell")  # (n, L, 3)
    fraction = builder.add("Unsqueeze", (builder.add("Sub", (position, cell), f"{name}.fraction"), axes[3]),
                           f"{name}.fraction4")  # (n, L, 3, 1)
    lower = builder.add("Cast", (cell,), f"{name}.lower", to=7)
    dense_levels = int(levels.dense.sum())  # a prefix: resolutions grow with the level
    hashed_levels = len(levels.rows) - dense_levels
    dense_lower = hashed_lower = lower
    if dense_levels and hashed_levels:
        dense_lower, hashed_lower = builder.split(lower, builder.constant(f"{name}.split.levels", np.array(
            [dense_levels, hashed_levels], np.int64)), (f"{name}.dense.lower", f"{name}.hashed.lower"), axis=1)
    indices = ([dense_index(builder, f"{name}.dense", dense_lower, levels, slice(0, dense_levels))] if dense_levels
               else []) + ([hashed_index(builder, f"{name}.hashed", hashed_lower, log2_table)]
                           if hashed_levels else [])
    joined = indices[0] if len(indices) == 1 else builder.add("Concat", tuple(indices), f"{name}.level_index", axis=1)
    index = builder.add("Add", (joined, builder.constant(f"{name}.offset", levels.offset[:, None])), f"{name}.index")
    builder.weights[table] = (levels.total_rows, features)
    values = builder.add("Gather", (table, index), f"{name}.values", axis=0)  # (n, L, 8, F)
    factors = builder.add("Concat", (builder.add("Sub", (builder.constant("float.1", np.ones(1, np.float32)), fraction),
                                                 f"{name}.rest"), fraction), f"{name}.factors", axis=3)  # (n, L, 3, 2)
    wx, wy, wz = corner_grid(builder, f"{name}.weight", factors)
    weights = builder.add("Reshape", (builder.add("Mul", (builder.add("Mul", (wx, wy), f"{name}.wxy"), wz),
                                                  f"{name}.weights5"), corners_shape(builder)), f"{name}.weights")
    summed = builder.add("ReduceSum", (builder.add("Mul", (builder.add("Unsqueeze", (weights, axes[3]), f"{name}.weights4"),
                                                           values), f"{name}.weighted"), axes[2]),
                         f"{name}.summed", keepdims=0)  # (n, L, F)
    return builder.add("Reshape", (summed, builder.constant("shape.flat", np.array([0, -1], np.int64))), f"{name}.features")


def spherical_harmonics(builder: GraphBuilder, degree: int, directions: str = "viewdirs", signs=None) -> str:
    """SH of `directions` (n, 3) up to `degree` -> (n, degree²): sh_matrix over the monomials, by one Gemm;
    `signs` (16,) flips rows (nerfstudio's torch SH, runtime.fields.nerfacto)."""
    prefix = "sh" if directions == "viewdirs" else f"{directions}.sh"
    name, monomials = f"{prefix}.{degree}", f"{prefix}.monomials"
    if builder.computed(name):
        return name
    if not builder.computed(monomials):  # shared by every degree
        gather = lambda x, index, out: builder.add("Gather", (x, builder.constant(  # noqa: E731
            f"sh.index.{out}", np.array(index, np.int64))), f"{prefix}.{out}", axis=1)
        degree2 = builder.add("Mul", (gather(directions, DEGREE2[0], "a2"), gather(directions, DEGREE2[1], "b2")),
                              f"{prefix}.deg2")
        degree3 = builder.add("Mul", (gather(degree2, DEGREE3[0], "a3"), gather(directions, DEGREE3[1], "b3")),
                              f"{prefix}.deg3")
        builder.add("Concat", (directions, degree2, degree3), monomials, axis=1)
    matrix, constant = sh_matrix()
    rows = degree ** 2
    if signs is not None:
        matrix, constant = matrix * signs[:, None], constant * signs
    return builder.add("Gemm", (monomials, builder.constant(f"{prefix}.matrix.{degree}", matrix[:rows]),
                                builder.constant(f"{prefix}.constant.{degree}", constant[:rows])), name, transB=1)


HASHGRID = HashGridKind()
