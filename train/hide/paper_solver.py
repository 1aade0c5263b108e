"""`--method paper`: the paper's optimisation (paper.py), a tile's blocks one after another, each saved
so a hide resumes per block; noise per sample (the paper's layout) or per ray."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import torch

from noisenerf.runtime.bundle import VectorNoise, noise_shape
from noisenerf.runtime.metrics import tile_quality
from noisenerf.train.hide.paper import PaperSettings, recipe, recorded_points, solve_blocks, survey
from noisenerf.train.hide.secret_view import SecretView, pass_samples_for
from noisenerf.train.hide.solver import ChunkPool, Solver, TileSolution, storage_dtype

if TYPE_CHECKING:
    from noisenerf.train.hide.plan import HideConfig
    from noisenerf.train.hide.progress import Progress


class PaperSolver(Solver):
    name = "paper"
    settings_types = (PaperSettings,)
    layouts = ("sample", "ray")
    default_samples = 64  # nerf-pytorch's N_samples, the coarse sampling the paper's code renders with
    default_network = "coarse"  # as the paper's authors render

    def settings_from_arguments(self, args: argparse.Namespace, device: torch.device) -> tuple:
        overrides = {name: value for name, value in (("iters", args.iters), ("revival", args.revival))
                     if value is not None}
        return (recipe(args.recipe, pass_samples=pass_samples_for(device), **overrides),)

    def solve_tile(self, secret_view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                   progress: Progress, k: int, bar, pool: ChunkPool) -> TileSolution:
        """The tile's blocks (resuming saved ones). Its noise waits on the CPU in the storage dtype, so
        device memory holds one block. The report has the tile's quality at each recorded iteration and
        how many of its rays were dead (every density ≤ 0) before solving. Blocks run one after another
        in this process (each already fills the device); the pool is left unused."""
        settings = config.get(PaperSettings)
        points = recorded_points(settings)
        clean = survey(secret_view, settings.pass_samples)
        stored_shape = noise_shape(config.layout, *shape, secret_view.n_samples, secret_view.noise_dims)
        layout_samples = stored_shape[2] if config.layout == "sample" else 1
        noise = torch.zeros(secret_view.n_rays, layout_samples, secret_view.noise_dims,
                            dtype=storage_dtype(config.dtype))
        colors = torch.zeros(len(points), secret_view.n_rays, 3)

        def saved_block(b: int) -> dict | None:
            m = min(settings.block_pixels, secret_view.n_rays - b * settings.block_pixels)
            return progress.load(k, b, {"noise": ((m, *noise.shape[1:]), noise.dtype),
                                               "colors": ((len(points), m, 3), torch.float32)})

        for b, block in enumerate(solve_blocks(secret_view, pixels, layout_samples, settings, clean, noise.dtype,
                                               saved_block)):
            if block.solved:
                progress.save(k, b, {"noise": block.noise, "colors": block.colors})
            noise[block.index.cpu()] = block.noise
            colors[:, block.index.cpu()] = block.colors
            bar.update(block.index.numel())
        target = pixels.cpu().float() / 255.0
        records = [{"iteration": t, "loss": float(((colors[i] - target) ** 2).sum(-1).mean()),
                    **tile_quality(colors[i].numpy(), pixels.cpu().numpy(), shape)} for i, t in enumerate(points)]
        report = {"records": records, "dead_rays": int((~clean.alive).sum())}
        return TileSolution(noise, report, VectorNoise(noise.reshape(stored_shape).numpy()))
