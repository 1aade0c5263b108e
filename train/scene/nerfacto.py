"""The `nerfacto` field in torch: nerfstudio's nerfacto field and proposal networks, as imported
(train.scene.import_nerfstudio); runtime.fields.nerfacto documents the math, which this module computes
with the graph's operations.

It is a hash-grid field (train.scene.hashgrid) whose grid reads scene-contracted points in the run's
implementation (`tcnn` or `torch`), whose SH are that implementation's, and whose density is scaled
(σ = density_scale·exp(raw)) and zero off the contracted cube. The contraction's cube edge is only reached
by points beyond ~8·10^6 units, so the noisy raw outputs the solvers use (without that factor) are the
forward's wherever a secret view samples.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from noisenerf.runtime.fields.hashgrid import DENSITY_EXPONENT_CAP
from noisenerf.runtime.fields.nerfacto import NERFACTO, TORCH_SH_SIGNS, cell_offset, grid_layout
from noisenerf.train.scene.field_module import noisy_forward
from noisenerf.train.scene.hashgrid import GridEncoding, GridFieldDims, HashGridField


@dataclass(frozen=True)
class ProposalConfig:
    """One proposal network (nerfstudio's HashMLPDensityField): its grid and hidden width."""

    features: int
    log2_table: int
    scales: tuple[float, ...]
    hidden: int

    @property
    def grid_dims(self) -> int:
        return len(self.scales) * self.features


@dataclass(frozen=True)
class SamplerConfig:
    """nerfacto's proposal sampler (runtime.proposal)."""

    proposal_samples: tuple[int, ...]
    samples: int
    histogram_padding: float
    near: float
    far: float


@dataclass(frozen=True)
class GridSamplerConfig:
    """nerfstudio's instant-ngp sampler, nerfacc's occupancy grid (runtime.grid_marching): occupancy is one bit
    per cell, C order [level, x, y, z], base64 (runtime.fields.nerfacto.checked_grid_sampler)."""

    step: float
    cone_angle: float
    near: float
    far: float
    levels: int
    resolution: int
    aabb: tuple[float, ...]
    occupancy: str


@dataclass(frozen=True)
class NerfactoConfig(GridFieldDims):
    """Architecture of an imported nerfacto field (runtime.fields.nerfacto's keys)."""

    kind: ClassVar[str] = "nerfacto"
    implementation: str
    features: int
    log2_table: int
    scales: tuple[float, ...]
    density_hidden: int
    geo_features: int
    sh_degree: int
    colour_hidden: int
    colour_layers: int
    density_scale: float
    proposals: tuple[ProposalConfig, ...]
    sampler: SamplerConfig | GridSamplerConfig  # the proposal sampler, or instant-ngp's grid where proposals is ()

    @property
    def position_dims(self) -> int:
        return len(self.scales) * self.features

    def to_dict(self) -> dict:
        data = dataclasses.asdict(self)
        lists = lambda d: {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}  # noqa: E731
        return {"kind": self.kind, **lists(data), "proposals": [lists(p) for p in data["proposals"]],
                "sampler": lists(data["sampler"])}

    @staticmethod
    def from_dict(data: dict) -> "NerfactoConfig":
        checked = NERFACTO.checked(data, "scene")
        tuples = lambda d: {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}  # noqa: E731
        return NerfactoConfig(**{
            **tuples({k: v for k, v in checked.items() if k != "kind"}),
            "proposals": tuple(ProposalConfig(**tuples(p)) for p in checked["proposals"]),
            "sampler": (SamplerConfig if checked["proposals"] else GridSamplerConfig)(**tuples(checked["sampler"]))})


def growth_factor(num_levels: int, base_res: int, max_res: int) -> float:
    """nerfstudio's per-level scale b = exp((ln max_res − ln base_res)/(L − 1)), numpy float64."""
    return float(np.exp((np.log(max_res) - np.log(base_res)) / (num_levels - 1))) if num_levels > 1 else 1.0


def grid_scales(implementation: str, num_levels: int, base_res: int, max_res: int) -> tuple[float, ...]:
    """Per-level float32 scales as each implementation computes them: nerfstudio's torch grid
    floor(base_res·b^l) with b^l a float32 torch power; tiny-cuda-nn's exp2(l·log2 b)·N_min − 1 in float32."""
    b = growth_factor(num_levels, base_res, max_res)
    if implementation == "torch":
        return tuple(float(v) for v in torch.floor(base_res * b ** torch.arange(num_levels)).tolist())
    levels = np.arange(num_levels, dtype=np.float32)
    scales = np.exp2(levels * np.log2(np.float32(b))) * np.float32(base_res) - np.float32(1)
    return tuple(float(v) for v in scales.astype(np.float32))


def contracted_unit(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """runtime.fields.nerfacto.contracted_unit: the grid input (n, 3) and the selector (n, 1)."""
    norm = points.abs().amax(-1, keepdim=True)
    contracted = torch.where(norm < 1, points, (2 - 1 / norm) * (points / norm))
    unit = (contracted + 2) / 4
    selector = ((unit > 0) & (unit < 1)).all(-1, keepdim=True).to(points.dtype)
    return unit * selector, selector


def scaled_exp(raw: torch.Tensor, scale: float) -> torch.Tensor:
    """nerfacto's density activation, σ = scale·exp(min(raw, cap)) (runtime.fields.nerfacto.activated_density)."""
    return scale * torch.exp(torch.clamp_max(raw, DENSITY_EXPONENT_CAP))


class ProposalNetwork(nn.Module):
    """σ of a proposal network at points (n, 3) -> (n,)."""

    def __init__(self, config: ProposalConfig, implementation: str, density_scale: float):
        super().__init__()
        levels = grid_layout(implementation, config.scales, config.log2_table)
        self.table = nn.Parameter(torch.zeros(levels.total_rows, config.features))
        self.grid = GridEncoding(levels, config.log2_table, config.features, cell_offset(implementation))
        self.linears = nn.ModuleList([nn.Linear(config.grid_dims, config.hidden), nn.Linear(config.hidden, 1)])
        self.density_scale = density_scale

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        unit, selector = contracted_unit(points)
        raw = self.linears[1](torch.relu(self.linears[0](self.grid(self.table, unit))))
        return (scaled_exp(raw, self.density_scale) * selector)[:, 0]


class NerfactoField(HashGridField):
    """F(enc(contract(x)) + δ_x, SH(d) + δ_d) -> (rgb, σ), nerfacto's field; `proposals` its proposal networks
    (none for nerfstudio's instant-ngp)."""

    def __init__(self, config: NerfactoConfig):
        nn.Module.__init__(self)
        self.config = config
        levels = grid_layout(config.implementation, config.scales, config.log2_table)
        self.table = nn.Parameter(torch.zeros(levels.total_rows, config.features))
        self.grid = GridEncoding(levels, config.log2_table, config.features, cell_offset(config.implementation))
        self.register_sh(config.direction_dims, TORCH_SH_SIGNS if config.implementation == "torch" else None)
        self.add_mlps(config)
        self.proposals = nn.ModuleList([ProposalNetwork(p, config.implementation, config.density_scale)
                                        for p in config.proposals])

    def grid_features(self, points: torch.Tensor) -> torch.Tensor:
        return self.grid(self.table, contracted_unit(points)[0])

    def spherical_harmonics(self, viewdirs: torch.Tensor) -> torch.Tensor:
        """tiny-cuda-nn's SH of d, or nerfstudio's torch SH of (d + 1)/2 (rows flipped in register_sh)."""
        return super().spherical_harmonics(viewdirs if self.config.implementation == "tcnn" else (viewdirs + 1) / 2)

    def density_of(self, raw: torch.Tensor) -> torch.Tensor:
        return scaled_exp(raw, self.config.density_scale)

    def raw_density_at(self, density: float) -> float:
        return math.log(density / self.config.density_scale)

    def forward(self, points: torch.Tensor, viewdirs: torch.Tensor, noise: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        rgb, sigma = noisy_forward(self, points, viewdirs, noise)
        return rgb, sigma * contracted_unit(points)[1][:, 0]

    def density(self, points: torch.Tensor) -> torch.Tensor:
        return super().density(points) * contracted_unit(points)[1][:, 0]

    def appearance_forward(self, points: torch.Tensor, viewdirs: torch.Tensor, appearance: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        """rgb (n, 3) and σ (n,) with a per-image appearance term (n, colour_hidden) added to the colour MLP's first
        pre-activation: nerfacto's appearance embedding through its share of that layer's weight, as fitting
        trains it (`fold_appearance` makes it part of the bias for good)."""
        raw_density, feature = self.trunk_outputs(self.grid_features(points))
        h = torch.cat([self.spherical_harmonics(viewdirs), feature], -1)
        for index, layer in enumerate(self.colour_linears[:-1]):
            h = torch.relu(layer(h) + appearance if index == 0 else layer(h))
        rgb = torch.sigmoid(self.colour_linears[-1](h))
        return rgb, self.density_of(raw_density) * contracted_unit(points)[1][:, 0]

    def fold_appearance(self, appearance: torch.Tensor) -> None:
        """Add a fixed appearance term (colour_hidden,) to the colour MLP's first bias: the eval render's (the mean
        embedding's, as nerfstudio renders held-out views and the import folds it)."""
        with torch.no_grad():
            self.colour_linears[0].bias += appearance.to(self.colour_linears[0].bias)
