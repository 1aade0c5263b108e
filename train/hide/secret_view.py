"""A secret view in torch: one tile's rays, sampled densely, rendered with per-pixel noise.

The encodings of its samples (the field kind's segments: γ(x), γ(d) for the MLP; grid features and SH
for the hash grid) never change while noise is trained, so they are computed once; each evaluation then
runs only the networks on encoding + δ. Noise has shape (n_rays, 1, dims) for the "ray" layout
(one vector shared by a ray's samples) or (n_rays, n_samples, dims) for the paper's "sample" layout.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from noisenerf.runtime.bundle import Tile
from noisenerf.runtime.rays import camera_ray_batch
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import sample_along, sample_positions
from noisenerf.train.scene.field_kinds import Field
from noisenerf.train.scene.render import composite, render_weights


ENCODING_CACHE_BYTES = 1 << 30  # a view's encodings up to this size are computed once and kept
BLAS_ROWS = 64  # a subset of a batch's rows is evaluated in multiples of this (SecretView.raw_of)
CACHE_ROWS = 64 * BLAS_ROWS  # rows a density check evaluates at once: their activations stay in cache


def pass_slices(n_rays: int, n_samples: int, pass_samples: int) -> list[slice]:
    """Contiguous ray ranges of at most pass_samples samples each (at least one ray per pass)."""
    step = max(1, pass_samples // n_samples)
    return [slice(s, min(s + step, n_rays)) for s in range(0, n_rays, step)]


class SecretView:
    """A tile's rays and sample intervals; renders any subset of them with noise. Encodings are kept when
    they are small (every exact view, paper views up to ~180k pixels); beyond that (the paper's 64
    samples at 800²: 14.7 GB) each batch of rays is encoded as it is rendered, so device memory follows
    the batch, not the view."""

    def __init__(self, field: Field, tile: Tile, render: RenderConfig, device: torch.device):
        rays = camera_ray_batch(tile.camera, render)
        points, deltas = sample_along(rays.origins, rays.directions, sample_positions(tile.sampling))
        self.field, self.device = field, device
        self.points = torch.from_numpy(np.ascontiguousarray(points)).to(device)  # (n_rays, n_samples, 3)
        self.viewdirs = torch.from_numpy(np.ascontiguousarray(rays.viewdirs)).to(device)  # (n_rays, 3)
        self.deltas = torch.from_numpy(deltas).to(device)
        self.background = torch.tensor(render.background, dtype=torch.float32, device=device)
        size = self.n_rays * self.n_samples * self.noise_dims * 4
        self.cached = self.encode(torch.arange(self.n_rays, device=device)) if size <= ENCODING_CACHE_BYTES else None

    def subset(self, index: torch.Tensor) -> SecretView:
        """A view of rays `index` (m,) alone, ray i being ray index[i] here, with the same field: what a
        worker process needs to solve one part (encodings included, not the whole tile's)."""
        part = copy.copy(self)
        part.points, part.viewdirs, part.deltas = self.points[index], self.viewdirs[index], self.deltas[index]
        part.cached = None if self.cached is None else self.cached[index]
        return part

    @property
    def n_rays(self) -> int:
        return self.points.shape[0]

    @property
    def n_samples(self) -> int:
        return self.points.shape[1]

    @property
    def noise_dims(self) -> int:
        return self.field.config.noise_dims

    def encode(self, index: torch.Tensor) -> torch.Tensor:
        """[γ(x) ‖ γ(d)] of rays `index` (m,) at every sample -> (m, n_samples, noise_dims)."""
        points = self.points[index]
        viewdirs = self.viewdirs[index, None, :].expand_as(points)
        with torch.no_grad():
            return self.field.encode(points.reshape(-1, 3), viewdirs.reshape(-1, 3)).reshape(*points.shape[:2], -1)

    def encodings(self, index: torch.Tensor) -> torch.Tensor:
        """The clean encodings of rays `index` (m,), kept or computed. -> (m, n_samples, noise_dims)."""
        return self.cached[index] if self.cached is not None else self.encode(index)

    def noisy_encodings(self, index: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """γ + δ (paper eq. 4) of rays `index` (m,) with noise (m, 1 or n_samples, dims)
        -> (m, n_samples, dims): what the field's noise port computes, from the kept encodings."""
        return self.encodings(index) + noise

    def raw(self, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-activation colour (m, n_samples, 3) and density (m, n_samples) of rays `index` (m,) with
        noise (m, 1 or n_samples, dims)."""
        encoded = self.noisy_encodings(index, noise)
        raw_rgb, raw_density = self.field.raw_outputs(encoded.reshape(-1, encoded.shape[-1]))
        m = index.shape[0]
        return raw_rgb.reshape(m, self.n_samples, 3), raw_density.reshape(m, self.n_samples)

    def raw_density(self, index: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Pre-activation density (m, n_samples) of rays `index` (m,) with noise (m, 1 or n_samples, dims),
        without the colour branch."""
        encoded = self.noisy_encodings(index, noise)[..., :self.field.config.position_dims]
        return self.densities(encoded.reshape(-1, encoded.shape[-1])).reshape(encoded.shape[:2])

    def sample_encodings(self, index: torch.Tensor, samples: torch.Tensor) -> torch.Tensor:
        """The clean encodings of `samples` (s,), positions in the flattened (m, n_samples) of rays `index`
        (m,) -> (s, noise_dims)."""
        if self.cached is not None:
            return self.cached[index[samples // self.n_samples], samples % self.n_samples]
        return self.encode(index).flatten(0, 1)[samples]

    def raw_density_of(self, index: torch.Tensor, noise_rows: torch.Tensor, samples: torch.Tensor, fill: torch.Tensor
                       ) -> torch.Tensor:
        """As raw_density, evaluating only `samples` (s,), positions in the flattened (m, n_samples) of rays
        `index` (m,), with their noise rows (s, dims); the others keep their density in fill (m, n_samples)."""
        encoded = (self.sample_encodings(index, samples) + noise_rows)[:, :self.field.config.position_dims]
        return fill.flatten().index_put((samples,), self.densities(encoded)).reshape(fill.shape)

    def densities(self, encoded_xyz: torch.Tensor) -> torch.Tensor:
        """The field's raw density of rows (n, position_dims), CACHE_ROWS at a time -> (n,)."""
        return torch.cat([self.field.raw_density(encoded_xyz[start:start + CACHE_ROWS])
                          for start in range(0, len(encoded_xyz), CACHE_ROWS)] or [encoded_xyz.new_zeros(0)])

    def raw_of(self, index: torch.Tensor, noise_rows: torch.Tensor, samples: torch.Tensor, fill: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """As raw, evaluating only `samples` (s,), positions in the flattened (m, n_samples) of rays `index`
        (m,), with their noise rows (s, dims); the others take their density from fill (m, n_samples) and
        colour 0. Rows are padded to a multiple of BLAS_ROWS so BLAS computes each one as it would in the
        full batch (its tail kernel rounds differently)."""
        encoded = self.sample_encodings(index, samples) + noise_rows
        raw_rgb, raw_density = self.field.raw_outputs(torch.cat([encoded, encoded[:1].expand(-len(encoded) % BLAS_ROWS, -1)]))
        n = samples.numel()
        density = fill.flatten().index_put((samples,), raw_density[:n])
        rgb = encoded.new_zeros(fill.numel(), 3).index_put((samples,), raw_rgb[:n])
        return rgb.reshape(*fill.shape, 3), density.reshape(fill.shape)

    def outputs_and_jacobian(self, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Single-sample views: [raw colour ‖ raw density] (m, 4) of rays `index` (m,) with noise (m, 1, dims),
        and its exact Jacobian ∂/∂noise (m, 4, dims), the field's input Jacobian (noise adds to the input)."""
        return self.field.outputs_and_jacobian(self.noisy_encodings(index, noise)[:, 0])

    def shade(self, index: torch.Tensor, raw_rgb: torch.Tensor, raw_density: torch.Tensor) -> torch.Tensor:
        """Colours (m, 3) of rays `index` (m,) from their raw outputs (m, n_samples, 3), (m, n_samples)."""
        weights = render_weights(self.field.density_of(raw_density), self.deltas[index])
        return composite(weights, torch.sigmoid(raw_rgb), self.background)

    def render(self, index: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Colours (m, 3) of rays `index` (m,) with noise (m, 1 or n_samples, dims)."""
        return self.shade(index, *self.raw(index, noise))

    def render_all(self, noise: torch.Tensor, pass_samples: int) -> torch.Tensor:
        """Colours (n_rays, 3) of the whole view, without gradients, in passes of at most pass_samples
        samples; noise (n_rays, 1 or n_samples, dims) in any dtype, on any device."""
        with torch.no_grad():
            return torch.cat([self.render(torch.arange(part.start, part.stop, device=self.device),
                                          noise[part].to(self.device, torch.float32))
                              for part in pass_slices(self.n_rays, self.n_samples, pass_samples)])


class BranchView:
    """A single-sample secret view whose noise moves only the direction segment, its position segment
    being one vector shared by every ray (a compact tile's offset, compact.tile_space): each ray's trunk,
    and with it its density and feature, is evaluated once, and what the exact solver evaluates again and
    again is the colour head alone (the MLP's view branch, one ReLU layer of width/2, ~1/12 of the standard
    NeRF's multiply-adds; the hash grid's colour MLP).

    Evaluates what SecretView would for noise whose position part equals `xyz_noise` (the part passed in is
    not read): the same ops on the same values, to float32 rounding (the trunk runs over every ray at
    once, not per call), far inside the solver's margin.
    """

    n_samples = 1

    def __init__(self, secret_view: SecretView, xyz_noise: torch.Tensor):
        if secret_view.n_samples != 1:
            raise ValueError("a BranchView needs a secret view with one sample per ray")
        self.field, self.xyz_dims = secret_view.field, secret_view.field.config.position_dims
        encoded = secret_view.encodings(torch.arange(secret_view.n_rays, device=secret_view.device))[:, 0]
        with torch.no_grad():
            self.density, self.feature = self.field.trunk_outputs(encoded[:, :self.xyz_dims] + xyz_noise)
        self.encoded_dirs = encoded[:, self.xyz_dims:]

    @property
    def n_rays(self) -> int:
        return self.density.shape[0]

    @property
    def noise_dims(self) -> int:
        return self.field.config.noise_dims

    def branch(self, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The field's view_branch of rays `index` (m,) with noise (m, 1, dims): raw colour (m, 3), its state."""
        return self.field.view_branch(self.feature[index], self.encoded_dirs[index] + noise[:, 0, self.xyz_dims:])

    def raw(self, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw colour (m, 1, 3) and density (m, 1) of rays `index` (m,) with noise (m, 1, dims)."""
        return self.branch(index, noise)[0][:, None], self.density[index, None]

    def outputs_and_jacobian(self, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """As SecretView.outputs_and_jacobian; only the colour rows' direction columns are nonzero."""
        raw_rgb, state = self.branch(index, noise)
        jacobian = raw_rgb.new_zeros(len(index), 4, self.noise_dims)
        jacobian[:, :3, self.xyz_dims:] = self.field.direction_jacobian(state)
        return torch.cat([raw_rgb, self.density[index, None]], dim=-1), jacobian
