"""`noisenerf fit`: fit a NeRF to a dataset on a CPU (or GPU), with skipping, checkpoints and resume.

Presets (`--field` picks a kind's default preset; without either, the dataset kind's: presets.DEFAULT_FIELDS):
- `small` (the `mlp` kind's default): one 6×128 MLP (nerf-pytorch compatible: netdepth 6, netwidth 128,
  skip at 4), 128 uniform samples per ray of which only those in occupied grid cells and before the ray
  turns opaque are evaluated. Chosen for 2 CPU cores: several times the training throughput of 8×256.
- `paper`: nerf-pytorch's lego setup, 8×256 coarse + fine, 64 + 128 hierarchical samples.
- `hashgrid` (the `hashgrid` kind's): Instant-NGP's field (16 levels × 2 features, 2^17 rows a level,
  resolutions 16 to 1024, SH degree 4, 64-wide MLPs) spanning the dataset's box, with the same sampler,
  occupancy grid and early termination as `small`; Instant-NGP's Adam (β₂ 0.99, ε 1e-15, weight decay on
  the MLPs only) at its learning rate 1e-2, decaying to 1e-3 (the best of the variants measured:
  docs/field-kinds.md). Its scene renders with 256 samples per ray through a 128³ grid built at the end: the
  fitted field is sharper than 128 jittered samples and a 64³ grid of 4 points per cell resolve.
- `nerfacto` (the `nerfacto` kind's) and `nerfacto-big`: nerfstudio's nerfacto field and proposal networks, trained
  with its proposal sampler and losses in a contracted frame (train.scene.fit_proposal), no occupancy grid; sized
  for 2 CPU cores (64 → 32 → 32 samples, 1,024 rays) and nerfstudio's own sizes for a GPU.

The learning rate decays exponentially from `lr` to `lr_final` over the run (by steps with --iters,
by wall time with --minutes, so that a time-boxed run still anneals). With --iters the result is a
deterministic function of the seed on CPU; with --minutes it depends on the machine's speed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from safetensors.torch import load_file, save

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import check_output_directory, read_json, write_bytes, write_json
from noisenerf.runtime.progress import Counter, ProgressFn
from noisenerf.runtime.metrics import psnr, ssim
from noisenerf.runtime.rays import field_space_rays
from noisenerf.runtime.render import RenderConfig, render_view
from noisenerf.runtime.sampling import SamplingConfig, jitter_positions, sample_positions
from noisenerf.train.scene.datasets import view_rays
from noisenerf.train.scene.field import MlpConfig
from noisenerf.train.scene.field_kinds import FieldConfigs
from noisenerf.train.scene.hashgrid import HashGridConfig, HashGridField
from noisenerf.train.scene.nerfacto import NerfactoConfig, ProposalConfig, SamplerConfig, grid_scales
from noisenerf.train.scene.occupancy import OccupancyConfig, OccupancyTracker, build_occupancy_grid, carve, cell_points
from noisenerf.train.scene.render import TorchRays, numpy_field, render_hierarchical, render_rays, skip_mask
from noisenerf.train.scene.scene import (Scene, SceneConfig, build_fields, field_weights, named_fields, render_field,
                                         weights_of)

if TYPE_CHECKING:
    from noisenerf.train.scene.datasets import Dataset


CURVE_RAYS = 4096  # pixels per view behind each point of the progress curve
TEST_SHARE = 0.10  # a fit's closing test renders ÷ its training time, at most (the first held-out view always)


APPEARANCE_DIM = 32  # nerfstudio's appearance embedding width, what `fit --appearance` learns


@dataclass(frozen=True)
class ProposalTraining:
    """How a nerfacto field and its proposal networks are fitted (train.scene.fit_proposal), nerfstudio's
    nerfacto defaults but the appearance embedding: the loss weights, the proposal weights' annealed exponent, and
    how often the proposal networks take a gradient once warmed up (they only steer samples; the field's colour
    loss needs every step). Without `fit --appearance` there is no per-image embedding (0 wide): on fern it cost
    1.4 dB on held-out frames, which render with the mean, and it leaves some secrets inexact (docs/field-kinds.md)."""

    appearance_dim: int = 0
    interlevel_weight: float = 1.0
    distortion_weight: float = 0.002
    anneal_steps: int = 1000
    anneal_slope: float = 10.0
    update_every: int = 5
    update_warmup: int = 5000


@dataclass(frozen=True)
class FitConfig:
    """Everything that decides a fit's result; saved with its checkpoints so resume can check it."""

    preset: str
    field: FieldConfigs  # a hash grid's box is the dataset's (in_box)
    fine: MlpConfig | None
    n_samples: int  # uniform samples per ray for skipping-based fitting (jittered)
    n_coarse: int  # hierarchical fitting only (paper preset)
    n_importance: int
    batch_rays: int
    lr: float
    lr_final: float
    skipping: bool = True  # occupancy grid + early ray termination
    occupancy: OccupancyConfig = OccupancyConfig()
    early_stop: float = 1e-4
    precrop_steps: int = 300  # nerf-pytorch's centre crop at the start, so lego is not fitted as white
    precrop_fraction: float = 0.5
    # Until the occupancy grid knows where the scene is, every sample is evaluated; these cheap first
    # steps (fewer rays, fewer samples) teach the field where empty space is, so skipping starts early.
    warmup_rays: int = 256
    warmup_samples: int = 32
    # RGBA datasets: what the silhouettes show empty is carved from the grid from the first step, and
    # the field is taught it is empty (opacity at random carved points), so dense renders agree too.
    empty_points: int = 1024
    empty_weight: float = 0.1
    # uniform samples per ray of the saved scene's renders (None: n_samples): rendering a field fitted
    # with jittered samples on a finer step integrates it more closely than its training step did
    render_samples: int | None = None
    # a hash grid with tiny-cuda-nn's MLPs: no biases, the colour MLP reading the raw density among the geometric
    # features (geo_features = 16, the first a copy of the raw density): Instant-NGP's own network, kept so after
    # every step (tie_tcnn_layout); a scene fitted so can be written as an Instant-NGP snapshot
    tcnn_layout: bool = False
    proposal: ProposalTraining | None = None  # a nerfacto field: fitted by its proposal sampler (fit_proposal)
    seed: int = 0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def nerfacto_preset(name: str, log2_table: int, max_resolution: int, proposal_samples: tuple[int, int], samples: int,
                    batch_rays: int) -> FitConfig:
    """A nerfacto preset: nerfstudio's nerfacto (16 levels × 2 features from 16, 64-wide MLPs, SH degree 4, two
    proposal networks of 5 levels to 128 and 256 px, 2^17 rows, 16 wide; piecewise spacing from 0.05 to 1000,
    histogram padding 0.01; Adam at 1e-2, ε 1e-15) at the table size, finest level, samples and rays given."""
    field = NerfactoConfig(
        implementation="tcnn", features=2, log2_table=log2_table, scales=grid_scales("tcnn", 16, 16, max_resolution),
        density_hidden=64, geo_features=15, sh_degree=4, colour_hidden=64, colour_layers=2, density_scale=1.0,
        proposals=tuple(ProposalConfig(features=2, log2_table=17, scales=grid_scales("tcnn", 5, 16, top), hidden=16)
                        for top in (128, 256)),
        sampler=SamplerConfig(proposal_samples, samples, 0.01, 0.05, 1000.0))
    return FitConfig(preset=name, field=field, fine=None, n_samples=samples, n_coarse=0, n_importance=0,
                     batch_rays=batch_rays, lr=1e-2, lr_final=1e-3, skipping=False, precrop_steps=0,
                     proposal=ProposalTraining())


PRESETS = {
    "small": FitConfig(preset="small", field=MlpConfig(depth=6, width=128), fine=None, n_samples=128,
                       n_coarse=0, n_importance=0, batch_rays=1024, lr=2e-3, lr_final=1e-4,
                       occupancy=OccupancyConfig(warmup_steps=300)),
    "paper": FitConfig(preset="paper", field=MlpConfig(), fine=MlpConfig(), n_samples=192, n_coarse=64,
                       n_importance=128, batch_rays=1024, lr=5e-4, lr_final=5e-5, skipping=False),
    "hashgrid": FitConfig(preset="hashgrid", field=HashGridConfig(), fine=None, n_samples=128, n_coarse=0,
                          n_importance=0, batch_rays=1024, lr=1e-2, lr_final=1e-3, render_samples=256,
                          occupancy=OccupancyConfig(warmup_steps=100, final_resolution=128)),
    # sized for 2 CPU cores (docs/field-kinds.md has the sweep); nerfacto-big is nerfstudio's own, for a GPU
    # 64 → 32 proposal samples, not 128 → 64: on Instant-NGP's fox (¼ size, 3 minutes) 474 steps to 21.8 dB against
    # 332 steps to 20.1, and closing test renders 1.4× faster (docs/field-kinds.md)
    "nerfacto": nerfacto_preset("nerfacto", 17, 1024, (64, 32), 32, 1024),
    "nerfacto-big": nerfacto_preset("nerfacto-big", 19, 2048, (256, 96), 48, 4096),
}


@dataclass(frozen=True)
class Budget:
    """When a fit stops: after `iters` steps, or after `minutes` of training wall time (resumes included;
    the progress curve's evaluation renders excluded)."""

    iters: int | None = None
    minutes: float | None = None

    def progress(self, step: int, seconds: float) -> float:
        return step / self.iters if self.iters else seconds / (60 * self.minutes)


@dataclass
class TrainingRays:
    """All training pixels as rays in the field's space, with their target colours. (n, 3) each."""

    rays: TorchRays
    colors: torch.Tensor
    central: torch.Tensor  # indices of pixels in the centre crop
    views: torch.Tensor  # (n,) each pixel's image, its position among the training views


def training_rays(dataset: Dataset, render: RenderConfig, config: FitConfig, device) -> TrainingRays:
    origins, directions, viewdirs, colors, central, views = [], [], [], [], [], []
    offset = 0
    for position, index in enumerate(dataset.splits["train"]):
        camera = dataset.cameras[index]
        batch = field_space_rays(render, *view_rays(dataset.cameras[index], render.pixel_center))
        origins.append(batch.origins)
        directions.append(batch.directions)
        viewdirs.append(batch.viewdirs)
        colors.append(dataset.images[index].reshape(-1, 3))
        central.append(offset + _central_pixels(camera.width, camera.height, config.precrop_fraction))
        views.append(np.full(camera.width * camera.height, position, np.int64))
        offset += camera.width * camera.height
    as_tensor = lambda parts: torch.from_numpy(np.concatenate(parts)).to(device)  # noqa: E731
    return TrainingRays(TorchRays(as_tensor(origins), as_tensor(directions), as_tensor(viewdirs)),
                        as_tensor(colors), torch.from_numpy(np.concatenate(central)), as_tensor(views))


def _central_pixels(width: int, height: int, fraction: float) -> np.ndarray:
    """Flat indices of the centre crop covering `fraction` of each side. -> (m,) int64."""
    dw, dh = int(width * fraction / 2), int(height * fraction / 2)
    ys, xs = np.meshgrid(np.arange(height // 2 - dh, height // 2 + dh), np.arange(width // 2 - dw, width // 2 + dw),
                         indexing="ij")
    return (ys * width + xs).ravel().astype(np.int64)


class Fitter:
    """One fit: fields, optimizer, occupancy tracker and random state, checkpointable at any step."""

    def __init__(self, dataset: Dataset, config: FitConfig, device: torch.device):
        self.dataset, self.config, self.device = dataset, config, device
        torch.manual_seed(config.seed)
        self.scene_config = SceneConfig(
            coarse=config.field.in_box(dataset.aabb), fine=config.fine, n_coarse=config.n_coarse, n_importance=config.n_importance,
            render=RenderConfig(SamplingConfig(dataset.near, dataset.far, config.render_samples or config.n_samples),
                                background=dataset.background, ndc=dataset.ndc, pixel_center=0.5,
                                early_stop=config.early_stop),
            aabb=dataset.aabb, grid_resolution=config.occupancy.saved_resolution, cameras=dataset.cameras)
        self.coarse, self.fine = (f.to(device) if f is not None else None for f in build_fields(self.scene_config))
        if config.tcnn_layout:
            tie_tcnn_layout(self.coarse)
        groups = self.coarse.parameter_groups() + (self.fine.parameter_groups() if self.fine else [])
        self.optimizer = torch.optim.Adam(groups, lr=config.lr, **self.coarse.adam)
        self.step, self.seconds = 0, 0.0
        self.generator = torch.Generator().manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        self.hull = self.visual_hull(config.occupancy.resolution)
        self.empty_cells = np.flatnonzero(~self.hull) if self.hull is not None else np.zeros(0, np.int64)
        self.tracker = OccupancyTracker(dataset.aabb, self.step_size, config.occupancy, config.seed, self.hull)
        self.rays = training_rays(dataset, self.scene_config.render, config, device)
        self.background = torch.tensor(dataset.background, dtype=torch.float32, device=device)
        self.samples_evaluated = 0

    def visual_hull(self, resolution: int) -> np.ndarray | None:
        """The training silhouettes' hull on a grid of `resolution` (None without alpha or skipping)."""
        if self.dataset.alphas is None or not self.config.skipping:
            return None
        train = list(self.dataset.splits["train"])
        return carve([self.dataset.cameras[i] for i in train], self.dataset.alphas[train], self.dataset.aabb, resolution)

    @property
    def step_size(self) -> float:
        return (self.dataset.far - self.dataset.near) / self.config.n_samples

    @property
    def render_field(self):
        return render_field(self.coarse, self.fine)

    def train_step(self, lr: float) -> float:
        config = self.config
        warming = config.skipping and self.fine is None and self.step < config.occupancy.warmup_steps
        n_rays = config.warmup_rays if warming else config.batch_rays
        pool = self.rays.central if self.step < config.precrop_steps and len(self.rays.central) else None  # images too small to crop: all
        if pool is None:
            index = torch.randint(len(self.rays.colors), (n_rays,), generator=self.generator)
        else:
            index = pool[torch.randint(len(pool), (n_rays,), generator=self.generator)]
        index = index.to(self.device)
        rays = TorchRays(self.rays.rays.origins[index], self.rays.rays.directions[index],
                         self.rays.rays.viewdirs[index])
        target = self.rays.colors[index]
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        if self.fine is not None:
            t_vals = self._jittered(config.n_coarse, n_rays)
            coarse, fine = render_hierarchical(self.coarse, self.fine, rays, t_vals, config.n_importance,
                                               self.background)
            loss = torch.mean((coarse - target) ** 2) + torch.mean((fine - target) ** 2)
            fine_loss = torch.mean((fine - target) ** 2)
            self.samples_evaluated += len(rays) * (2 * config.n_coarse + config.n_importance)
        else:
            if config.skipping:
                self.tracker.maybe_update(self.coarse, self.step)
            t_vals = self._jittered(config.warmup_samples if warming else config.n_samples, n_rays)
            mask = (skip_mask(self.coarse, rays, t_vals, self.tracker.grid, 0.0 if warming else config.early_stop)
                    if config.skipping else torch.ones_like(t_vals, dtype=torch.bool))
            colors, _ = render_rays(self.coarse, rays, t_vals, self.background, mask=mask)
            loss = fine_loss = torch.mean((colors - target) ** 2)
            if self.empty_cells.size and config.empty_points:
                loss = loss + config.empty_weight * self._empty_opacity()
            self.samples_evaluated += int(mask.sum())
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        if config.tcnn_layout:
            tie_tcnn_layout(self.coarse)
        self.step += 1
        return float(fine_loss.detach())

    def _empty_opacity(self) -> torch.Tensor:
        """Mean opacity over one step at random points of carved-away cells (should be 0)."""
        cells = self.empty_cells[self.rng.integers(0, self.empty_cells.size, self.config.empty_points)]
        points = cell_points(np.asarray(self.dataset.aabb, np.float32), self.config.occupancy.resolution, cells,
                             self.rng)
        sigma = self.coarse.density(torch.from_numpy(points).to(self.device))
        return torch.mean(-torch.expm1(-sigma * self.step_size))

    def _jittered(self, n_samples: int, n_rays: int) -> torch.Tensor:
        sampling = SamplingConfig(self.dataset.near, self.dataset.far, n_samples)
        t = jitter_positions(sample_positions(sampling), n_rays, self.rng)
        return torch.from_numpy(t).to(self.device)

    def scene(self, final: bool) -> Scene:
        """The scene as it stands; `final` rebuilds the occupancy grid from the field at the saved resolution,
        evaluating the visual hull's cells only (all cells without one)."""
        occupancy = self.config.occupancy
        if not final and self.config.skipping and self.fine is None:
            config = dataclasses.replace(self.scene_config, grid_resolution=occupancy.resolution)
            return Scene(config, self.coarse, self.fine, self.tracker.grid)
        resolution = occupancy.saved_resolution
        hull = self.hull if resolution == occupancy.resolution else self.visual_hull(resolution)
        grid = build_occupancy_grid(self.render_field, self.dataset.aabb, resolution, self.step_size, occupancy,
                                    seed=self.config.seed, within=hull)
        return Scene(self.scene_config, self.coarse, self.fine, grid)

    # checkpoints: tensors in safetensors, the rest in JSON (never pickle)
    def save_checkpoint(self, directory: Path) -> None:
        tensors = {**field_weights(named_fields(self.coarse, self.fine)), **optimizer_tensors(self.optimizer)}
        tensors["tracker.density"] = torch.from_numpy(self.tracker.density)
        tensors["generator"] = self.generator.get_state()
        tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
        write_bytes(directory / "checkpoint.safetensors", save(tensors), replace=True)
        write_json(directory / "checkpoint.json", {
            "fit": self.config.to_dict(), "step": self.step, "seconds": self.seconds,
            "samples_evaluated": self.samples_evaluated,
            "rng": self.rng.bit_generator.state, "tracker_rng": self.tracker.rng.bit_generator.state,
            "param_groups": self.optimizer.state_dict()["param_groups"],
        })

    def load_checkpoint(self, directory: Path) -> bool:
        """Resume from directory's checkpoint if there is one made with the same config."""
        found = read_checkpoint(directory, self.config)
        if found is None:
            return False
        meta, tensors = found
        for network, field in named_fields(self.coarse, self.fine).items():
            field.load_state_dict(weights_of(network, tensors))
        load_optimizer(self.optimizer, tensors, meta["param_groups"])
        self.tracker.density[:] = tensors["tracker.density"].numpy()
        self.generator.set_state(tensors["generator"])
        self.rng.bit_generator.state = meta["rng"]
        self.tracker.rng.bit_generator.state = meta["tracker_rng"]
        self.step, self.seconds = int(meta["step"]), float(meta["seconds"])
        self.samples_evaluated = int(meta["samples_evaluated"])
        return True


def read_checkpoint(directory: Path, config: FitConfig) -> tuple[dict, dict[str, torch.Tensor]] | None:
    """directory's checkpoint (its JSON, its tensors), None where there is none; refused where another fit made it."""
    if not (directory / "checkpoint.json").is_file():
        return None
    meta = read_json(directory / "checkpoint.json", "checkpoint")
    if meta["fit"] != json.loads(json.dumps(config.to_dict())):
        raise UserError(f"{directory} holds a checkpoint of a different fit; remove "
                        f"{directory / 'checkpoint.json'} to start over")
    return meta, load_file(str(directory / "checkpoint.safetensors"))


def optimizer_tensors(optimizer: torch.optim.Optimizer) -> dict[str, torch.Tensor]:
    """The optimizer's state as named tensors (a checkpoint's safetensors; its param groups go to JSON)."""
    return {f"optimizer.{pid}.{name}": torch.as_tensor(value)
            for pid, state in optimizer.state_dict()["state"].items() for name, value in state.items()}


def load_optimizer(optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], groups: list) -> None:
    """The optimizer's state from a checkpoint's tensors (optimizer_tensors) and param groups."""
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("optimizer."):
            _, pid, name = key.split(".")
            state.setdefault(int(pid), {})[name] = value
    optimizer.load_state_dict({"state": state, "param_groups": groups})


def tie_tcnn_layout(field) -> None:
    """Project a hash-grid field onto Instant-NGP's network (FitConfig.tcnn_layout): every bias 0 and frozen, the
    density MLP's second output row (the first geometric feature) equal to its first (the raw density): both
    become their mean."""
    if not (isinstance(field, HashGridField) and field.config.geo_features >= 1):
        raise UserError("a tiny-cuda-nn layout needs a hash-grid field with a geometric feature")
    with torch.no_grad():
        for layer in [*field.density_linears, *field.colour_linears]:
            layer.bias.zero_()
            layer.bias.requires_grad_(False)
        weight = field.density_linears[1].weight
        weight[:2] = weight[:2].mean(0)


def held_out_quality(scene: Scene, dataset: Dataset, views: list[int], skipping: bool = True,
                     seconds: float | None = None) -> dict:
    """Mean PSNR / SSIM over views rendered the way recipients render them (runtime + skipping, or
    hierarchical for scenes with a fine network), through each camera's lens where it has one, in order. With
    `seconds`, the next view is started only while the renders so far and one more at their mean stay within it
    (the first always): a fit's closing report is bounded in time. -> psnr, ssim, views (rendered), held_out
    (given), per_view [{view, psnr, ssim}], samples_dense, samples_evaluated."""
    field, sampler = numpy_field(scene.render_field), scene.sampler(skipping)
    scores, dense, evaluated, started = [], 0, 0, time.perf_counter()
    for index in views:
        spent = time.perf_counter() - started
        if scores and seconds is not None and spent * (len(scores) + 1) / len(scores) > seconds:
            break
        image, stats = render_view(dataset.cameras[index], scene.config.render, field, sampler)
        target = dataset.images[index]
        scores.append({"view": int(index), "psnr": float(psnr(image, target)), "ssim": float(ssim(image, target))})
        dense += stats.n_samples_dense
        evaluated += stats.n_samples_evaluated
    return {**mean_quality(scores), "held_out": len(views), "samples_dense": dense, "samples_evaluated": evaluated}


def mean_quality(per_view: list[dict]) -> dict:
    """Mean PSNR / SSIM of views' scores ({view, psnr, ssim}), with the scores and their count."""
    return {"psnr": float(np.mean([s["psnr"] for s in per_view])), "ssim": float(np.mean([s["ssim"] for s in per_view])),
            "views": len(per_view), "per_view": per_view}


def pooled_quality(parts: list[dict]) -> dict:
    """held_out_quality of views rendered in parts, as one: the means over every part's views."""
    return {**mean_quality([score for part in parts for score in part["per_view"]]),
            "held_out": sum(part["views"] for part in parts),
            **{key: sum(part[key] for part in parts) for key in ("samples_dense", "samples_evaluated")}}


def curve_psnr(scene: Scene, dataset: Dataset, views: list[int], rays_per_view: int, seed: int) -> float:
    """PSNR over a seeded random subset of the views' pixels, rendered like `held_out_quality` renders them: an
    unbiased estimate of the views' PSNR at a fraction of the cost (a full LLFF render is minutes here)."""
    field, rng, errors = numpy_field(scene.render_field), np.random.default_rng(seed), []
    sampler = scene.sampler()
    for index in views:
        camera = dataset.cameras[index]
        chosen = rng.choice(camera.width * camera.height, min(rays_per_view, camera.width * camera.height),
                            replace=False)
        rays_o, rays_d = view_rays(camera, scene.config.render.pixel_center)
        rays = field_space_rays(scene.config.render, rays_o[chosen], rays_d[chosen])
        colors, _ = sampler.render(rays, field)
        errors.append((colors - dataset.images[index].reshape(-1, 3)[chosen]) ** 2)
    return float(-10 * np.log10(max(np.mean(np.concatenate(errors)), 1e-10)))


def held_out_views(dataset: Dataset) -> list[int]:
    """The views a fit's closing report renders: the test split, or the training views where there is none."""
    return list(dataset.splits.get("test") or dataset.splits["train"])


def fitting_frame(dataset: Dataset, config: FitConfig) -> Dataset:
    """The dataset in the frame the config's fit works and saves its cameras in: a nerfacto field's contraction
    frame (train.scene.fit_proposal), else its own."""
    if config.proposal is None:
        return dataset
    from noisenerf.train.scene.fit_proposal import contraction_frame
    return contraction_frame(dataset)


def new_fitter(dataset: Dataset, config: FitConfig, device: torch.device):
    """The fitter of the config's field: a nerfacto field's with its proposal sampler, else the skipping or
    hierarchical one; in fitting_frame."""
    if config.proposal is None:
        return Fitter(dataset, config, device)
    from noisenerf.train.scene.fit_proposal import ProposalFitter
    return ProposalFitter(fitting_frame(dataset, config), config, device)


def fit(dataset: Dataset, out_dir: Path, config: FitConfig, budget: Budget, device: torch.device,
        checkpoint_seconds: float = 60.0, curve_seconds: float = 120.0, curve_views: int = 3,
        test_share: float | None = TEST_SHARE, progress: ProgressFn | None = None) -> dict:
    """Fit, checkpointing into out_dir, then save the scene there and report test-view quality. The folder
    is created only once the data has given a fitter, so input the fitter refuses leaves no empty folder.
    test_share: the closing test renders' time ÷ the training time, at most (held_out_quality); None renders
    every held-out view. progress: told of the steps (an iteration budget) or seconds (a time budget) done, and
    the loss."""
    out_dir = check_output_directory(out_dir)
    fitter = new_fitter(dataset, config, device)
    dataset = fitter.dataset
    out_dir.mkdir(exist_ok=True)
    resumed = fitter.load_checkpoint(out_dir)
    test_views = held_out_views(dataset)
    curve_subset = test_views[:: max(1, len(test_views) // curve_views)][:curve_views]
    curve_path = out_dir / "curve.json"
    curve = read_json(curve_path, "fit curve")["curve"] if resumed and curve_path.is_file() else []
    total = budget.iters if budget.iters else int(budget.minutes * 60)
    done = Counter(progress, "fit", total, "it" if budget.iters else "s",
                   done=fitter.step if budget.iters else int(fitter.seconds))
    last_checkpoint = last_curve = wall_start = time.perf_counter()
    start = time.perf_counter() - fitter.seconds
    while budget.progress(fitter.step, fitter.seconds) < 1.0:
        lr = config.lr * (config.lr_final / config.lr) ** budget.progress(fitter.step, fitter.seconds)
        loss = fitter.train_step(lr)
        now = time.perf_counter()
        previous, fitter.seconds = fitter.seconds, now - start
        done(1 if budget.iters else int(fitter.seconds) - int(previous),
             f"loss {loss:.4f}, {-10 * math.log10(max(loss, 1e-10)):.1f} dB")
        if curve_seconds and now - last_curve >= curve_seconds:
            quality = curve_psnr(fitter.scene(final=False), dataset, curve_subset, CURVE_RAYS, config.seed)
            curve.append({"seconds": round(fitter.seconds, 1), "step": fitter.step, "psnr": quality})
            write_json(curve_path, {"curve": curve, "views": curve_subset})
            last_curve = time.perf_counter()
            start += last_curve - now  # the curve is a report: its renders do not spend the training budget
        if now - last_checkpoint >= checkpoint_seconds:
            fitter.save_checkpoint(out_dir)
            last_checkpoint = time.perf_counter()
    fit_seconds = fitter.seconds
    scene = fitter.scene(final=True)
    for field in scene.fields().values():
        field.eval().requires_grad_(False)
    scene.save(out_dir)
    fitter.save_checkpoint(out_dir)
    started = time.perf_counter()
    report = {
        "scene": str(out_dir), "preset": config.preset, "steps": fitter.step, "seconds": round(fit_seconds, 1),
        "wall_seconds": round(started - wall_start, 1), "resumed": resumed,
        "samples_evaluated": fitter.samples_evaluated, "fingerprint": scene.fingerprint(),
        "occupancy": scene.grid.occupancy_fraction(), "curve": curve, "skipped_frames": list(dataset.skipped),
        "test": held_out_quality(scene, dataset, test_views,
                                 seconds=None if test_share is None else test_share * fit_seconds),
    }
    report["eval_seconds"] = round(time.perf_counter() - started, 1)
    write_json(out_dir / "fit_report.json", report)
    return report
