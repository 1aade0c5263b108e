"""The field kinds in torch: which module implements each kind, and the protocol the rest of the code uses.

A field kind (runtime.fields) is registered here with its config dataclass and its nn.Module: `mlp`
(train.scene.field: MlpConfig, MlpField), `hashgrid` (train.scene.hashgrid: HashGridConfig,
HashGridField) and `nerfacto` (train.scene.nerfacto: NerfactoConfig, NerfactoField, imported only), each module
a train.scene.field_module.FieldModule (the protocol's defaults). Fitting, the render pipeline, the occupancy grid,
the secret view and the solvers reach a field only through `Field`; nothing else branches on a kind.
"""

from __future__ import annotations

from typing import ClassVar, Protocol

import torch

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import DEFAULT_KIND
from noisenerf.train.scene.field import MlpConfig, MlpField
from noisenerf.train.scene.hashgrid import HashGridConfig, HashGridField
from noisenerf.train.scene.nerfacto import NerfactoConfig, NerfactoField

FieldConfigs = MlpConfig | HashGridConfig | NerfactoConfig
CLASSES = {"mlp": (MlpConfig, MlpField), "hashgrid": (HashGridConfig, HashGridField),
           "nerfacto": (NerfactoConfig, NerfactoField)}


class Field(Protocol):
    """What every field kind's module provides (shapes for n samples; "position" and "direction" are the
    noise segments, the trunk reading the first and the colour head the second with the trunk's feature)."""

    config: FieldConfigs  # with position_dims, direction_dims, noise_dims, has_view_branch
    adam: ClassVar[dict]  # the optimizer's arguments besides the learning rate

    def encode(self, points: torch.Tensor, viewdirs: torch.Tensor) -> torch.Tensor:
        """The clean encodings the noise adds to: (n, 3), (n, 3) -> (n, noise_dims)."""

    def raw_outputs(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-activation colour (n, 3) and density (n,) of noisy encodings (n, noise_dims)."""

    def trunk_outputs(self, encoded_position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw density (n,) and the feature the colour head reads, from the position segment."""

    def view_branch(self, feature: torch.Tensor, encoded_dirs: torch.Tensor) -> tuple[torch.Tensor, object]:
        """Raw colour (n, 3) and what direction_jacobian needs."""

    def direction_jacobian(self, state: object) -> torch.Tensor:
        """∂raw colour/∂direction segment (n, 3, direction_dims)."""

    def outputs_and_jacobian(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[raw colour ‖ raw density] (n, 4) and its exact Jacobian ∂/∂noise (n, 4, noise_dims)."""

    def raw_density(self, encoded_position: torch.Tensor) -> torch.Tensor:
        """Pre-activation density (n,) from the position segment alone."""

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ (n,) at points (n, 3)."""

    def density_of(self, raw: torch.Tensor) -> torch.Tensor:
        """The density activation (the colour's is a sigmoid for every kind)."""

    def raw_density_at(self, density: float) -> float:
        """The density activation's inverse at a density > 0."""

    def zero_slope(self, raw: torch.Tensor) -> torch.Tensor:
        """Samples whose density cannot move with their raw density (bool, raw's shape)."""

    def negligible(self, raw: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
        """Samples of rays (m, n_samples) the paper's method may leave out between checks (bool)."""

    def parameter_groups(self) -> list[dict]:
        """The optimizer's parameter groups (weight decay per group)."""

    def density_layers(self) -> list[torch.nn.Linear]:
        """The linear layers a density alone runs through (cost models)."""

    def __call__(self, points: torch.Tensor, viewdirs: torch.Tensor, noise: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """rgb (n, 3) in [0, 1] and σ (n,) ≥ 0."""


def config_from_dict(data: dict) -> FieldConfigs:
    """A network's config from scene.json; the kind it names (an `mlp` where it names none)."""
    kind = data.get("kind", DEFAULT_KIND)
    if kind not in CLASSES:
        raise UserError(f"unknown field kind {kind!r}; this noisenerf knows {sorted(CLASSES)}")
    return CLASSES[kind][0].from_dict(data)


def build_field(config: FieldConfigs) -> Field:
    """A new field of the config's kind, freshly initialised (torch's global generator)."""
    return CLASSES[config.kind][1](config)

