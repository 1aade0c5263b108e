"""The defaults every torch field kind starts from (train.scene.field_kinds.Field).

A kind's module subclasses `FieldModule` and writes what only it knows: its encodings (`encode`), its trunk
(`trunk_outputs`: raw density and the feature its colour head reads, from the position segment), its colour
head (`colour_head`), and its density activation (`density_of`, `raw_density_at`, `zero_slope`). The forward
pass with noise (paper eq. 4–5), the raw outputs, and the exact Jacobians the solvers need follow here, the
Jacobians by torch.func; the built-in kinds override those with hand-written reverse passes, which cost a
fraction of autograd's on their ReLU nets.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import nn


def noisy_forward(field, points: torch.Tensor, viewdirs: torch.Tensor, noise: torch.Tensor | None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Every field kind's forward (eq. 4–5): its encodings plus the optional noise (n, noise_dims), its raw
    outputs, sigmoid colour (n, 3) and its density activation (n,). points, viewdirs: (n, 3)."""
    encoded = field.encode(points, viewdirs)
    if noise is not None:
        encoded = encoded + noise
    raw_rgb, raw_density = field.raw_outputs(encoded)
    return torch.sigmoid(raw_rgb), field.density_of(raw_density)


class FieldModule(nn.Module):
    """A field kind's module: `config` (with position_dims, direction_dims, noise_dims, has_view_branch) and
    the Field protocol's methods, derived from the few a kind must write (the module docstring)."""

    adam: ClassVar[dict] = {}  # torch's Adam defaults

    def colour_head(self, feature: torch.Tensor, encoded_dirs: torch.Tensor) -> torch.Tensor:
        """Raw colour (n, 3) from the trunk's feature and the direction segment (n, direction_dims)."""
        raise NotImplementedError

    def forward(self, points: torch.Tensor, viewdirs: torch.Tensor, noise: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """rgb (n, 3) in [0, 1] and σ (n,) ≥ 0 at points (n, 3) seen along viewdirs (n, 3), with optional
        noise (n, noise_dims) added to the encodings."""
        return noisy_forward(self, points, viewdirs, noise)

    def raw_outputs(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-activation colour (n, 3) and density (n,) of noisy encodings (n, noise_dims)."""
        density, feature = self.trunk_outputs(encoded[:, :self.config.position_dims])
        return self.view_branch(feature, encoded[:, self.config.position_dims:])[0], density

    def raw_density(self, encoded_position: torch.Tensor) -> torch.Tensor:
        """Pre-activation density (n,) from the position segment alone."""
        return self.trunk_outputs(encoded_position)[0]

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ (n,) at points (n, 3) (occupancy-grid updates)."""
        encoded = self.encode(points, torch.zeros_like(points))
        return self.density_of(self.raw_density(encoded[:, :self.config.position_dims]))

    def view_branch(self, feature: torch.Tensor, encoded_dirs: torch.Tensor) -> tuple[torch.Tensor, object]:
        """Raw colour (n, 3), and what direction_jacobian needs: here the head's inputs."""
        return self.colour_head(feature, encoded_dirs), (feature, encoded_dirs)

    def direction_jacobian(self, state: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """∂raw colour/∂direction segment (n, 3, direction_dims), per sample by torch.func."""
        feature, encoded_dirs = state

        def head(one_feature, one_dirs):
            return self.colour_head(one_feature[None], one_dirs[None])[0]

        return torch.func.vmap(torch.func.jacrev(head, argnums=1))(feature, encoded_dirs)

    def outputs_and_jacobian(self, encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[raw colour ‖ raw density] (n, 4) and its exact Jacobian ∂/∂encoded (n, 4, noise_dims), per sample
        by torch.func."""
        def outputs(one):
            raw_rgb, raw_density = self.raw_outputs(one[None])
            return torch.cat([raw_rgb[0], raw_density]), torch.cat([raw_rgb[0], raw_density])

        jacobian, raw = torch.func.vmap(torch.func.jacrev(outputs, has_aux=True))(encoded)
        return raw, jacobian

    def negligible(self, raw: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
        """Samples of rays (m, n_samples) the paper's method may leave out between checks: those whose density
        cannot move (zero_slope), whose weight in eq. 2 and gradient are exactly zero."""
        return self.zero_slope(raw)

    def parameter_groups(self) -> list[dict]:
        """The optimizer's groups: one."""
        return [{"params": list(self.parameters())}]
