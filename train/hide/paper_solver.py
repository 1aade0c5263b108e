"""`--method paper`: the paper's optimisation (paper.py), a tile's blocks as parts (each saved so a hide
resumes per block) after a survey of its clean view; noise per sample (the paper's layout) or per ray."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import torch

from noisenerf.runtime.layouts import LAYOUTS, VectorNoise
from noisenerf.runtime.metrics import tile_quality
from noisenerf.train.hide.methods import METHODS
from noisenerf.train.hide.paper import ViewSurvey, recorded_points, skip_shares, solved_block, survey
from noisenerf.train.hide.secret_view import SecretView
from noisenerf.train.hide.settings import PaperSettings
from noisenerf.train.hide.solver import Solver, TileSolution, storage_dtype

if TYPE_CHECKING:
    from noisenerf.train.hide.plan import HideConfig


class PaperSolver(Solver):
    method = METHODS["paper"]

    def prepares(self, config: HideConfig) -> bool:
        return True

    def prepare(self, secret_view: SecretView, pixels: torch.Tensor, config: HideConfig, tile_index: int) -> ViewSurvey:
        """The clean view: revival's donors and the report's dead rays."""
        return survey(secret_view, config.get(PaperSettings).pass_samples)

    def part_pixels(self, config: HideConfig) -> int:
        return config.get(PaperSettings).block_pixels

    def solve_part(self, secret_view: SecretView, rows: range, pixels: torch.Tensor, config: HideConfig, tile_index: int,
                   part: int, prepared: ViewSurvey, width: int) -> dict[str, torch.Tensor]:
        """Block `part`, its noise on the CPU in the storage dtype (so device memory holds one block), and
        its colours at each recorded iteration."""
        index = torch.arange(rows.start, rows.stop, device=pixels.device)
        block = solved_block(secret_view, index, pixels, layout_samples(config), config.get(PaperSettings), prepared,
                             storage_dtype(config.dtype))
        return {"noise": block.noise, "colors": block.colors, "work": block.work}

    def part_layout(self, config: HideConfig, rows: int, dims: int, prepared: ViewSurvey) -> tuple[dict, Callable]:
        points = recorded_points(config.get(PaperSettings))
        return ({"noise": ((rows, layout_samples(config), dims), storage_dtype(config.dtype)),
                 "colors": ((len(points), rows, 3), torch.float32), "work": ((3,), torch.int64)}, lambda tensors: True)

    def assemble(self, secret_view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                 prepared: ViewSurvey, parts: list[dict[str, torch.Tensor]]) -> TileSolution:
        """The blocks' noise; the report has the tile's quality at each recorded iteration, how many of its
        rays were dead (every density ≤ 0) before solving, and the share of the work skipping left out."""
        points = recorded_points(config.get(PaperSettings))
        noise = torch.cat([part["noise"] for part in parts])
        colors = torch.cat([part["colors"] for part in parts], dim=1)
        target = pixels.cpu().float() / 255.0
        records = [{"iteration": t, "loss": float(((colors[i] - target) ** 2).sum(-1).mean()),
                    **tile_quality(colors[i].numpy(), pixels.cpu().numpy(), shape)} for i, t in enumerate(points)]
        report = {"records": records, "dead_rays": int((~prepared.alive).sum()),
                  "skipping": skip_shares(sum(part["work"] for part in parts), secret_view.n_rays, secret_view.n_samples,
                                          config.get(PaperSettings).iters)}
        stored_shape = LAYOUTS[config.layout].stored_shape(*shape, secret_view.n_samples, secret_view.noise_dims)
        return TileSolution(noise, report, VectorNoise(noise.reshape(stored_shape).numpy()))


def layout_samples(config: HideConfig) -> int:
    """Noise vectors per ray the layout stores: one per sample (the paper's), or one per ray."""
    return LAYOUTS[config.layout].vectors_per_ray(config.n_samples)
