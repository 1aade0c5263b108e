"""Fitting a `nerfacto` field as nerfstudio's nerfacto trains one: the field and its proposal networks, the proposal
sampler (train.scene.proposal) in place of the occupancy grid, L∞ scene contraction, a per-image appearance
embedding, and the loss colour MSE + interlevel + distortion (mip-NeRF 360's).

The frame: the field's unit cube (where the contraction is the identity) is the dataset's box, centred and scaled
(`contraction_frame`); a forward-facing (LLFF) dataset's box is the cube out to its nearest content, so the
scene beyond lies in the contracted shell, linear in disparity like NDC. The saved scene is the `nerfacto` kind
imports write (train.scene.scene.own_sampler_scene): cameras in that frame, the appearance embedding's mean
folded into the colour MLP's first bias, and no occupancy grid: every render goes through the proposal sampler.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save
from torch import nn

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.files import write_bytes, write_json
from noisenerf.runtime.proposal import ProposalSampling
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import SamplingConfig
from noisenerf.train.scene.datasets import LLFF_BD_FACTOR, Dataset, farthest_corner
from noisenerf.train.scene.fit import FitConfig, load_optimizer, optimizer_tensors, read_checkpoint, training_rays
from noisenerf.train.scene.hashgrid import TABLE_INIT
from noisenerf.train.scene.nerfacto import NerfactoField
from noisenerf.train.scene.proposal import (distortion_loss, euclidean_bins, interlevel_loss, midpoints,
                                            proposal_stages)
from noisenerf.train.scene.render import TorchRays, composite, render_weights
from noisenerf.train.scene.scene import Scene, field_weights, own_sampler_scene, weights_of

SECRET_SAMPLES = 128  # uniform samples per ray of a secret view, as an imported nerfacto scene's


def contraction_frame(dataset: Dataset) -> Dataset:
    """The dataset in the field's frame: its box (for LLFF, ±the nearest content's distance round the recentred
    cameras, which llff_c2w puts at 1/bd_factor) moved and scaled onto [-1, 1]³; world rays, no NDC. Rays start at
    the dataset's own near plane (NeRF-Synthetic's 2, LLFF's NDC plane at 1, where no camera can paint its view on a
    film just in front of itself; a capture's nerfstudio's 0.05, where on lego one did: docs/field-kinds.md), and
    end at the farthest corner of the cube seen from a camera (what a secret view samples)."""
    if dataset.ndc is not None:
        centre, half, near = np.zeros(3), 1.0 / LLFF_BD_FACTOR, dataset.ndc.near_plane
    else:
        lo, hi = np.asarray(dataset.aabb[:3], np.float64), np.asarray(dataset.aabb[3:], np.float64)
        centre, half, near = (lo + hi) / 2, float(np.max(hi - lo) / 2), dataset.near

    def moved(camera: Camera) -> Camera:
        c2w = np.asarray(camera.c2w, np.float64).copy()
        c2w[:3, 3] = (c2w[:3, 3] - centre) / half
        return dataclasses.replace(camera, c2w=tuple(tuple(float(v) for v in row) for row in c2w))

    cameras = tuple(moved(camera) for camera in dataset.cameras)
    unit = (-1.0,) * 3 + (1.0,) * 3
    far = farthest_corner(np.array([camera.matrix()[:3, 3] for camera in cameras], np.float64), unit)
    return dataclasses.replace(dataset, cameras=cameras, ndc=None, near=near / half, far=far, aabb=unit)


class Appearance(nn.Module):
    """nerfacto's per-image appearance embedding (views, dim) and its share of the colour MLP's first weight. The
    embedding starts at zero, not nerfstudio's N(0, 1): the mean that the saved field keeps then starts as no change
    to the field, rather than random codes the network must learn to ignore."""

    def __init__(self, views: int, dim: int, hidden: int):
        super().__init__()
        self.embedding = nn.Parameter(torch.zeros(views, dim))
        self.projection = nn.Linear(dim, hidden, bias=False)

    def forward(self, views: torch.Tensor) -> torch.Tensor:
        """The first colour layer's appearance term of images `views` (n,) -> (n, hidden)."""
        return self.projection(self.embedding[views])

    def mean_term(self) -> torch.Tensor:
        """The term of the mean embedding (hidden,): the eval render's."""
        return self.projection(self.embedding.mean(0))


def anneal_exponent(step: int, steps: int, slope: float) -> float:
    """nerfstudio's proposal-weight exponent: bias(min(step/steps, 1)) with bias(x) = s·x / ((s − 1)·x + 1)."""
    x = min(step / steps, 1.0) if steps else 1.0
    return slope * x / ((slope - 1) * x + 1)


class ProposalFitter:
    """One nerfacto fit (train.scene.fit.Fitter's interface): field, proposal networks, appearance, optimizer and
    random state, checkpointable at any step. `dataset` is in the field's frame (contraction_frame)."""

    def __init__(self, dataset: Dataset, config: FitConfig, device: torch.device):
        self.dataset, self.config, self.device = dataset, config, device
        self.training = config.proposal
        torch.manual_seed(config.seed)
        sampler = dataclasses.replace(config.field.sampler, near=dataset.near)
        self.field = NerfactoField(dataclasses.replace(config.field, sampler=sampler)).to(device)
        with torch.no_grad():
            for network in [self.field, *self.field.proposals]:
                network.table.uniform_(-TABLE_INIT, TABLE_INIT)
        self.render = RenderConfig(SamplingConfig(dataset.near, dataset.far, SECRET_SAMPLES),
                                   background=dataset.background, pixel_center=0.5)
        self.appearance = (Appearance(len(dataset.splits["train"]), self.training.appearance_dim,
                                      config.field.colour_hidden).to(device) if self.training.appearance_dim else None)
        groups = self.field.parameter_groups() + (
            [{"params": list(self.appearance.parameters()), "weight_decay": 0.0}] if self.appearance else [])
        self.optimizer = torch.optim.Adam(groups, lr=config.lr, **self.field.adam)
        self.sampling = ProposalSampling(**dataclasses.asdict(sampler))
        self.step, self.seconds, self.samples_evaluated = 0, 0.0, 0
        self.generator = torch.Generator().manual_seed(config.seed)
        self.rays = training_rays(dataset, self.render, config, device)

    def train_step(self, lr: float) -> float:
        config, training = self.config, self.training
        index = torch.randint(len(self.rays.colors), (config.batch_rays,), generator=self.generator).to(self.device)
        rays = TorchRays(self.rays.rays.origins[index], self.rays.rays.directions[index], self.rays.rays.viewdirs[index])
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        exponent = anneal_exponent(self.step, training.anneal_steps, training.anneal_slope)
        updating = self.step < training.update_warmup or self.step % training.update_every == 0
        with torch.set_grad_enabled(updating):
            stages, bins = proposal_stages(rays, self.sampling, list(self.field.proposals), self.generator, exponent)
        points, deltas = midpoints(rays, euclidean_bins(bins, self.sampling.near, self.sampling.far))
        n, m = deltas.shape
        viewdirs = rays.viewdirs[:, None, :].expand(n, m, 3).reshape(-1, 3)
        if self.appearance is None:
            rgb, sigma = self.field(points.reshape(-1, 3), viewdirs)
        else:
            term = self.appearance(self.rays.views[index])[:, None, :].expand(n, m, -1).reshape(n * m, -1)
            rgb, sigma = self.field.appearance_forward(points.reshape(-1, 3), viewdirs, term)
        rgbs, weights = rgb.reshape(n, m, 3), render_weights(sigma.reshape(n, m), deltas)
        colours = composite(weights, rgbs, rgbs[:, -1])  # nerfstudio's last_sample background
        colour_loss = torch.mean((colours - self.rays.colors[index]) ** 2)
        loss = (colour_loss + training.distortion_weight * distortion_loss(bins, weights)
                + (training.interlevel_weight * interlevel_loss(bins, weights, stages) if updating else 0))
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.samples_evaluated += n * m
        self.step += 1
        return float(colour_loss.detach())

    def scene(self, final: bool) -> Scene:
        """The scene as it stands: the field with the mean appearance folded in (a copy unless `final`)."""
        field = self.field
        if self.appearance is not None:
            field = self.field if final else copy.deepcopy(self.field)
            with torch.no_grad():
                field.fold_appearance(self.appearance.mean_term())
                if final:  # folded: a checkpoint written after holds no second copy
                    self.appearance.embedding.zero_()
        return own_sampler_scene(field, self.dataset.cameras, self.render, "fit")

    # checkpoints: tensors in safetensors, the rest in JSON (never pickle)
    def save_checkpoint(self, directory: Path) -> None:
        appearance = self.appearance.state_dict() if self.appearance else {}
        tensors = {**field_weights({"coarse": self.field}), **{f"appearance.{k}": v for k, v in appearance.items()},
                   **optimizer_tensors(self.optimizer), "generator": self.generator.get_state()}
        write_bytes(directory / "checkpoint.safetensors",
                    save({k: v.detach().cpu().contiguous() for k, v in tensors.items()}), replace=True)
        write_json(directory / "checkpoint.json", {
            "fit": self.config.to_dict(), "step": self.step, "seconds": self.seconds,
            "samples_evaluated": self.samples_evaluated, "param_groups": self.optimizer.state_dict()["param_groups"]})

    def load_checkpoint(self, directory: Path) -> bool:
        """Resume from directory's checkpoint if there is one made with the same config."""
        found = read_checkpoint(directory, self.config)
        if found is None:
            return False
        meta, tensors = found
        self.field.load_state_dict(weights_of("coarse", tensors))
        if self.appearance is not None:
            self.appearance.load_state_dict(weights_of("appearance", tensors))
        load_optimizer(self.optimizer, tensors, meta["param_groups"])
        self.generator.set_state(tensors["generator"])
        self.step, self.seconds = int(meta["step"]), float(meta["seconds"])
        self.samples_evaluated = int(meta["samples_evaluated"])
        return True

