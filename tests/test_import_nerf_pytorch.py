"""Imported nerf-pytorch checkpoints render as nerf-pytorch does (within 1e-5 in torch, 1e-4 through the
exported model and `noisenerf-reveal --view`), keep their weights bit for bit, and bad input is refused
before anything is written.

The reference below is an independent rewrite of nerf-pytorch's test-time path (NeRF, Embedder,
get_rays, ndc_rays, raw2outputs with its cumprod, sample_pdf with det=True, render_rays, and the
load_llff_data pose processing); it shares no code with the project.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from helpers import run_reveal, write_blender, write_llff
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime.camera import camera_rays
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fingerprint import weights_fingerprint
from noisenerf.runtime.images import read_image
from noisenerf.runtime.rays import field_space_rays
from noisenerf.runtime.sampling import SamplingConfig, sample_positions
from noisenerf.train.scene.import_nerf_pytorch import (
    import_nerf_pytorch, llff_world_bounds, load_fields, parse_config_text, read_checkpoint, read_config,
    scene_geometry,
)
from noisenerf.train.scene.render import TorchRays, render_hierarchical
from noisenerf.train.scene.scene import load_scene

TOLERANCE = 1e-5


# ---- the independent nerf-pytorch reference ------------------------------------------------------

class ReferenceNeRF(nn.Module):
    """nerf-pytorch's NeRF: views_linears always built, output_linear only without view directions."""

    def __init__(self, depth: int, width: int, input_ch: int, input_ch_views: int, output_ch: int,
                 use_viewdirs: bool, skips=(4,)):
        super().__init__()
        self.input_ch, self.input_ch_views, self.skips, self.use_viewdirs = input_ch, input_ch_views, skips, use_viewdirs
        self.pts_linears = nn.ModuleList([nn.Linear(input_ch, width)] + [
            nn.Linear(width + input_ch if i in skips else width, width) for i in range(depth - 1)])
        self.views_linears = nn.ModuleList([nn.Linear(input_ch_views + width, width // 2)])
        if use_viewdirs:
            self.feature_linear = nn.Linear(width, width)
            self.alpha_linear = nn.Linear(width, 1)
            self.rgb_linear = nn.Linear(width // 2, 3)
        else:
            self.output_linear = nn.Linear(width, output_ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pts, views = torch.split(x, [self.input_ch, self.input_ch_views], dim=-1)
        h = pts
        for i, layer in enumerate(self.pts_linears):
            h = F.relu(layer(h))
            if i in self.skips:
                h = torch.cat([pts, h], -1)
        if not self.use_viewdirs:
            return self.output_linear(h)
        alpha = self.alpha_linear(h)
        h = torch.cat([self.feature_linear(h), views], -1)
        for layer in self.views_linears:
            h = F.relu(layer(h))
        return torch.cat([self.rgb_linear(h), alpha], -1)


def reference_embed(x: torch.Tensor, multires: int) -> torch.Tensor:
    """Embedder with include_input and log sampling: [x, sin(2^0 x), cos(2^0 x), ...]."""
    bands = 2.0 ** torch.linspace(0.0, multires - 1, steps=multires)
    return torch.cat([x] + [fn(x * freq) for freq in bands for fn in (torch.sin, torch.cos)], -1)


def reference_rays(height: int, width: int, focal: float, c2w: torch.Tensor):
    """get_rays with K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]]: integer pixel coordinates."""
    i, j = torch.meshgrid(torch.linspace(0, width - 1, width), torch.linspace(0, height - 1, height), indexing="ij")
    i, j = i.t(), j.t()
    dirs = torch.stack([(i - 0.5 * width) / focal, -(j - 0.5 * height) / focal, -torch.ones_like(i)], -1)
    rays_d = torch.sum(dirs[..., None, :] * c2w[:3, :3], -1)
    return c2w[:3, -1].expand(rays_d.shape), rays_d


def reference_ndc(height: int, width: int, focal: float, near: float, rays_o, rays_d):
    t = -(near + rays_o[..., 2]) / rays_d[..., 2]
    rays_o = rays_o + t[..., None] * rays_d
    ax, ay = -1.0 / (width / (2.0 * focal)), -1.0 / (height / (2.0 * focal))
    ox, oy, oz = rays_o[..., 0], rays_o[..., 1], rays_o[..., 2]
    dx, dy, dz = rays_d[..., 0], rays_d[..., 1], rays_d[..., 2]
    origins = torch.stack([ax * ox / oz, ay * oy / oz, 1.0 + 2.0 * near / oz], -1)
    directions = torch.stack([ax * (dx / dz - ox / oz), ay * (dy / dz - oy / oz), -2.0 * near / oz], -1)
    return origins, directions


def reference_raw2outputs(raw, z_vals, rays_d, white_bkgd: bool):
    dists = torch.cat([z_vals[..., 1:] - z_vals[..., :-1], torch.tensor([1e10]).expand(z_vals[..., :1].shape)], -1)
    dists = dists * torch.norm(rays_d[..., None, :], dim=-1)
    rgb = torch.sigmoid(raw[..., :3])
    alpha = 1.0 - torch.exp(-F.relu(raw[..., 3]) * dists)
    transmittance = torch.cumprod(torch.cat([torch.ones((alpha.shape[0], 1)), 1.0 - alpha + 1e-10], -1), -1)[:, :-1]
    weights = alpha * transmittance
    rgb_map = torch.sum(weights[..., None] * rgb, -2)
    if white_bkgd:
        rgb_map = rgb_map + (1.0 - weights.sum(-1))[..., None]
    return rgb_map, weights


def reference_sample_pdf(bins, weights, n_samples: int):
    weights = weights + 1e-5
    pdf = weights / torch.sum(weights, -1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, -1)], -1)
    u = torch.linspace(0.0, 1.0, steps=n_samples).expand(list(cdf.shape[:-1]) + [n_samples]).contiguous()
    inds = torch.searchsorted(cdf, u, right=True)
    inds_g = torch.stack([torch.clamp(inds - 1, min=0), torch.clamp(inds, max=cdf.shape[-1] - 1)], -1)
    matched = [inds_g.shape[0], inds_g.shape[1], cdf.shape[-1]]
    cdf_g = torch.gather(cdf.unsqueeze(1).expand(matched), 2, inds_g)
    bins_g = torch.gather(bins.unsqueeze(1).expand(matched), 2, inds_g)
    denom = cdf_g[..., 1] - cdf_g[..., 0]
    denom = torch.where(denom < 1e-5, torch.ones_like(denom), denom)
    return bins_g[..., 0] + (u - cdf_g[..., 0]) / denom * (bins_g[..., 1] - bins_g[..., 0])


@dataclass
class Reference:
    """A nerf-pytorch model: its nets and the config options that shape the test-time render."""

    coarse: ReferenceNeRF
    fine: ReferenceNeRF
    multires: int = 10
    multires_views: int = 4
    use_viewdirs: bool = True
    n_samples: int = 64
    n_importance: int = 64

    def query(self, net: ReferenceNeRF, pts: torch.Tensor, viewdirs: torch.Tensor) -> torch.Tensor:
        flat = reference_embed(pts.reshape(-1, 3), self.multires)
        if self.use_viewdirs:
            dirs = viewdirs[:, None].expand(pts.shape).reshape(-1, 3)
            flat = torch.cat([flat, reference_embed(dirs, self.multires_views)], -1)
        return net(flat).reshape(*pts.shape[:-1], -1)

    @torch.no_grad()
    def render_rays(self, rays_o, rays_d, viewdirs, near: float, far: float, white_bkgd: bool) -> torch.Tensor:
        t = torch.linspace(0.0, 1.0, steps=self.n_samples)
        z_vals = (near * (1.0 - t) + far * t).expand([rays_o.shape[0], self.n_samples])
        pts = rays_o[..., None, :] + rays_d[..., None, :] * z_vals[..., :, None]
        _, weights = reference_raw2outputs(self.query(self.coarse, pts, viewdirs), z_vals, rays_d, white_bkgd)
        mids = 0.5 * (z_vals[..., 1:] + z_vals[..., :-1])
        z_samples = reference_sample_pdf(mids, weights[..., 1:-1], self.n_importance)
        z_vals, _ = torch.sort(torch.cat([z_vals, z_samples], -1), -1)
        pts = rays_o[..., None, :] + rays_d[..., None, :] * z_vals[..., :, None]
        rgb_map, _ = reference_raw2outputs(self.query(self.fine, pts, viewdirs), z_vals, rays_d, white_bkgd)
        return rgb_map

    def render_view(self, c2w: np.ndarray, height: int, width: int, focal: float, ndc: bool,
                    near: float, far: float, white_bkgd: bool) -> np.ndarray:
        """nerf-pytorch's render(c2w=...) at test time -> (height, width, 3)."""
        rays_o, rays_d = reference_rays(height, width, focal, torch.tensor(c2w[:3, :4], dtype=torch.float32))
        viewdirs = (rays_d / torch.norm(rays_d, dim=-1, keepdim=True)).reshape(-1, 3)
        if ndc:
            rays_o, rays_d = reference_ndc(height, width, focal, 1.0, rays_o, rays_d)
        rgb = self.render_rays(rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), viewdirs, near, far, white_bkgd)
        return rgb.reshape(height, width, 3).numpy()


def make_reference(seed: int, use_viewdirs: bool = True, half_size: float = 1.0, tame: bool = True) -> Reference:
    """Seeded random nets (netdepth 8, so the skip at 4 is used).

    With `tame` they are made to look like a trained model (see tame_field), and the fine net agrees with
    the coarse one on where matter is, as after training: it is the coarse net with every weight
    perturbed by 0.2 % (relative). Without, both nets are left as initialised.
    """
    torch.manual_seed(seed)
    input_ch, input_ch_views = 3 + 6 * 10, (3 + 6 * 4 if use_viewdirs else 0)
    coarse, fine = (ReferenceNeRF(8, 32, input_ch, input_ch_views, 5, use_viewdirs) for _ in range(2))
    reference = Reference(coarse, fine, use_viewdirs=use_viewdirs)
    if tame:
        tame_field(reference, coarse, half_size)
        with torch.no_grad():
            for name, value in coarse.state_dict().items():
                fine.state_dict()[name].copy_(value * (1 + 0.002 * torch.randn(value.shape)))
    return reference


def tame_field(reference: Reference, net: ReferenceNeRF, half_size: float) -> None:
    """Turn a fresh net's field into something like a trained scene, in place: semi-transparent matter
    inside the cube |x|, |y|, |z| < half_size, empty space around it.

    Why: nerf-pytorch's render is defined only up to float32 ulps (torch.linspace alone rounds
    differently per CPU vector width and on CUDA), and the hierarchical sampler amplifies ulps where the
    coarse weights are nearly flat — most at u = 1, where the last fine sample jumps between the last
    bin edge and a point before it as cdf[-1] rounds either side of 1. Any faithful reimplementation
    differs from nerf-pytorch (and nerf-pytorch from itself across devices) by that amplified noise,
    which for a fresh net's 2^9-frequency wiggles everywhere reaches 1e-3..1e-2. A scene with empty
    space around the object and a field that changes at the rate of a smooth scene keeps it below 1e-5.
    So: band k of γ(x) enters with weight 4^-k; inside the cube raw density gets mean −0.3, std 1.5 and
    raw colour std 2; six hidden units carry the distance outside the cube through every layer and
    push the density below zero there.
    """
    band = torch.cat([torch.zeros(3), torch.arange(reference.multires).repeat_interleave(6).float()])
    points = (torch.rand(4096, 3) * 2 - 1) * half_size
    dirs = F.normalize(torch.randn(4096, 3), dim=-1)
    density_layer, density_rows = ((net.alpha_linear, slice(0, 1)) if net.use_viewdirs
                                   else (net.output_linear, slice(3, 4)))
    with torch.no_grad():
        for layer in (net.pts_linears[0], net.pts_linears[5]):  # the layers γ(x) enters: input and skip
            layer.weight[:, :band.numel()] *= 0.25 ** band
        raw = reference.query(net, points[:, None], dirs)[:, 0]
        rescale_rows(density_layer, density_rows, raw[:, 3:4], -0.3, 1.5)
        rescale_rows(net.rgb_linear if net.use_viewdirs else net.output_linear, slice(0, 3), raw[:, :3], 0.0, 2.0)
        carry_outside_distance(net, half_size)
        density_layer.weight[density_rows, :6] = -10.0


def carry_outside_distance(net: ReferenceNeRF, half_size: float) -> None:
    """Hidden units 0..5 of every trunk layer hold relu(±x_i − half_size), zero inside the cube."""
    for index, layer in enumerate(net.pts_linears):
        layer.weight[:6] = 0.0
        layer.bias[:6] = 0.0
        if index == 0:
            for unit in range(6):
                layer.weight[unit, unit // 2] = 1.0 if unit % 2 == 0 else -1.0
            layer.bias[:6] = -half_size
        else:
            offset = net.input_ch if index - 1 in net.skips else 0  # after the skip: cat([γ(x), h])
            for unit in range(6):
                layer.weight[unit, offset + unit] = 1.0


def rescale_rows(layer: nn.Linear, rows: slice, raw: torch.Tensor, mean: float, std: float) -> None:
    """Affinely remap output `rows` of a last linear layer so that `raw`, its outputs now, gets the given
    mean and standard deviation."""
    gain = std / raw.std(dim=0)
    layer.weight[rows] *= gain[:, None]
    layer.bias[rows] = (layer.bias[rows] - raw.mean(dim=0)) * gain + mean


def save_checkpoint(path: Path, reference: Reference) -> Path:
    """nerf-pytorch's checkpoint layout, with a populated Adam state (a zero-gradient step moves nothing)."""
    params = list(reference.coarse.parameters()) + list(reference.fine.parameters())
    optimizer = torch.optim.Adam(params, lr=5e-4, betas=(0.9, 0.999))
    for p in params:
        p.grad = torch.zeros_like(p)
    optimizer.step()
    torch.save({"global_step": 1234, "network_fn_state_dict": reference.coarse.state_dict(),
                "network_fine_state_dict": reference.fine.state_dict(),
                "optimizer_state_dict": optimizer.state_dict()}, path)
    return path


# ---- tiny datasets -----------------------------------------------------------------------------

def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """An OpenGL camera-to-world (looking down −z) at eye towards target."""
    back = np.asarray(eye, float) - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
    return c2w


BLENDER_SIZE, BLENDER_FOV = (12, 10), 0.8  # (width, height): not square, so x and y cannot be swapped


def orbit_blender(folder: Path) -> list[np.ndarray]:
    """transforms_{train,val,test}.json with 2/1/1 frames and tiny RGBA PNGs; returns the c2w per frame."""
    eyes = {"train": [(0.5, -3.8, 1.2), (3.5, 1.0, 1.5)], "val": [(-3.0, 2.0, 1.0)], "test": [(2.0, 3.0, -1.5)]}
    rng = np.random.default_rng(0)
    width, height = BLENDER_SIZE
    frames = {split: [(rng.integers(0, 256, (height, width, 4), dtype=np.uint8), look_at(eye)) for eye in split_eyes]
              for split, split_eyes in eyes.items()}
    write_blender(folder, frames, camera_angle_x=BLENDER_FOV)
    return [c2w for split_frames in frames.values() for _, c2w in split_frames]


LLFF_FULL, LLFF_FACTOR = (80, 96, 90.0), 8  # original (H, W, focal); images_8 are 10 × 12


def forward_llff(folder: Path) -> np.ndarray:
    """poses_bounds.npy for three cameras looking down −z + images_8; returns the array."""
    eyes = [(0.0, 0.0, 0.0), (0.4, 0.1, 0.2), (-0.3, 0.3, -0.1)]
    c2ws = [look_at(eye, target=(0.1 * k, 0.0, -10.0), up=(0.0, 1.0, 0.0)) for k, eye in enumerate(eyes)]
    return write_llff(folder, c2ws, LLFF_FULL, [[2.0 + 0.3 * k, 9.0 - k] for k in range(3)], (LLFF_FACTOR,), 40)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def reference_llff_poses(poses_bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """load_llff_data(recenter=True, bd_factor=.75) poses -> c2w (n, 4, 4) float32, scaled bounds (n, 2)."""
    raw = poses_bounds[:, :15].reshape(-1, 3, 5)
    c2w = np.concatenate([raw[:, :, 1:2], -raw[:, :, 0:1], raw[:, :, 2:4]], axis=2).astype(np.float32)
    bounds = poses_bounds[:, -2:].astype(np.float32)
    scale = 1.0 / (bounds.min() * 0.75)
    c2w[:, :, 3] *= scale
    z, up, center = unit(c2w[:, :, 2].sum(0)), c2w[:, :, 1].sum(0), c2w[:, :, 3].mean(0)
    x = unit(np.cross(up, z))
    # recenter_poses appends a float64 [0, 0, 0, 1] row: the inverse and product run in float64
    average = np.eye(4)
    average[:3] = np.stack([x, unit(np.cross(z, x)), z, center], 1)
    full = np.tile(np.eye(4), (len(c2w), 1, 1))
    full[:, :3] = c2w
    return (np.linalg.inv(average) @ full).astype(np.float32), bounds * scale


def write_config(path: Path, **options) -> Path:
    lines = ["# written by the test, as nerf-pytorch's configs are", "expname = tiny", "basedir = ./logs"]
    lines += [f"{key} = {value}" for key, value in options.items()]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


TINY_NETS = dict(netdepth=8, netwidth=32, netdepth_fine=8, netwidth_fine=32, N_samples=64, N_importance=64,
                 multires=10, multires_views=4)


def blender_config(folder: Path, **overrides) -> Path:
    options = dict(datadir="./data", dataset_type="blender", white_bkgd="True", use_viewdirs="True",
                   half_res="False  # inline comment", raw_noise_std="1e0", **TINY_NETS)
    return write_config(folder / "config.txt", **{**options, **overrides})


# ---- our side ------------------------------------------------------------------------------------

def imported_view(scene, index: int) -> np.ndarray:
    """The scene's hierarchical render of a dataset camera (runtime rays -> TorchRays -> render_hierarchical)."""
    config = scene.config
    camera = config.cameras[index]
    rays = TorchRays.from_batch(field_space_rays(config.render, *camera_rays(camera, config.render.pixel_center)), "cpu")
    sampling = config.render.sampling
    t_vals = torch.from_numpy(sample_positions(SamplingConfig(sampling.near, sampling.far, config.n_coarse)))
    background = torch.tensor(config.render.background, dtype=torch.float32)
    with torch.no_grad():
        _, colors = render_hierarchical(scene.coarse, scene.fine, rays, t_vals.expand(len(rays), -1),
                                        config.n_importance, background)
    return colors.reshape(camera.height, camera.width, 3).numpy()


def reference_fingerprint(reference: Reference, architecture: dict) -> str:
    tensors = {f"{role}.{name}": value.numpy() for role, net in (("coarse", reference.coarse), ("fine", reference.fine))
               for name, value in net.state_dict().items()}
    return weights_fingerprint(tensors, architecture)


# ---- tests ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("use_viewdirs", [True, False])
def test_blender_import_renders_as_nerf_pytorch(tmp_path, use_viewdirs):
    folder = tmp_path / "run"
    poses = orbit_blender(folder / "data")
    config = blender_config(folder, use_viewdirs=str(use_viewdirs))
    reference = make_reference(seed=2, use_viewdirs=use_viewdirs)
    checkpoint = save_checkpoint(tmp_path / "200000.tar", reference)
    import_nerf_pytorch(checkpoint, config, tmp_path / "scene", grid_resolution=8)
    scene = load_scene(tmp_path / "scene")

    assert scene.config.source == "nerf-pytorch" and scene.config.render.pixel_center == 0.0
    assert scene.config.render.background == (1.0, 1.0, 1.0) and scene.config.render.ndc is None
    assert (scene.config.render.sampling.near, scene.config.render.sampling.far) == (2.0, 6.0)
    assert len(scene.config.cameras) == len(poses)
    width, height = BLENDER_SIZE
    focal = 0.5 * width / np.tan(0.5 * BLENDER_FOV)
    for index in (0, 3):  # a train and the test view
        expected = reference.render_view(poses[index], height, width, focal, False, 2.0, 6.0, True)
        ours = imported_view(scene, index)
        assert 0.05 < expected.std() and expected.min() < 0.9  # the view composites something
        assert np.abs(ours - expected).max() < TOLERANCE
    if use_viewdirs:  # every parameter maps one to one: the weights are bit-identical
        assert scene.fingerprint() == reference_fingerprint(reference, scene.config.architecture())


@pytest.mark.parametrize("use_viewdirs", [True, False])
def test_imported_fields_equal_nerf_pytorch_networks(tmp_path, use_viewdirs):
    """Fresh nets (every encoding band at full weight): same outputs, bit-identical weights."""
    reference = make_reference(seed=5, use_viewdirs=use_viewdirs, tame=False)
    config = read_config(blender_config(tmp_path, use_viewdirs=str(use_viewdirs)))
    checkpoint = save_checkpoint(tmp_path / "c.tar", reference)
    fields = load_fields(read_checkpoint(checkpoint), config, checkpoint)
    points, dirs = torch.randn(512, 3) * 2, F.normalize(torch.randn(512, 3), dim=-1)
    for ours, theirs in zip(fields, (reference.coarse, reference.fine)):
        with torch.no_grad():
            rgb, sigma = ours(points, dirs)
            raw = reference.query(theirs, points[:, None], dirs)[:, 0]
        # equal up to float32 rounding: the matmuls may sum in another order
        assert torch.allclose(rgb, torch.sigmoid(raw[:, :3]), rtol=0, atol=1e-6)
        assert torch.allclose(sigma, F.relu(raw[:, 3]), rtol=1e-6, atol=1e-6)
        expected = theirs.state_dict()
        for name, value in ours.state_dict().items():
            assert torch.equal(value, expected[name][:4] if name.startswith("output_linear") else expected[name])


def test_llff_ndc_import_renders_as_nerf_pytorch(tmp_path):
    poses_bounds = forward_llff(tmp_path / "fern_tiny")
    config = write_config(tmp_path / "config.txt", datadir=tmp_path / "fern_tiny", dataset_type="llff",
                          factor=LLFF_FACTOR, llffhold=8, use_viewdirs="True", **TINY_NETS)
    reference = make_reference(seed=2, half_size=0.8)
    import_nerf_pytorch(save_checkpoint(tmp_path / "ckpt.tar", reference), config, tmp_path / "scene",
                        grid_resolution=8)
    scene = load_scene(tmp_path / "scene")

    c2ws, _ = reference_llff_poses(poses_bounds)
    height, width, focal = LLFF_FULL[0] // LLFF_FACTOR, LLFF_FULL[1] // LLFF_FACTOR, LLFF_FULL[2] / LLFF_FACTOR
    ndc = scene.config.render.ndc
    assert ndc is not None and scene.config.render.background == (0.0, 0.0, 0.0)
    assert np.allclose([ndc.tan_half_fov_x, ndc.tan_half_fov_y, ndc.near_plane],
                       [width / (2 * focal), height / (2 * focal), 1.0], rtol=1e-6)
    for index in (0, 2):
        expected = reference.render_view(c2ws[index], height, width, focal, True, 0.0, 1.0, False)
        ours = imported_view(scene, index)
        assert expected.std() > 0.02
        assert np.abs(ours - expected).max() < TOLERANCE
    assert scene.fingerprint() == reference_fingerprint(reference, scene.config.architecture())


def revealed_view(model: Path, index: int, folder: Path) -> tuple[np.ndarray, dict]:
    """`noisenerf-reveal MODEL --view index` as a subprocess -> float image (from EXR), JSON report."""
    out = folder / f"view{index}.exr"
    result = run_reveal(model, "--view", index, "-o", out, "--json", "--threads", 1)
    assert result.returncode == 0, result.stderr
    return read_image(out), json.loads(result.stdout)


HIERARCHICAL_SAMPLES = 32  # N_samples = N_importance: 32 coarse + 32 fine, as in issue 10's reference renders


@pytest.mark.parametrize("kind", ["blender", "llff"])
def test_reveal_view_renders_hierarchically_as_nerf_pytorch(tmp_path, kind):
    """The recipient's ordinary render is nerf-pytorch's: coarse → sample_pdf → fine, in numpy through
    onnxruntime. Blender with fresh nets (density everywhere in the box and beyond), LLFF/NDC tamed."""
    n = HIERARCHICAL_SAMPLES
    nets = {**TINY_NETS, "N_samples": n, "N_importance": n}
    if kind == "blender":
        poses = orbit_blender(tmp_path / "data")
        config = blender_config(tmp_path, **nets)
        reference = make_reference(seed=3, tame=False)
        width, height = BLENDER_SIZE
        views = [(index, poses[index], height, width, 0.5 * width / np.tan(0.5 * BLENDER_FOV)) for index in (0, 3)]
        render_args = (False, 2.0, 6.0, True)
    else:
        c2ws, _ = reference_llff_poses(forward_llff(tmp_path / "fern_tiny"))
        config = write_config(tmp_path / "config.txt", datadir=tmp_path / "fern_tiny", dataset_type="llff",
                              factor=LLFF_FACTOR, llffhold=8, use_viewdirs="True", **nets)
        reference = make_reference(seed=2, half_size=0.8)
        height, width, focal = LLFF_FULL[0] // LLFF_FACTOR, LLFF_FULL[1] // LLFF_FACTOR, LLFF_FULL[2] / LLFF_FACTOR
        views = [(index, c2ws[index], height, width, focal) for index in (0, 2)]
        render_args = (True, 0.0, 1.0, False)
    reference.n_samples = reference.n_importance = n
    import_nerf_pytorch(save_checkpoint(tmp_path / "ckpt.tar", reference), config, tmp_path / "scene",
                        grid_resolution=8)
    export_scene(tmp_path / "scene", tmp_path / "model.onnx")
    for index, c2w, h, w, focal in views:
        expected = reference.render_view(c2w, h, w, focal, *render_args)
        ours, report = revealed_view(tmp_path / "model.onnx", index, tmp_path)
        assert expected.std() > 0.02
        assert np.abs(ours - expected).max() < 1e-4
        assert report["hierarchical"] and report["samples"] == h * w * (n + n + n)  # coarse, then fine on 2n


def test_llff_without_ndc_uses_scaled_depth_bounds(tmp_path):
    poses_bounds = forward_llff(tmp_path / "data")
    _, bounds = reference_llff_poses(poses_bounds)
    assert llff_world_bounds(tmp_path / "data") == pytest.approx((0.9 * bounds.min(), bounds.max()), rel=1e-6)
    config = read_config(write_config(tmp_path / "c.txt", dataset_type="llff", no_ndc="True", **TINY_NETS))
    cameras, near, far, ndc, aabb = scene_geometry(config, tmp_path / "data")
    assert ndc is None and (near, far) == pytest.approx((0.9 * bounds.min(), bounds.max()))
    centres = np.array([c.matrix()[:3, 3] for c in cameras])
    assert np.all(centres >= np.array(aabb[:3]) - 1e-6) and np.all(centres <= np.array(aabb[3:]) + 1e-6)


def test_blender_half_res_halves_size_and_focal(tmp_path):
    orbit_blender(tmp_path / "data")
    config = read_config(blender_config(tmp_path, half_res="True", white_bkgd="False"))
    cameras, near, far, ndc, _ = scene_geometry(config, tmp_path / "data")
    width, height = BLENDER_SIZE
    assert [(c.width, c.height, c.cx, c.cy) for c in cameras] == [(width // 2, height // 2, 3.0, 2.5)] * 4
    assert cameras[0].fx == pytest.approx(0.25 * width / np.tan(0.5 * BLENDER_FOV), rel=1e-12)
    assert (near, far, ndc, config.background) == (2.0, 6.0, None, (0.0, 0.0, 0.0))


def test_fern_cameras_follow_load_llff_data(shared_data, tmp_path):
    folder = shared_data / "scenes" / "llff" / "fern"
    poses_bounds = np.load(folder / "poses_bounds.npy")
    c2ws, _ = reference_llff_poses(poses_bounds)
    config = read_config(write_config(tmp_path / "fern.txt", datadir=folder, dataset_type="llff", factor=8))
    cameras, near, far, ndc, _ = scene_geometry(config, folder)
    focal = poses_bounds[0, 14] / 8
    assert (near, far) == (0.0, 1.0) and len(cameras) == len(c2ws)
    for camera, c2w in zip(cameras, c2ws):
        assert np.abs(camera.matrix() - c2w).max() < 1e-5
        assert camera.fx == pytest.approx(focal, rel=1e-6) and (camera.width, camera.height) == (504, 378)
    assert ndc.tan_half_fov_x == pytest.approx(504 / (2 * focal), rel=1e-6)


def test_config_follows_configargparse_and_nerf_pytorch_defaults(tmp_path):
    text = "# comment\n; also a comment\n[section]\nN_samples: 32\n--netwidth 128\nwhite_bkgd\n" \
           "use_viewdirs = False  # inline\nexpname = 'quoted name'\nN_samples = 48\n"
    assert parse_config_text(text, "t") == {"N_samples": "48", "netwidth": "128", "white_bkgd": "true",
                                            "use_viewdirs": "False", "expname": "quoted name"}
    path = tmp_path / "c.txt"
    path.write_text("expname = x\n")
    config = read_config(path)
    assert (config.dataset_type, config.use_viewdirs, config.n_samples, config.n_importance, config.factor) == \
        ("llff", False, 64, 0, 8)
    assert (config.netdepth, config.netwidth, config.multires, config.multires_views) == (8, 256, 10, 4)
    assert config.uses_ndc and config.background == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("options, message", [
    ({"lindisp": "True"}, "lindisp"),
    ({"i_embed": "-1"}, "i_embed"),
    ({"dataset_type": "deepvoxels"}, "deepvoxels"),
    ({"netwidth": "wide"}, "netwidth"),
    ({"N_rays": "4"}, "unknown option 'N_rays'"),
])
def test_unsupported_configs_are_refused(tmp_path, options, message):
    config = blender_config(tmp_path, **options)
    checkpoint = save_checkpoint(tmp_path / "c.tar", make_reference(0))
    with pytest.raises(UserError, match=message):
        import_nerf_pytorch(checkpoint, config, tmp_path / "scene")
    assert not (tmp_path / "scene").exists()


def test_lindisp_is_accepted_under_ndc_where_nerf_pytorch_ignores_it(tmp_path):
    assert read_config(write_config(tmp_path / "c.txt", dataset_type="llff", lindisp="True")).lindisp


class Payload:
    """Unpickling this would create the marker file: a weights-only load must never do it."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def broken_checkpoints(folder: Path) -> dict[str, tuple[Path, str]]:
    """Name -> (checkpoint, expected message) for every way a checkpoint is refused."""
    reference = make_reference(0)
    state = {"global_step": 1, "network_fn_state_dict": reference.coarse.state_dict(),
             "network_fine_state_dict": reference.fine.state_dict()}
    missing = {**state, "network_fn_state_dict": {k: v for k, v in state["network_fn_state_dict"].items()
                                                  if k != "pts_linears.3.bias"}}
    wrong = {**state, "network_fine_state_dict": {**state["network_fine_state_dict"],
                                                  "pts_linears.5.weight": torch.zeros(32, 32)}}
    extra = {**state, "network_fn_state_dict": {**state["network_fn_state_dict"], "extra.weight": torch.zeros(1)}}
    no_fine = {k: v for k, v in state.items() if k != "network_fine_state_dict"}
    nan = {**state, "network_fine_state_dict": {**state["network_fine_state_dict"],
                                                "rgb_linear.bias": torch.tensor([0.0, float("nan"), 0.0])}}
    cases = {"nan": (nan, r"network_fine_state_dict\['rgb_linear.bias'\] holds NaN or infinite values"),
             "missing": (missing, "lacks parameter 'pts_linears.3.bias'"),
             "shape": (wrong, r"network_fine_state_dict\['pts_linears.5.weight'\] has shape \(32, 32\)"),
             "extra": (extra, "has parameter 'extra.weight'"),
             "no_fine": (no_fine, "needs a fine network"),
             "payload": ({**state, "optimizer_state_dict": Payload(folder / "MARKER")}, "refused")}
    paths = {}
    for name, (content, message) in cases.items():
        torch.save(content, folder / f"{name}.tar")
        paths[name] = (folder / f"{name}.tar", message)
    torch.save({**state, "optimizer_state_dict": Payload(folder / "MARKER")}, folder / "legacy.tar",
               _use_new_zipfile_serialization=False)
    paths["legacy"] = (folder / "legacy.tar", "refused")
    (folder / "text.tar").write_text("not a checkpoint at all\n")
    paths["text"] = (folder / "text.tar", "not a torch checkpoint")
    return paths


def test_bad_checkpoints_are_refused_without_running_or_writing_anything(tmp_path):
    config = blender_config(tmp_path)
    for name, (checkpoint, message) in broken_checkpoints(tmp_path).items():
        with pytest.raises(UserError, match=message):
            import_nerf_pytorch(checkpoint, config, tmp_path / "scene")
        assert not (tmp_path / "scene").exists(), name
    assert not (tmp_path / "MARKER").exists()


def test_missing_output_parent_is_refused(tmp_path):
    config = blender_config(tmp_path)
    checkpoint = save_checkpoint(tmp_path / "c.tar", make_reference(0))
    with pytest.raises(UserError, match="output folder does not exist"):
        import_nerf_pytorch(checkpoint, config, tmp_path / "nowhere" / "scene")
