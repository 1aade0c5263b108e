"""The standard NeRF MLP, layer for layer nerf-pytorch's, with the Noise-NeRF noise port.

Noise δ is added to the concatenated encodings [γ(x) ‖ γ(d)] (paper eq. 4–5) before the first layer, so
the skip connection sees the noisy γ(x) too, exactly as if the encoded input itself had moved.
Module names match nerf-pytorch's state dict, so its checkpoints load without renaming.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import nn

from noisenerf.runtime.encoding import encoding_dims
from noisenerf.train.scene.field_module import FieldModule


@dataclass(frozen=True)
class MlpConfig:
    """Architecture of one NeRF MLP (nerf-pytorch's netdepth, netwidth, multires, multires_views), the
    `mlp` field kind (runtime.fields.mlp), whose architecture names no kind."""

    kind: ClassVar[str] = "mlp"
    depth: int = 8
    width: int = 256
    skips: tuple[int, ...] = (4,)
    xyz_freqs: int = 10
    dir_freqs: int = 4
    use_viewdirs: bool = True

    @property
    def xyz_dims(self) -> int:
        return encoding_dims(self.xyz_freqs)

    @property
    def dir_dims(self) -> int:
        return encoding_dims(self.dir_freqs) if self.use_viewdirs else 0

    @property
    def noise_dims(self) -> int:
        """Width of the noise vector at one sample: the whole encoded input, 90 for the standard NeRF."""
        return self.xyz_dims + self.dir_dims

    @property
    def position_dims(self) -> int:
        """The noise the trunk reads: γ(x)."""
        return self.xyz_dims

    @property
    def direction_dims(self) -> int:
        return self.dir_dims

    @property
    def has_view_branch(self) -> bool:
        """Whether colour has a head of its own that reads the direction segment (and the trunk's feature)."""
        return self.use_viewdirs

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def in_box(self, aabb) -> "MlpConfig":
        """The config for a scene in this box: unchanged (γ(x) spans all space)."""
        return self

    @staticmethod
    def from_dict(data: dict) -> "MlpConfig":
        return MlpConfig(**{**data, "skips": tuple(data.get("skips", (4,)))})


def positional_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """γ(x), the torch twin of noisenerf.runtime.encoding.positional_encoding. (..., 3) -> (..., 3 + 6L)."""
    freqs = 2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)
    scaled = x[..., None, :] * freqs[:, None]  # (..., L, 3)
    bands = torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2)  # (..., L, 2, 3)
    return torch.cat([x, bands.flatten(-3)], dim=-1)


class MlpField(FieldModule):
    """F(γ(x) + δ_x, γ(d) + δ_d) -> (rgb, σ) with sigmoid colour and ReLU density."""

    def __init__(self, config: MlpConfig):
        super().__init__()
        self.config = config
        width, xyz = config.width, config.xyz_dims
        self.pts_linears = nn.ModuleList(
            [nn.Linear(xyz, width)]
            + [nn.Linear(width + xyz if i in config.skips else width, width) for i in range(config.depth - 1)]
        )
        if config.use_viewdirs:
            self.views_linears = nn.ModuleList([nn.Linear(config.dir_dims + width, width // 2)])
            self.feature_linear = nn.Linear(width, width)
            self.alpha_linear = nn.Linear(width, 1)
            self.rgb_linear = nn.Linear(width // 2, 3)
        else:
            self.output_linear = nn.Linear(width, 4)

    def encode(self, points: torch.Tensor, viewdirs: torch.Tensor) -> torch.Tensor:
        """[γ(x) ‖ γ(d)]: (n, 3), (n, 3) -> (n, noise_dims)."""
        parts = [positional_encoding(points, self.config.xyz_freqs)]
        if self.config.use_viewdirs:
            parts.append(positional_encoding(viewdirs, self.config.dir_freqs))
        return torch.cat(parts, dim=-1)

    def trunk(self, encoded_xyz: torch.Tensor) -> torch.Tensor:
        """The density MLP with its skip connection. (n, xyz_dims) -> (n, width)."""
        h = encoded_xyz
        for i, layer in enumerate(self.pts_linears):
            h = torch.relu(layer(h))
            if i in self.config.skips:
                h = torch.cat([encoded_xyz, h], dim=-1)
        return h

    def raw_outputs(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-activation colour and density. encoded: (n, noise_dims) -> (n, 3), (n,)."""
        encoded_xyz = encoded[..., : self.config.xyz_dims]
        if not self.config.use_viewdirs:
            raw = self.output_linear(self.trunk(encoded_xyz))
            return raw[..., :3], raw[..., 3]
        density, feature = self.trunk_outputs(encoded_xyz)
        raw_rgb, _ = self.view_branch(feature, encoded[..., self.config.xyz_dims:])
        return raw_rgb, density

    def trunk_outputs(self, encoded_xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What the position alone decides (view-direction fields): raw density (n,) and the feature the view
        branch reads (n, width). encoded_xyz: (n, xyz_dims)."""
        h = self.trunk(encoded_xyz)
        return self.alpha_linear(h)[..., 0], self.feature_linear(h)

    def view_branch(self, feature: torch.Tensor, encoded_dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw colour (n, 3) from the trunk's feature (n, width) and the encoded direction (n, dir_dims), and
        the branch's pre-activation (n, width/2), whose ReLU mask is all view_branch_rows needs."""
        pre = self.views_linears[0](torch.cat([feature, encoded_dirs], dim=-1))
        return self.rgb_linear(torch.relu(pre)), pre

    def direction_jacobian(self, pre: torch.Tensor) -> torch.Tensor:
        """∂raw colour/∂γ(d) (n, 3, dir_dims) at the view branch's pre-activation pre."""
        return self.view_branch_rows(pre, slice(self.config.width, None))

    def view_branch_rows(self, pre: torch.Tensor, inputs: slice = slice(None)) -> torch.Tensor:
        """∂raw colour/∂(the branch's input [feature ‖ encoded dirs])[inputs] at its pre-activation pre
        (n, width/2) -> (n, 3, len(inputs)): one ReLU layer, so its weight times the mask."""
        return ((pre > 0)[:, None, :] * self.rgb_linear.weight) @ self.views_linears[0].weight[:, inputs]

    def outputs_and_jacobian(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[raw colour ‖ raw density] (n, 4) and its exact Jacobian with respect to the encoded input
        (n, 4, noise_dims), by one hand-written reverse pass that carries all four rows at once: the net
        is piecewise linear, so each layer's backward is its weight times the forward's ReLU mask. It
        costs about one forward more than four (autograd's four separate backward passes took ~2x as
        long). encoded: (n, noise_dims)."""
        xyz_dims = self.config.xyz_dims
        encoded_xyz = encoded[:, :xyz_dims]
        masks, h = [], encoded_xyz
        for i, layer in enumerate(self.pts_linears):
            h = layer(h)
            masks.append(h > 0)
            h = torch.relu(h)
            if i in self.config.skips:
                h = torch.cat([encoded_xyz, h], dim=-1)
        if self.config.use_viewdirs:
            raw_rgb, view_pre = self.view_branch(self.feature_linear(h), encoded[:, xyz_dims:])
            raw = torch.cat([raw_rgb, self.alpha_linear(h)], dim=-1)
            # rows 0-2: colour through the view branch; row 3: density straight from the trunk
            rgb_in = self.view_branch_rows(view_pre)  # (n, 3, width + dir_dims)
            width = self.config.width
            rows = torch.cat([rgb_in[:, :, :width] @ self.feature_linear.weight,
                              self.alpha_linear.weight.expand(encoded.shape[0], 1, width)], dim=1)
            direction_part = torch.cat([rgb_in[:, :, width:], rgb_in.new_zeros(encoded.shape[0], 1, self.config.dir_dims)],
                                       dim=1)
        else:
            raw = self.output_linear(h)
            rows = self.output_linear.weight.expand(encoded.shape[0], 4, -1)
            direction_part = None
        xyz_part = torch.zeros(encoded.shape[0], 4, xyz_dims, dtype=encoded.dtype, device=encoded.device)
        for i in reversed(range(len(self.pts_linears))):
            if i in self.config.skips:
                xyz_part = xyz_part + rows[:, :, :xyz_dims]
                rows = rows[:, :, xyz_dims:]
            rows = (rows * masks[i][:, None, :]) @ self.pts_linears[i].weight
        xyz_part = xyz_part + rows
        jacobian = xyz_part if direction_part is None else torch.cat([xyz_part, direction_part], dim=-1)
        return raw, jacobian

    def density_layers(self) -> list[nn.Linear]:
        """The layers a density alone runs through (the bench's cost model): the trunk and the density layer."""
        return [*self.pts_linears, self.alpha_linear if self.config.use_viewdirs else self.output_linear]



    @staticmethod
    def density_of(raw: torch.Tensor) -> torch.Tensor:
        """σ = ReLU(raw)."""
        return torch.relu(raw)

    @staticmethod
    def raw_density_at(density: float) -> float:
        """The raw value whose σ is `density` (> 0): itself."""
        return density

    @staticmethod
    def zero_slope(raw: torch.Tensor) -> torch.Tensor:
        """Samples whose σ cannot move with their raw density: ReLU's off side."""
        return raw <= 0



    def raw_density(self, encoded_xyz: torch.Tensor) -> torch.Tensor:
        """Pre-activation density alone, without the view branch. encoded_xyz: (n, xyz_dims) -> (n,)."""
        h = self.trunk(encoded_xyz)
        return self.alpha_linear(h)[..., 0] if self.config.use_viewdirs else self.output_linear(h)[..., 3]

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ (n,) alone, without the view branch (for occupancy-grid updates). points: (n, 3)."""
        return self.density_of(self.raw_density(positional_encoding(points, self.config.xyz_freqs)))
