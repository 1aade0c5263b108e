"""The `hashgrid` field in torch: Instant-NGP's multiresolution hash encoding with two tiny MLPs.

Every operation is the graph's (runtime.fields.hashgrid, which documents the math), so a torch render
and an onnxruntime render differ by float32 summation order only. Noise δ is added to the interpolated
grid features and to the SH encoding, [enc(x) ‖ SH(d)] + δ (paper eq. 4–5 with the hash encoding in
place of γ). Both MLPs are ReLU networks, so raw outputs are piecewise linear in the noise and the
exact solver's Gauss–Newton steps carry over; their Jacobian is written by hand (`outputs_and_jacobian`).

Training follows Instant-NGP: the tables' gradient is accumulated by weighted bincounts (GridGather;
embedding_bag's own backward is several times slower on a CPU), Adam with β₂ = 0.99 and ε = 1e-15, and
weight decay on the MLPs only (`parameter_groups`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from noisenerf.runtime.fields.hashgrid import (
    DEGREE2, DEGREE3, DENSITY_EXPONENT_CAP, HASHGRID, PRIMES, GridLevels, config_levels, sh_matrix,
)
from noisenerf.train.scene.field_module import FieldModule

TABLE_INIT = 1e-4  # tables start uniform in ±this (Instant-NGP's)
NEGLIGIBLE_OPACITY = 0.5 / 255  # Σ σΔ a ray's left-out samples may hold (negligible): half an 8-bit step
MLP_WEIGHT_DECAY = 1e-6


class GridFieldDims:
    """The noise widths of a config with `position_dims` (grid features) and `sh_degree`."""

    has_view_branch: ClassVar[bool] = True

    @property
    def direction_dims(self) -> int:
        return self.sh_degree ** 2

    @property
    def noise_dims(self) -> int:
        return self.position_dims + self.direction_dims


@dataclass(frozen=True)
class HashGridConfig(GridFieldDims):
    """Architecture of one hash-grid field (runtime.fields.hashgrid's keys). `aabb` is the scene box the
    grid spans; per_level_scale = (max_resolution / base_resolution)^(1 / (levels − 1)) (`with_max_resolution`)."""

    kind: ClassVar[str] = "hashgrid"
    levels: int = 16
    features: int = 2
    log2_table: int = 17
    base_resolution: int = 16
    per_level_scale: float = 1.3195079107728942  # 16 → 1024 over 16 levels
    density_hidden: int = 64
    geo_features: int = 15
    sh_degree: int = 4
    colour_hidden: int = 64
    colour_layers: int = 2
    aabb: tuple[float, ...] = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)

    @staticmethod
    def per_level_scale_for(base_resolution: int, max_resolution: int, levels: int) -> float:
        """Instant-NGP's b = exp((ln N_max − ln N_min) / (L − 1)), in float64."""
        return float(np.exp((np.log(max_resolution) - np.log(base_resolution)) / max(levels - 1, 1)))

    @property
    def position_dims(self) -> int:
        return self.levels * self.features

    def to_dict(self) -> dict:
        return {"kind": self.kind, **dataclasses.asdict(self), "aabb": [float(v) for v in self.aabb]}

    def in_box(self, aabb) -> "HashGridConfig":
        """The config for a scene in this box: the grid spans it."""
        return dataclasses.replace(self, aabb=tuple(float(v) for v in aabb))

    @staticmethod
    def from_dict(data: dict) -> "HashGridConfig":
        checked = HASHGRID.checked(data, "scene")
        return HashGridConfig(**{**{k: v for k, v in checked.items() if k != "kind"}, "aabb": tuple(checked["aabb"])})


CORNERS = tuple((c & 1, (c >> 1) & 1, c >> 2) for c in range(8))  # corner c = 4·b_z + 2·b_y + b_x: (b_x, b_y, b_z)


class GridGather(torch.autograd.Function):
    """Σ_corners weight · table[index] per (sample, level), with the table's gradient by one weighted
    bincount per feature (on a CPU ~4x faster than index_add, which embedding_bag's own backward uses).
    table (rows, F), index (b, 8) int32/int64, weights (b, 8) -> (b, F). No gradient for index or weights."""

    @staticmethod
    def forward(ctx, table, index, weights):
        ctx.save_for_backward(index, weights)
        ctx.rows = table.shape[0]
        return functional.embedding_bag(index, table, per_sample_weights=weights, mode="sum")

    @staticmethod
    def backward(ctx, grad):
        index, weights = ctx.saved_tensors
        flat = index.reshape(-1).long()
        columns = [torch.bincount(flat, (weights * grad[:, f, None]).reshape(-1), minlength=ctx.rows)
                   for f in range(grad.shape[1])]
        return torch.stack(columns, 1), None, None


class GridEncoding(nn.Module):
    """runtime.fields.hashgrid.interpolated_features in torch: the interpolated features of unit-cube points
    from a table laid out by `levels`, cell of scale·u + cell_offset. Holds only constants; the table is its
    owner's parameter (so weight names stay the owner's)."""

    def __init__(self, levels: GridLevels, log2_table: int, features: int, cell_offset: float):
        super().__init__()
        self.levels, self.features, self.cell_offset = len(levels.rows), features, cell_offset
        self.dense_levels = dense = int(levels.dense.sum())
        self.mask = (1 << log2_table) - 1
        # int32 where every product fits: the finest vertex times a prime reduced modulo the table
        self.index_dtype = torch.int32 if (int(levels.resolution.max()) + 1) * self.mask < 2 ** 31 else torch.int64
        integer = np.int32 if self.index_dtype == torch.int32 else np.int64
        strides = np.stack([np.ones_like(levels.resolution), levels.resolution, levels.resolution ** 2], 1)[:dense]
        for name, value in {"scale": levels.scale[:, None], "strides": strides.astype(integer),
                            "rows": levels.rows[:dense, None].astype(integer), "offset": levels.offset[:, None].astype(integer),
                            "primes": (np.array(PRIMES, np.int64)[:, None] & self.mask).astype(integer)}.items():
            self.register_buffer(name, torch.from_numpy(np.ascontiguousarray(value)), persistent=False)

    def forward(self, table: torch.Tensor, unit: torch.Tensor) -> torch.Tensor:
        """Features of unit-cube points (n, 3) -> (n, L·F), level-major: the graph's corners, indices and weights
        (runtime.fields.hashgrid: corner c = 4·b_z + 2·b_y + b_x, weight (w_x·w_y)·w_z, hash h_x ^ h_y ^ h_z)."""
        n, levels = unit.shape[0], self.levels
        index = torch.empty((levels, n, 8), dtype=self.index_dtype, device=unit.device)
        weights = torch.empty((levels, n, 8), dtype=unit.dtype, device=unit.device)
        with torch.no_grad():  # GridGather takes no gradient through indices or weights
            self.write_bags(unit, index, weights)
        gathered = GridGather.apply(table, index.view(-1, 8), weights.view(-1, 8))
        return gathered.view(levels, n, self.features).transpose(0, 1).reshape(n, levels * self.features)

    def write_bags(self, unit: torch.Tensor, index: torch.Tensor, weights: torch.Tensor) -> None:
        """Each (level, point)'s 8 corner rows and weights into index and weights (L, n, 8): unit (n, 3). Worked
        with the points innermost (L, 3, n), the x-y pairs once, each corner written straight into its column (on
        a CPU, temporaries copied into the columns took a third of a render's time)."""
        dense = self.dense_levels
        position = unit.T[None] * self.scale[:, :, None]  # (L, 3, n)
        if self.cell_offset:
            position = position + self.cell_offset
        cell = torch.floor(position)
        fraction = position - cell
        lower = cell.to(self.index_dtype)
        # dense levels: row = Σ_a (lower_a + b_a)·stride_a, wrapped; hashed: ⊕_a (lower_a + b_a)·prime_a, masked
        # (the primes are taken modulo the table: the masked XOR is unchanged and the products fit index_dtype)
        dense_terms = [(lower[:dense, a] * self.strides[:, a, None], (lower[:dense, a] + 1) * self.strides[:, a, None])
                       for a in range(3)]  # (dense, n)
        primes, hashed = self.primes[:, 0], lower[dense:]
        hash_terms = [((hashed[:, a] * primes[a]) & self.mask, ((hashed[:, a] + 1) * primes[a]) & self.mask)
                      for a in range(3)]  # (L − dense, n)
        weight_terms = [(1.0 - fraction[:, a], fraction[:, a]) for a in range(3)]  # (L, n)
        pairs = [(dense_terms[0][bx] + dense_terms[1][by], hash_terms[0][bx] ^ hash_terms[1][by],
                  weight_terms[0][bx] * weight_terms[1][by]) for bx, by, _ in CORNERS[:4]]
        for c, (_, _, bz) in enumerate(CORNERS):
            dense_xy, hash_xy, weight_xy = pairs[c & 3]
            torch.remainder(dense_xy + dense_terms[2][bz], self.rows, out=index[:dense, :, c])
            torch.bitwise_xor(hash_xy, hash_terms[2][bz], out=index[dense:, :, c])
            torch.mul(weight_xy, weight_terms[2][bz], out=weights[:, :, c])
        index += self.offset[:, :, None]


class HashGridField(FieldModule):
    """F(enc(x) + δ_x, SH(d) + δ_d) -> (rgb, σ) with sigmoid colour and σ = exp(min(raw, cap))."""

    def __init__(self, config: HashGridConfig):
        super().__init__()
        self.config = config
        levels = config_levels(config.to_dict())
        self.table = nn.Parameter(torch.empty(levels.total_rows, config.features).uniform_(-TABLE_INIT, TABLE_INIT))
        self.grid = GridEncoding(levels, config.log2_table, config.features, cell_offset=0.5)
        for name, value in {"lo": np.asarray(config.aabb[:3], np.float32),
                            "extent": np.asarray(config.aabb[3:], np.float32) - np.asarray(config.aabb[:3], np.float32)
                            }.items():
            self.register_buffer(name, torch.from_numpy(value), persistent=False)
        self.register_sh(config.direction_dims)
        self.add_mlps(config)

    def add_mlps(self, config) -> None:
        """The density MLP (grid features -> [raw density ‖ geometric feature]) and the colour MLP
        ([SH ‖ geometric feature] -> raw colour), freshly initialised."""
        self.density_linears = nn.ModuleList([nn.Linear(config.position_dims, config.density_hidden),
                                              nn.Linear(config.density_hidden, 1 + config.geo_features)])
        widths = [config.direction_dims + config.geo_features] + [config.colour_hidden] * config.colour_layers
        self.colour_linears = nn.ModuleList([nn.Linear(a, b) for a, b in zip(widths, widths[1:] + [3])])

    def register_sh(self, rows: int, signs: np.ndarray | None = None) -> None:
        """The SH matrix and constant (runtime.fields.hashgrid.sh_matrix), rows flipped by `signs`."""
        matrix, constant = sh_matrix()
        if signs is not None:
            matrix, constant = matrix * signs[:, None], constant * signs
        self.register_buffer("sh_matrix", torch.from_numpy(matrix[:rows].copy()), persistent=False)
        self.register_buffer("sh_constant", torch.from_numpy(constant[:rows].copy()), persistent=False)

    def density_layers(self) -> list[nn.Linear]:
        """The layers a density alone runs through (the bench's cost model; the grid is gathers)."""
        return list(self.density_linears)

    def parameter_groups(self) -> list[dict]:
        """The optimizer's groups: the tables without weight decay, the MLPs with it (Instant-NGP)."""
        mlps = [p for name, p in self.named_parameters() if name != "table"]
        return [{"params": [self.table], "weight_decay": 0.0}, {"params": mlps, "weight_decay": MLP_WEIGHT_DECAY}]

    adam: ClassVar[dict] = {"betas": (0.9, 0.99), "eps": 1e-15}

    def grid_features(self, points: torch.Tensor) -> torch.Tensor:
        """enc(x): the interpolated features of points (n, 3) in the scene box -> (n, L·F), level-major."""
        return self.grid(self.table, torch.clamp((points - self.lo) / self.extent, 0.0, 1.0))

    def spherical_harmonics(self, viewdirs: torch.Tensor) -> torch.Tensor:
        """SH(d) of unit directions (n, 3) -> (n, sh_degree²), as the graph computes it."""
        degree2 = viewdirs[:, DEGREE2[0]] * viewdirs[:, DEGREE2[1]]
        degree3 = degree2[:, DEGREE3[0]] * viewdirs[:, DEGREE3[1]]
        return functional.linear(torch.cat([viewdirs, degree2, degree3], -1), self.sh_matrix, self.sh_constant)

    def encode(self, points: torch.Tensor, viewdirs: torch.Tensor) -> torch.Tensor:
        """[enc(x) ‖ SH(d)]: (n, 3), (n, 3) -> (n, noise_dims)."""
        return torch.cat([self.grid_features(points), self.spherical_harmonics(viewdirs)], -1)

    def trunk_outputs(self, encoded_position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw density (n,) and the geometric feature (n, geo_features) from noisy grid features (n, L·F)."""
        out = self.density_linears[1](torch.relu(self.density_linears[0](encoded_position)))
        return out[:, 0], out[:, 1:]

    def view_branch(self, feature: torch.Tensor, encoded_dirs: torch.Tensor) -> tuple[torch.Tensor, list]:
        """Raw colour (n, 3) from the geometric feature and the noisy SH (n, sh_degree²), and the colour
        MLP's ReLU masks, all its Jacobian needs (`direction_jacobian`)."""
        h, masks = torch.cat([encoded_dirs, feature], -1), []
        for layer in self.colour_linears[:-1]:
            h = layer(h)
            masks.append(h > 0)
            h = torch.relu(h)
        return self.colour_linears[-1](h), masks

    def head_jacobian(self, masks: list) -> torch.Tensor:
        """∂raw colour/∂[SH ‖ geometric feature] at the masks of view_branch. -> (n, 3, dims + geo)."""
        rows = self.colour_linears[-1].weight.expand(masks[0].shape[0], 3, -1)
        for layer, mask in zip(reversed(self.colour_linears[:-1]), reversed(masks)):
            rows = (rows * mask[:, None, :]) @ layer.weight
        return rows

    def direction_jacobian(self, masks: list) -> torch.Tensor:
        """∂raw colour/∂SH (n, 3, sh_degree²)."""
        return self.head_jacobian(masks)[:, :, :self.config.direction_dims]

    def outputs_and_jacobian(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[raw colour ‖ raw density] (n, 4) and its exact Jacobian ∂/∂encoded (n, 4, noise_dims): both MLPs
        are ReLU nets, so each layer's backward is its weight times the forward's mask."""
        position = self.config.position_dims
        first = self.density_linears[0](encoded[:, :position])
        trunk_mask = first > 0
        out = self.density_linears[1](torch.relu(first))
        raw_rgb, masks = self.view_branch(out[:, 1:], encoded[:, position:])
        trunk_rows = (self.density_linears[1].weight * trunk_mask[:, None, :]) @ self.density_linears[0].weight
        head = self.head_jacobian(masks)  # (n, 3, sh + geo)
        dirs = self.config.direction_dims
        rgb_position = head[:, :, dirs:] @ trunk_rows[:, 1:]  # (n, 3, L·F)
        jacobian = torch.cat([torch.cat([rgb_position, head[:, :, :dirs]], -1),
                              torch.cat([trunk_rows[:, :1], trunk_rows.new_zeros(len(encoded), 1, dirs)], -1)], 1)
        return torch.cat([raw_rgb, out[:, :1]], -1), jacobian

    @staticmethod
    def density_of(raw: torch.Tensor) -> torch.Tensor:
        """σ = exp(min(raw, cap)) (nerfacto's trunc_exp forward, capped as the graph caps it)."""
        return torch.exp(torch.clamp_max(raw, DENSITY_EXPONENT_CAP))

    @staticmethod
    def raw_density_at(density: float) -> float:
        """The raw value whose σ is `density` (> 0): log σ."""
        return math.log(density)

    @staticmethod
    def zero_slope(raw: torch.Tensor) -> torch.Tensor:
        """Samples whose σ cannot move with their raw density: above the cap."""
        return raw >= DENSITY_EXPONENT_CAP

    def negligible(self, raw: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
        """Samples of rays (m, n_samples) whose colour the paper's method may leave out: exp density has no
        dead samples, so a ray's least opaque ones, σΔ smallest first, as long as their σΔ sum stays within
        NEGLIGIBLE_OPACITY. Left out (their density kept, their colour 0), they move the ray's colour by at
        most Σ w ≤ Σ σΔ (eq. 2: w = T(1 − e^(−σΔ)) ≤ σΔ): under half an 8-bit step. deltas: (m, n_samples)."""
        opacity = self.density_of(raw) * deltas
        order = opacity.argsort(-1)
        within = opacity.gather(-1, order).cumsum(-1) <= NEGLIGIBLE_OPACITY
        return torch.zeros_like(within).scatter(-1, order, within)

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ (n,) alone (occupancy-grid updates). points: (n, 3)."""
        return self.density_of(self.raw_density(self.grid_features(points)))
