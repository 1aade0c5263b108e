"""The `nerfacto` field kind: nerfstudio's nerfacto field and its proposal networks, as nerfstudio renders them.

Position: nerfstudio's scene contraction with the L∞ norm, x if ‖x‖∞ < 1 else (2 − 1/‖x‖∞)·x/‖x‖∞, then
u = (x + 2)/4; points with u outside the open unit cube are moved to u = 0 and get σ = 0 (its `selector`).
u feeds a hash grid (runtime.fields.hashgrid) in one of the two functions nerfstudio trains with, which
differ in math, not only in layout:
- `tcnn` (tiny-cuda-nn): scale_l = N_min·b^l − 1, cell of scale_l·u + 0.5, dense levels where they fit;
- `torch` (nerfstudio's fallback): scale_l = floor(N_min·b^l), cell of scale_l·u, every level hashed into
  its own 2^log2_table rows.
The config holds the float32 scales themselves (`scales`, one per level), as the importer computed them
for the run's implementation. Direction: SH of degree 4 of the unit view direction in tiny-cuda-nn's
convention (`tcnn`), or nerfstudio's torch SH, which evaluates its polynomial at (d + 1)/2 with the odd-m
rows negated (`torch`). Density: σ = density_scale·exp(min(raw, cap)) (nerfstudio's
average_init_density·trunc_exp) from a ReLU MLP on the grid features, which also gives the geometric
feature; colour: a ReLU MLP on [SH ‖ geometric feature] with sigmoid (the mean appearance embedding nerfacto
uses at eval is folded into the first layer's bias by the importer). Noise segments as the hash grid's:
the interpolated grid features, then the SH values.

Proposal networks (nerfstudio's HashMLPDensityField): their own grid on the same u and a ReLU MLP to one raw
density, σ as above; outputs sigma_proposal0, … on the points alone, no noise (they only place the
ordinary render's samples: runtime.proposal). A field without proposal networks is nerfstudio's instant-ngp:
its `sampler` is then nerfacc's occupancy grid (runtime.grid_marching). Every MLP layer has a bias (tiny-cuda-nn's have none: the
importer writes zeros, and its padded-one input columns as the bias they act as).
"""

from __future__ import annotations

import base64
import binascii

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import FieldKind, Segment
from noisenerf.runtime.fields.hashgrid import (
    DENSITY_EXPONENT_CAP, GridLevels, checked_mlps, field_mlps, grid_axes, interpolated_features, layout_levels,
    spherical_harmonics,
)
from noisenerf.runtime.graph import GraphBuilder, proposal_output
from noisenerf.runtime.limits import (
    MAX_FIELD_WIDTH, MAX_GRID_RESOLUTION, MAX_HASH_FEATURES, MAX_HASH_LEVELS, MAX_HASH_RESOLUTION, MAX_LOG2_TABLE,
    MAX_PROPOSAL_NETWORKS, MAX_SAMPLES_PER_RAY, MAX_TABLE_VALUES, checked_float, checked_int, checked_list,
)

IMPLEMENTATIONS = ("tcnn", "torch")
KEYS = {"kind", "implementation", "features", "log2_table", "scales", "density_hidden", "geo_features", "sh_degree",
        "colour_hidden", "colour_layers", "density_scale", "proposals", "sampler"}
PROPOSAL_KEYS = {"features", "log2_table", "scales", "hidden"}
SAMPLER_KEYS = {"proposal_samples", "samples", "histogram_padding", "near", "far"}
GRID_SAMPLER_KEYS = {"step", "cone_angle", "near", "far", "levels", "resolution", "aabb", "occupancy"}
MAX_GRID_LEVELS = 8  # nerfacc's cascades (nerfstudio's instant-ngp: 4)
# nerfstudio's torch SH (nerfstudio.utils.spherical_harmonics) against tiny-cuda-nn's: odd-m rows negated
TORCH_SH_SIGNS = np.array([1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1], np.float32)


def grid_layout(implementation: str, scales, log2_table: int) -> GridLevels:
    """The level layout of a grid of this implementation at these scales (float32)."""
    return layout_levels(np.asarray(scales, np.float32), log2_table, all_hashed=implementation == "torch")


class NerfactoKind(FieldKind):
    name = "nerfacto"
    opset = 18

    def checked(self, config, what: str) -> dict:
        if not isinstance(config, dict) or set(config) != KEYS:
            raise UserError(f"the {what} network's architecture must have exactly {', '.join(sorted(KEYS))}",
                            code="field.keys", network=what, kind=self.name)
        implementation = config["implementation"]
        if implementation not in IMPLEMENTATIONS:
            raise UserError(f"the {what} network's implementation must be one of {', '.join(IMPLEMENTATIONS)}",
                            code="field.implementation", network=what,
                            implementation=implementation[:60] if isinstance(implementation, str) else None)
        checked = {"kind": self.name, "implementation": implementation,
                   **checked_grid(config, implementation, f"{what} network"), **checked_mlps(config, what),
                   "density_scale": checked_float(config["density_scale"], f"{what} density_scale", 1e-12, 1e12,
                                                    code="field.density_scale")}
        proposals = checked_list(config["proposals"], f"{what} proposals", most=MAX_PROPOSAL_NETWORKS,
                                 code="field.proposals")
        checked["proposals"] = [checked_proposal(proposal, implementation, f"{what} proposal network {i}")
                                for i, proposal in enumerate(proposals)]
        checked["sampler"] = (checked_sampler(config["sampler"], len(proposals), what) if proposals
                              else checked_grid_sampler(config["sampler"], what))
        values = sum(grid_layout(implementation, grid["scales"], grid["log2_table"]).total_rows * grid["features"]
                     for grid in [checked, *checked["proposals"]])
        if values > MAX_TABLE_VALUES:
            raise UserError(f"the {what} network's tables hold {values} values, more than {MAX_TABLE_VALUES}",
                            code="field.table_values", network=what, values=values, most=MAX_TABLE_VALUES)
        return checked

    def segments(self, config: dict) -> tuple[Segment, ...]:
        return (Segment("position", len(config["scales"]) * config["features"]),
                Segment("direction", config["sh_degree"] ** 2))

    def proposal_sampler(self, config: dict) -> dict | None:
        """The sampler of ordinary renders: one proposal stage per proposal network (outputs sigma_proposal0, …);
        None for nerfstudio's instant-ngp (no proposal networks: grid_sampler)."""
        return config["sampler"] if config["proposals"] else None

    def grid_sampler(self, config: dict) -> dict | None:
        """nerfstudio's instant-ngp: nerfacc's occupancy-grid marcher (runtime.grid_marching) renders ordinary views."""
        return None if config["proposals"] else config["sampler"]

    def build(self, builder: GraphBuilder, prefix: str, config: dict, rgb: str, sigma: str) -> None:
        axes = grid_axes(builder)
        unit, selector = contracted_unit(builder, prefix)
        features = grid_on(builder, prefix, unit, config["implementation"], config, axes)
        density = field_mlps(builder, prefix, config, self.segments(config), features, field_sh(builder, config), rgb)
        activated_density(builder, prefix, config, density, selector, sigma)
        for i, proposal in enumerate(config["proposals"]):
            name = f"{prefix}.proposals.{i}"
            features = grid_on(builder, name, unit, config["implementation"], proposal, axes)
            dims = len(proposal["scales"]) * proposal["features"]
            hidden = builder.add("Relu", (builder.linear(name, "linears.0", features, dims, proposal["hidden"]),),
                                 f"{name}.hidden")
            raw = builder.linear(name, "linears.1", hidden, proposal["hidden"], 1)
            activated_density(builder, name, config, raw, selector, proposal_output(i))


def cell_offset(implementation: str) -> float:
    return 0.5 if implementation == "tcnn" else 0.0


def grid_on(builder: GraphBuilder, name: str, unit: str, implementation: str, grid: dict, axes: dict[int, str]) -> str:
    """The features of network `name`'s grid (features, log2_table, scales) of the run's implementation at the
    contracted points `unit` -> (n, L·F)."""
    return interpolated_features(builder, f"{name}.grid", f"{name}.table", unit,
                                 grid_layout(implementation, grid["scales"], grid["log2_table"]), grid["features"],
                                 grid["log2_table"], axes, cell_offset=cell_offset(implementation))


def checked_grid(config: dict, implementation: str, what: str) -> dict:
    """A grid's features, log2_table and float32 scales (one per level), within the caps."""
    scales = checked_list(config["scales"], f"{what} scales", most=MAX_HASH_LEVELS, code="field.scales")
    if not scales:
        raise UserError(f"the {what}'s grid needs at least one level", code="field.no_levels", network=what)
    lowest = 1.0 if implementation == "torch" else 0.0
    values = [float(np.float32(checked_float(v, f"{what} scales", lowest, MAX_HASH_RESOLUTION - 2,
                                                        code="field.scales"))) for v in scales]
    if any(finer < coarser for coarser, finer in zip(values, values[1:])):
        raise UserError(f"the {what}'s scales must not decrease from level to level",  # dense levels come first
                        code="field.scales_decrease", network=what)
    return {"features": checked_int(config["features"], f"{what} features", 1, MAX_HASH_FEATURES,
                                    code="field.features"),
            "log2_table": checked_int(config["log2_table"], f"{what} log2_table", 3, MAX_LOG2_TABLE,
                                      code="field.log2_table"), "scales": values}


def checked_proposal(config, implementation: str, what: str) -> dict:
    if not isinstance(config, dict) or set(config) != PROPOSAL_KEYS:
        raise UserError(f"the {what} must have exactly {', '.join(sorted(PROPOSAL_KEYS))}", code="field.proposal_keys",
                        network=what)
    return {**checked_grid(config, implementation, what),
            "hidden": checked_int(config["hidden"], f"{what} hidden", 1, MAX_FIELD_WIDTH, code="field.width")}


def checked_sampler(config, proposals: int, what: str) -> dict:
    """nerfacto's proposal sampler: samples per proposal stage (one per network), the field's samples, the
    PDF's histogram padding, the ray interval of ordinary renders."""
    if not isinstance(config, dict) or set(config) != SAMPLER_KEYS:
        raise UserError(f"the {what} network's sampler must have exactly {', '.join(sorted(SAMPLER_KEYS))}",
                        code="field.sampler_keys", network=what)
    stages = checked_list(config["proposal_samples"], f"{what} proposal_samples", length=proposals,
                          code="field.proposal_samples")
    near = checked_float(config["near"], f"{what} sampler near", 0.0, 1e9, code="field.sampler_near")
    far = checked_float(config["far"], f"{what} sampler far", 0.0, 1e9, code="field.sampler_far")
    if not near < far:
        raise UserError(f"the {what} network's sampler needs near < far, got {near}, {far}", code="field.near_far",
                        network=what, near=near, far=far)
    return {"proposal_samples": [checked_int(n, f"{what} proposal_samples", 1, MAX_SAMPLES_PER_RAY,
                                             code="field.proposal_samples") for n in stages],
            "samples": checked_int(config["samples"], f"{what} sampler samples", 1, MAX_SAMPLES_PER_RAY,
                                   code="field.sampler_samples"),
            "histogram_padding": checked_float(config["histogram_padding"], f"{what} histogram_padding", 0.0, 1.0,
                                                       code="field.histogram_padding"),
            "near": near, "far": far}


def checked_grid_sampler(config, what: str) -> dict:
    """nerfstudio's instant-ngp sampler (runtime.grid_marching): the step, the cone angle, the ray interval, the
    grid's levels, cells per side, scene box and occupancy (one bit per cell, C order [level, x, y, z], base64),
    its size checked before it is decoded."""
    if not isinstance(config, dict) or set(config) != GRID_SAMPLER_KEYS:
        raise UserError(f"the {what} network's grid sampler must have exactly {', '.join(sorted(GRID_SAMPLER_KEYS))}",
                        code="field.sampler_keys", network=what)
    near = checked_float(config["near"], f"{what} sampler near", 0.0, 1e9, code="field.sampler_near")
    far = checked_float(config["far"], f"{what} sampler far", 0.0, 1e9, code="field.sampler_far")
    if not near < far:
        raise UserError(f"the {what} network's sampler needs near < far, got {near}, {far}", code="field.near_far",
                        network=what, near=near, far=far)
    levels = checked_int(config["levels"], f"{what} grid levels", 1, MAX_GRID_LEVELS, code="field.grid_levels")
    resolution = checked_int(config["resolution"], f"{what} grid resolution", 1, MAX_GRID_RESOLUTION,
                             code="field.grid_resolution")
    aabb = [checked_float(v, f"{what} grid aabb", -1e9, 1e9, code="field.grid_aabb")
            for v in checked_list(config["aabb"], f"{what} grid aabb", length=6, code="field.grid_aabb")]
    if not all(aabb[i] < aabb[i + 3] for i in range(3)):
        raise UserError(f"the {what} network's grid aabb must have min < max on every axis", code="field.grid_aabb",
                        network=what)
    if levels * resolution ** 3 > MAX_GRID_RESOLUTION ** 3:
        raise UserError(f"the {what} network's grid holds {levels} x {resolution}^3 cells, more than "
                        f"{MAX_GRID_RESOLUTION}^3", code="field.grid_cells", network=what)
    needed = -(-levels * resolution ** 3 // 8)
    occupancy = config["occupancy"]
    if not isinstance(occupancy, str) or len(occupancy) != 4 * -(-needed // 3) or len(base64_bytes(occupancy)) != needed:
        raise UserError(f"the {what} network's grid occupancy must be {needed} bytes in base64 (levels x resolution^3 "
                        "bits)", code="field.grid_occupancy", network=what, needed=needed)
    return {"step": checked_float(config["step"], f"{what} sampler step", 1e-9, 1e9, code="field.sampler_step"),
            "cone_angle": checked_float(config["cone_angle"], f"{what} cone angle", 0.0, 1.0, code="field.cone_angle"),
            "near": near, "far": far, "levels": levels, "resolution": resolution, "aabb": aabb, "occupancy": occupancy}


def base64_bytes(text: str) -> bytes:
    """Standard base64 as Python's strict decoder reads it; b'' where it is not."""
    try:
        return base64.b64decode(text, validate=True)
    except (ValueError, binascii.Error):
        return b""


def contracted_unit(builder: GraphBuilder, prefix: str) -> tuple[str, str]:
    """nerfstudio's L∞ scene contraction of `points`, then (x + 2)/4, points off the open unit cube at 0.
    -> the grid input (n, 3) and the selector (n, 1) float, 1 inside."""
    name = f"{prefix}.contraction"
    norm = builder.add("ReduceMax", (builder.add("Abs", ("points",), f"{name}.abs"),
                                     builder.constant("axes.1", np.array([1], np.int64))), f"{name}.norm", keepdims=1)
    one, two = (builder.constant(f"float.{v}", np.array([v], np.float32)) for v in (1, 2))
    outer = builder.add("Mul", (builder.add("Sub", (two, builder.add("Div", (one, norm), f"{name}.inverse")),
                                            f"{name}.radius"),
                                builder.add("Div", ("points", norm), f"{name}.direction")), f"{name}.outer")
    contracted = builder.add("Where", (builder.add("Less", (norm, one), f"{name}.inner"), "points", outer),
                             f"{name}.contracted")
    unit = builder.add("Div", (builder.add("Add", (contracted, two), f"{name}.shifted"),
                               builder.constant("float.4", np.array([4.0], np.float32))), f"{name}.unit")
    within = builder.add("And", (builder.add("Greater", (unit, builder.constant("float.0", np.zeros(1, np.float32))),
                                             f"{name}.above"), builder.add("Less", (unit, one), f"{name}.below")),
                         f"{name}.within")
    selector = builder.add("ReduceMin", (builder.add("Cast", (within,), f"{name}.within_float", to=1),
                                         builder.constant("axes.1", np.array([1], np.int64))),
                           f"{name}.selector", keepdims=1)
    return builder.add("Mul", (unit, selector), f"{name}.selected"), selector


def field_sh(builder: GraphBuilder, config: dict) -> str:
    """The direction encoding of the run's implementation (module docstring)."""
    if config["implementation"] == "tcnn":
        return spherical_harmonics(builder, config["sh_degree"])
    two = builder.constant("float.2", np.array([2.0], np.float32))
    halved = builder.add("Div", (builder.add("Add", ("viewdirs", builder.constant("float.1", np.ones(1, np.float32))),
                                             "viewdirs.plus1"), two), "viewdirs.halved")
    return spherical_harmonics(builder, config["sh_degree"], halved, TORCH_SH_SIGNS)


def activated_density(builder: GraphBuilder, prefix: str, config: dict, raw: str, selector: str, output: str) -> None:
    """σ = density_scale·exp(min(raw, cap))·selector, squeezed to (n,)."""
    cap = builder.constant("density.exponent_cap", np.array([DENSITY_EXPONENT_CAP], np.float32))
    exp = builder.add("Exp", (builder.add("Min", (raw, cap), f"{prefix}.capped_density"),), f"{prefix}.exp_density")
    scaled = builder.add("Mul", (builder.constant("density.scale", np.array([config["density_scale"]], np.float32)),
                                 exp), f"{prefix}.scaled_density")
    builder.add("Squeeze", (builder.add("Mul", (scaled, selector), f"{prefix}.sigma"),
                            builder.constant("axes.1", np.array([1], np.int64))), output)


NERFACTO = NerfactoKind()
