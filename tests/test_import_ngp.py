"""`noisenerf import-nerfstudio` of nerfstudio's `instant-ngp` method: a run made by nerfstudio 1.1.5's own classes on
the CPU (tests/goldens/ngp_torch, tools/nerfstudio_ngp_goldens.py: nerfacc cannot train or march without CUDA, so the
run is untrained, its hash table redrawn wide and its occupancy grid updated once by nerfacc's own torch code).

Checked against nerfstudio's numbers: the field, the grid, the compositor on nerfstudio's intervals. nerfacc's marcher
(a CUDA kernel) has no CPU path, so runtime.grid_marching is checked against a line-by-line transcription of
nerfacc/cuda/csrc/grid.cu written here, scalar, one ray at a time."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import (
    NGP_GOLDENS, assert_photos_hide_exactly, assert_refused, nerfstudio_run_from_goldens, run_main, run_reveal,
)
from noisenerf.cli.main import main
from noisenerf.runtime.model import load_model

F32 = np.float32


@pytest.fixture(scope="module")
def ngp_run(tmp_path_factory):
    from safetensors.numpy import load_file
    folder = tmp_path_factory.mktemp("ngp")
    run, data = nerfstudio_run_from_goldens(folder, NGP_GOLDENS)
    assert main(["import-nerfstudio", str(run), "-o", str(folder / "scene"), "--data", str(data)]) in (0, None)
    assert main(["export", str(folder / "scene"), "-o", str(folder / "model.onnx")]) in (0, None)
    return (load_model(folder / "model.onnx"), load_file(NGP_GOLDENS / "golden.safetensors"),
            load_file(NGP_GOLDENS / "weights.safetensors"), folder)


def test_field_outputs_are_nerfstudios(ngp_run):
    """NerfactoField as instant-ngp builds it (density scale 1, zero appearance at eval) at points inside, around
    and far outside the box."""
    model, golden, _, _ = ngp_run
    rgb, sigma = model.field(golden["points"], golden["points_directions"])
    assert np.abs(rgb - golden["points_rgb"]).max() < 1e-5
    assert np.allclose(sigma, golden["points_density"][:, 0], rtol=1e-4, atol=1e-12)


def test_the_grid_is_the_checkpoints(ngp_run):
    """The occupancy bits, the levels' boxes as nerfacc enlarges them, and nerfstudio's default step (the box's
    diagonal / 1000)."""
    model, _, weights, _ = ngp_run
    marching = model.sampler().marching
    assert np.array_equal(marching.occupied, weights["_model.occupancy_grid.binaries"])
    assert np.array_equal(marching.aabbs, weights["_model.occupancy_grid.aabbs"])
    assert F32(marching.step) == F32(0.003464101552963257)
    assert (marching.cone_angle, marching.near, marching.far) == (0.004, 0.05, 1000.0)


def test_compositing_is_nerfaccs(ngp_run):
    """On nerfstudio's own intervals and field outputs (512 steps from the near plane): nerfacc's weights
    (T·α, T = exp(−exclusive cumsum σδ)) and nerfstudio's RGB renderer over black."""
    from noisenerf.runtime.compositing import composite, render_weights
    _, golden, _, _ = ngp_run
    deltas = golden["rays_t_ends"] - golden["rays_t_starts"]
    weights = render_weights(golden["rays_sample_density"], deltas)
    assert np.allclose(weights, golden["rays_sample_weights"], rtol=1e-5, atol=1e-7)
    colours = np.clip(composite(weights, golden["rays_sample_rgb"], np.zeros(3, F32)), 0, 1)
    assert np.abs(colours - golden["rays_rgb"]).max() < 1e-5


def test_box_entries_are_nerfaccs(ngp_run):
    from noisenerf.runtime.grid_marching import box_entries
    model, golden, _, _ = ngp_run
    directions = golden["rays_directions"]
    t_min, t_max, hit = box_entries(golden["rays_origins"], (F32(1) / directions).astype(F32), model.sampler().marching.aabbs)
    assert np.array_equal(hit, golden["rays_aabb_hit"].astype(bool))
    assert np.allclose(t_min[hit], golden["rays_aabb_tmin"][hit], rtol=1e-6, atol=1e-6)
    assert np.allclose(t_max[hit], golden["rays_aabb_tmax"][hit], rtol=1e-6, atol=1e-6)


# ---- nerfacc/cuda/csrc/grid.cu, transcribed line by line (one ray, float32 scalars) --------------------

def kernel_fma(a, b, c):
    return F32(float(a) * float(b) + float(c))


def kernel_dt(t, cone, step):
    return max(F32(step), min(F32(t * F32(cone)), F32(1e10)))


def kernel_intersect(o, inv, box):
    """utils_grid.cuh ray_aabb_intersect."""
    def axis(i):
        if inv[i] >= 0:
            return F32((box[i] - o[i]) * inv[i]), F32((box[i + 3] - o[i]) * inv[i])
        return F32((box[i + 3] - o[i]) * inv[i]), F32((box[i] - o[i]) * inv[i])
    tmin, tmax = axis(0)
    for i in (1, 2):
        lo, hi = axis(i)
        if tmin > hi or lo > tmax:
            return False, np.inf, np.inf
        tmin, tmax = (lo if lo > tmin else tmin), (hi if hi < tmax else tmax)
    if tmax <= 0:
        return False, np.inf, np.inf
    return True, tmin, tmax


def kernel_march(o, d, marching):
    """traverse_grids_kernel for one ray: its intervals [(t0, t1), ...]."""
    o, d = o.astype(F32), d.astype(F32)
    with np.errstate(divide="ignore"):
        inv = (F32(1) / d).astype(F32)
    boxes, res, step, cone = marching.aabbs, marching.resolution, marching.step, marching.cone_angle
    near, far, eps = F32(marching.near), F32(marching.far), F32(1e-6)
    hits, enters, leaves = zip(*(kernel_intersect(o, inv, box) for box in boxes))
    events, n = [*enters, *leaves], len(boxes)
    order = np.argsort(np.array(events, F32), kind="stable")
    t_sorted = np.array(events, F32)[order]
    out, t_last, continuous = [], near, False
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for i in range(2 * n - 1):
            entering, level = order[i] < n, order[i] % n
            if not hits[level]:
                continue
            if not entering:
                if order[i + 1] < n:
                    continue
                level = order[i + 1] % n
                if not hits[level]:
                    continue
            tmin, tmax = max(t_sorted[i], near), min(t_sorted[i + 1], far)
            if tmin >= tmax:
                continue
            if not continuous:
                dt = kernel_dt(t_last, cone, step)
                while not t_last + dt * F32(0.5) >= tmin:
                    t_last = F32(t_last + dt)
            lo, hi = boxes[level][:3], boxes[level][3:]
            voxel = ((hi - lo) / F32(res)).astype(F32)
            start = np.array([kernel_fma(d[k], F32(tmin + eps), o[k]) for k in range(3)], F32)
            end = np.array([kernel_fma(d[k], F32(tmax - eps), o[k]) for k in range(3)], F32)
            current = [min(max(int(F32(F32((start[k] - lo[k]) / (hi[k] - lo[k])) * F32(res))), 0), res - 1) for k in range(3)]
            final = [min(max(int(F32(F32((end[k] - lo[k]) / (hi[k] - lo[k])) * F32(res))), 0), res - 1) for k in range(3)]
            steps = [0 if d[k] == 0 else (1 if d[k] > 0 else -1) for k in range(3)]
            tdist = [tmax if d[k] == 0 else kernel_fma(F32(lo[k] + kernel_fma(F32(current[k] + (d[k] > 0)), voxel[k], -start[k])),
                                                       inv[k], tmin) for k in range(3)]
            delta = [tmax if d[k] == 0 else F32(F32(voxel[k] * inv[k]) * F32(steps[k])) for k in range(3)]
            overflow = [final[k] + steps[k] for k in range(3)]
            while True:
                t_traverse = min(min(tdist), tmax)
                if not marching.occupied[level, current[0], current[1], current[2]]:
                    dt = kernel_dt(t_last, cone, step)
                    while not t_last + dt * F32(0.5) >= t_traverse:
                        t_last = F32(t_last + dt)
                    continuous = False
                else:
                    while True:
                        dt = kernel_dt(t_last, cone, step)
                        if t_last + dt * F32(0.5) >= t_traverse:
                            break
                        t_next = F32(t_last + dt)
                        out.append((t_last, t_next))
                        continuous, t_last = True, t_next
                        if t_next >= t_traverse:
                            break
                k = 0 if tdist[0] < tdist[1] and tdist[0] < tdist[2] else (1 if tdist[1] < tdist[2] else 2)
                current[k] += steps[k]
                tdist[k] = F32(tdist[k] + delta[k])
                if current[k] == overflow[k]:
                    break
    return out


def test_the_marcher_is_nerfaccs_kernel(ngp_run):
    """runtime.grid_marching.march against the kernel transcribed above, interval for interval, on nerfstudio's
    rays of a train camera and on rays from outside every box, from inside the box, and along the axes."""
    from noisenerf.runtime.grid_marching import march
    model, golden, _, _ = ngp_run
    marching = model.sampler().marching
    rng = np.random.default_rng(3)
    outside = rng.normal(size=(6, 3)) * 12
    origins = [golden["rays_origins"], rng.uniform(-0.9, 0.9, (6, 3)), outside, np.array([[0.3, 0.2, -9.0], [0.0, 0.0, 0.0]])]
    directions = [golden["rays_directions"], rng.normal(size=(6, 3)), rng.normal(size=(6, 3)) * 2 - outside,
                  np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])]
    origins, directions = np.concatenate(origins).astype(F32), np.concatenate(directions)
    directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(F32)
    ray_index, t_start, t_end = march(origins, directions, marching)
    total = 0
    for ray in range(len(origins)):
        want = np.array(kernel_march(origins[ray], directions[ray], marching), F32).reshape(-1, 2)
        mine = np.stack([t_start[ray_index == ray], t_end[ray_index == ray]], 1)
        assert np.array_equal(mine, want), ray
        total += len(want)
    assert total > 2000 and len(np.unique(ray_index)) == len(origins)


def test_ordinary_render_marches_the_grid(ngp_run, tmp_path):
    """`noisenerf-reveal MODEL --view I`: onnxruntime's render equals the torch field's through the same marcher;
    every pixel composited over black and clamped."""
    from noisenerf.runtime.render import render_view
    from noisenerf.train.scene.render import numpy_field
    from noisenerf.train.scene.scene import load_scene
    model, _, _, folder = ngp_run
    scene = load_scene(folder / "scene")
    camera = model.cameras[3]
    onnx_image, stats = render_view(camera, model.render_config, model.field, model.sampler())
    torch_image, _ = render_view(camera, model.render_config, numpy_field(scene.render_field), scene.sampler())
    assert np.abs(onnx_image - torch_image).max() < 1e-5
    assert stats.n_samples_evaluated > 64 * 64 and np.isfinite(onnx_image).all()
    assert onnx_image.min() >= 0 and onnx_image.max() <= 1 and onnx_image.std() > 0.01
    result = run_reveal(folder / "model.onnx", "--view", "3", "-o", tmp_path / "view3.png")
    assert result.returncode == 0, result.stderr


def test_photos_hidden_in_an_instant_ngp_run_reveal_exactly(ngp_run, shared_data, tmp_path, capfd):
    _, _, _, folder = ngp_run
    photos = (shared_data / "secrets" / "imagenet" / "n01882714_koala.JPEG", shared_data / "secrets" / "ost" / "OST_013.png")
    assert_photos_hide_exactly(folder, photos, (5, 20), tmp_path, capfd)


@pytest.mark.parametrize("edit, message", [
    (("disable_scene_contraction: false", "disable_scene_contraction: true"), "without scene contraction"),
    (("background_color: random", "background_color: white"), "background 'white' is not reproduced"),
    (("enable_collider: false", "enable_collider: true"), "with a collider is not reproduced"),
    (("grid_levels: 4", "grid_levels: 3"), "occupancy_grid.binaries has shape [4, 32, 32, 32], the config implies [3, 32, 32, 32]"),
])
def test_instant_ngp_runs_that_would_not_be_reproduced_are_refused(tmp_path, capfd, edit, message):
    run, data = nerfstudio_run_from_goldens(tmp_path, NGP_GOLDENS)
    config = run / "config.yml"
    assert edit[0] in config.read_text()
    config.write_text(config.read_text().replace(*edit))
    result = run_main(main, ["import-nerfstudio", run, "-o", tmp_path / "out", "--data", data], capfd)
    assert_refused(result, tmp_path / "out", message)

