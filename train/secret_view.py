"""A secret view in torch: one tile's rays, sampled densely, rendered with per-pixel noise.

The encodings γ(x), γ(d) of its samples never change while noise is trained, so they are computed once;
each evaluation then runs only the MLP on γ + δ. Noise has shape (n_rays, 1, dims) for the "ray" layout
(one vector shared by a ray's samples) or (n_rays, n_samples, dims) for the paper's "sample" layout.
"""

from __future__ import annotations

import numpy as np
import torch

from noisenerf.runtime.bundle import Tile
from noisenerf.runtime.render import RenderConfig, sample_along
from noisenerf.runtime.reveal import tile_rays
from noisenerf.runtime.sampling import sample_positions
from noisenerf.train.field import NeRFField
from noisenerf.train.rendering import composite, render_weights


class SecretView:
    """Precomputed encodings and intervals of a tile's rays; renders any subset of them with noise."""

    def __init__(self, field: NeRFField, tile: Tile, render: RenderConfig, device: torch.device):
        rays = tile_rays(tile, render)
        points, deltas = sample_along(rays, sample_positions(tile.sampling))
        n_rays, n_samples = deltas.shape
        viewdirs = np.broadcast_to(rays.viewdirs[:, None, :], points.shape)
        self.field = field
        with torch.no_grad():
            self.encoded = field.encode(torch.from_numpy(points.reshape(-1, 3)).to(device),
                                        torch.from_numpy(viewdirs.reshape(-1, 3).copy()).to(device)
                                        ).reshape(n_rays, n_samples, -1)
        self.deltas = torch.from_numpy(deltas).to(device)
        self.background = torch.tensor(render.background, dtype=torch.float32, device=device)

    @property
    def n_rays(self) -> int:
        return self.encoded.shape[0]

    @property
    def n_samples(self) -> int:
        return self.encoded.shape[1]

    def raw(self, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-activation colour (m, n_samples, 3) and density (m, n_samples) of rays `index` (m,) with
        noise (m, 1 or n_samples, dims)."""
        encoded = self.encoded[index] + noise
        raw_rgb, raw_density = self.field.raw_outputs(encoded.reshape(-1, encoded.shape[-1]))
        m = index.shape[0]
        return raw_rgb.reshape(m, self.n_samples, 3), raw_density.reshape(m, self.n_samples)

    def shade(self, index: torch.Tensor, raw_rgb: torch.Tensor, raw_density: torch.Tensor) -> torch.Tensor:
        """Colours (m, 3) of rays `index` (m,) from their raw outputs (m, n_samples, 3), (m, n_samples)."""
        weights = render_weights(torch.relu(raw_density), self.deltas[index])
        return composite(weights, torch.sigmoid(raw_rgb), self.background)

    def render(self, index: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Colours (m, 3) of rays `index` (m,) with noise (m, 1 or n_samples, dims)."""
        return self.shade(index, *self.raw(index, noise))
