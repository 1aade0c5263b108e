"""`noisenerf import-nerfstudio`: nerfacto runs of both implementations, checked against the layouts' spec
(an independent numpy evaluation of the checkpoint's own tensors, written from the research notes' figures,
not from the importer), against nerfstudio's own numbers (tests/goldens/nerfacto_torch, made by
tools/nerfstudio_goldens.py from a run nerfstudio trained), end to end through a hide and a reveal, and
with hostile run directories."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from helpers import (
    NERFSTUDIO_RUNS, assert_hides_exactly, assert_photos_hide_exactly, assert_refused, nerfstudio_layout, nerfstudio_run_from_goldens, run_main, run_reveal, spec_grid, tcnn_mlp, tcnn_sh, write_nerfstudio_run, write_png,
)
from noisenerf.cli.main import main
from noisenerf.runtime.model import load_model

# ---- the spec, evaluated on the checkpoint's own tensors ---------------------------------------------

def contract(points):
    norm = np.abs(points).max(-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        contracted = np.where(norm < 1, points, (2 - 1 / norm) * (points / norm))
    unit = (contracted + 2) / 4
    inside = np.all((unit > 0) & (unit < 1), -1, keepdims=True)
    return unit * inside, inside[:, 0]


def spec_sh(d, implementation):
    """tiny-cuda-nn's SH of d (degree 4), or nerfstudio's torch SH polynomial of (d + 1)/2."""
    if implementation == "tcnn":
        return tcnn_sh(d)
    x, y, z = ((d + 1) / 2).T
    xx, yy, zz = x * x, y * y, z * z
    return np.stack([np.full_like(x, 0.28209479177387814), 0.4886025119029199 * y, 0.4886025119029199 * z,
                     0.4886025119029199 * x, 1.0925484305920792 * x * y, 1.0925484305920792 * y * z,
                     0.9461746957575601 * zz - 0.31539156525251999, 1.0925484305920792 * x * z,
                     0.5462742152960396 * (xx - yy), 0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * x * y * z,
                     0.4570457994644658 * y * (5 * zz - 1), 0.3731763325901154 * z * (5 * zz - 3),
                     0.4570457994644658 * x * (5 * zz - 1), 1.445305721320277 * z * (xx - yy),
                     0.5900435899266435 * x * (xx - 3 * yy)], 1)


def torch_mlp(state, prefix, x, layers):
    for i in range(layers):
        x = x @ state[f"{prefix}{i}.weight"].T + state[f"{prefix}{i}.bias"]
        if i < layers - 1:
            x = np.maximum(x, 0)
    return x


def spec_field(state, implementation, points, viewdirs):
    """rgb, σ of the nerfacto field and σ of each proposal network, float64, from the checkpoint's tensors."""
    state = {k: v.double().numpy() for k, v in state.items()}
    if implementation == "tcnn":
        state = {k: v.astype(np.float16).astype(np.float64) if "params" in k else v for k, v in state.items()}
    unit, inside = contract(points.astype(np.float64))
    appearance = state["field.embedding_appearance.embedding.weight"].mean(0)
    sh = spec_sh(viewdirs.astype(np.float64), implementation)
    if implementation == "tcnn":
        flat = state["field.mlp_base.model.params"]
        features = spec_grid(unit, flat[64 * 16 + 16 * 64:].reshape(-1, 2), 8, 10, 256, implementation)
        base, _ = tcnn_mlp(flat, features, (64, 16), 0.0)
        head_in = np.concatenate([sh, base[:, 1:], np.broadcast_to(appearance, (len(sh), 32))], 1)
        rgb, _ = tcnn_mlp(state["field.mlp_head.tcnn_encoding.params"], head_in, (64, 64, 3), 1.0)
    else:
        features = spec_grid(unit, state["field.mlp_base.model.0.hash_table"], 8, 10, 256, implementation)
        base = torch_mlp(state, "field.mlp_base.model.1.layers.", features, 2)
        head_in = np.concatenate([sh, base[:, 1:], np.broadcast_to(appearance, (len(sh), 32))], 1)
        rgb = torch_mlp(state, "field.mlp_head.layers.", head_in, 3)
    sigma = 0.01 * np.exp(base[:, 0]) * inside
    proposals = []
    for i, max_res in enumerate((64, 128)):
        net = f"proposal_networks.{i}"
        if implementation == "tcnn":
            grid = spec_grid(unit, state[f"{net}.encoding.tcnn_encoding.params"].reshape(-1, 2), 5, 8, max_res, "tcnn")
            raw, _ = tcnn_mlp(state[f"{net}.mlp_base.1.tcnn_encoding.params"], grid, (16, 1), 1.0)
        else:
            grid = spec_grid(unit, state[f"{net}.encoding.hash_table"], 5, 8, max_res, "torch")
            raw = torch_mlp(state, f"{net}.mlp_base.1.layers.", grid, 2)
        proposals.append(0.01 * np.exp(raw[:, 0]) * inside)
    return 1 / (1 + np.exp(-rgb)), sigma, proposals


def checkpoint_state(run):
    from noisenerf.train.scene.import_nerfstudio import read_pipeline
    return read_pipeline(run / "nerfstudio_models" / "step-000000099.ckpt")


@pytest.fixture(scope="module", params=["torch", "tcnn"])
def imported(request, tmp_path_factory):
    """A synthetic run of each implementation, imported and exported through the command line."""
    folder = tmp_path_factory.mktemp(f"ns_{request.param}")
    run, data = write_nerfstudio_run(folder, request.param, seed=3, prefix="_model.module." if request.param == "tcnn"
                                     else "_model.")
    assert main(["import-nerfstudio", str(run), "-o", str(folder / "scene"), "--data", str(data)]) in (0, None)
    assert main(["export", str(folder / "scene"), "-o", str(folder / "model.onnx")]) in (0, None)
    return request.param, run, data, folder


def test_layout_figures_of_nerfactos_defaults():
    """The research notes' parameter counts: the default field's 12,199,312 (tcnn), its proposals' grids."""
    from noisenerf.runtime.fields.nerfacto import grid_layout
    from noisenerf.train.scene.nerfacto import grid_scales
    field = grid_layout("tcnn", grid_scales("tcnn", 16, 16, 2048), 19)
    assert field.total_rows * 2 + 64 * 32 + 16 * 64 == 12_199_312
    assert field.dense.tolist() == [1] * 5 + [0] * 11 and field.resolution[:5].tolist() == [16, 23, 31, 43, 59]
    assert grid_layout("tcnn", grid_scales("tcnn", 5, 16, 128), 17).total_rows * 2 == 766_528
    assert grid_layout("tcnn", grid_scales("tcnn", 5, 16, 256), 17).total_rows * 2 == 860_160
    torch_grid = grid_layout("torch", grid_scales("torch", 16, 16, 2048), 19)
    assert torch_grid.total_rows == 16 << 19 and not torch_grid.dense.any()
    assert torch_grid.offset.tolist() == [level << 19 for level in range(16)]


def test_field_equals_the_spec_through_onnxruntime(imported):
    implementation, run, _, folder = imported
    model = load_model(folder / "model.onnx")
    rng = np.random.default_rng(0)
    points = (rng.normal(size=(3000, 3)) * rng.choice([0.3, 2.0, 40.0], size=(3000, 1))).astype(np.float32)
    viewdirs = rng.normal(size=(3000, 3)).astype(np.float32)
    viewdirs /= np.linalg.norm(viewdirs, axis=1, keepdims=True)
    rgb, sigma = model.field(points, viewdirs)
    want_rgb, want_sigma, want_proposals = spec_field(checkpoint_state(run), implementation, points, viewdirs)
    assert np.abs(rgb - want_rgb).max() < 2e-5
    assert np.allclose(sigma, want_sigma, rtol=2e-4, atol=1e-9)
    for i, want in enumerate(want_proposals):
        assert np.allclose(model.field.proposal_density(i)(points), want, rtol=2e-4, atol=1e-9)


def test_cameras_are_nerfstudios(imported):
    """Frames sorted by file name, poses through the dataparser transform and scale, intrinsics as given."""
    import json
    _, run, data, folder = imported
    model = load_model(folder / "model.onnx")
    meta = json.loads((data / "transforms.json").read_text())
    frames = sorted(meta["frames"], key=lambda f: f["file_path"])
    parser = json.loads((run / "dataparser_transforms.json").read_text())
    for camera, frame in zip(model.cameras, frames, strict=True):
        pose = np.vstack([parser["transform"], [0, 0, 0, 1]]) @ np.array(frame["transform_matrix"])
        pose[:3, 3] *= parser["scale"]
        assert np.allclose(camera.matrix(), pose, atol=1e-6)
        assert (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy) == (12, 10, 11.0, 10.5, 6.2, 4.9)


def test_ordinary_render_follows_the_proposal_sampler(imported):
    """`noisenerf-reveal MODEL --view I`: onnxruntime's render equals the torch field's through the same
    pipeline, and every pixel is the last-sample compositor's (in [0, 1], finite)."""
    from noisenerf.runtime.render import render_view
    from noisenerf.train.scene.render import numpy_field
    from noisenerf.train.scene.scene import load_scene
    _, _, _, folder = imported
    model = load_model(folder / "model.onnx")
    scene = load_scene(folder / "scene")
    onnx_image, stats = render_view(model.cameras[2], model.render_config, model.field, model.sampler())
    torch_image, _ = render_view(model.cameras[2], model.render_config, numpy_field(scene.render_field), scene.sampler())
    assert stats.n_samples_evaluated == 12 * 10 * 48
    assert np.abs(onnx_image - torch_image).max() < 1e-5
    assert np.isfinite(onnx_image).all() and onnx_image.min() >= 0 and onnx_image.max() <= 1
    result = run_reveal(folder / "model.onnx", "--view", "2", "-o", folder / "view2.png")
    assert result.returncode == 0, result.stderr


def test_a_photo_hidden_in_an_imported_run_reveals_exactly(imported, tmp_path, capfd):
    _, _, _, folder = imported
    rng = np.random.default_rng(5)
    secret = write_png(tmp_path / "secret.png", rng.integers(0, 256, (6, 7, 3), dtype=np.uint8))
    assert_hides_exactly(folder, secret, 4, capfd)


# ---- hostile and unsupported run directories ---------------------------------------------------------

def refused_import(tmp_path, capfd, run, data, message):
    result = run_main(main, ["import-nerfstudio", run, "-o", tmp_path / "out", "--data", data], capfd)
    assert_refused(result, tmp_path / "out", message)


def test_the_data_the_run_recorded_is_found_or_named_in_the_refusal(tmp_path, capfd):
    """Without --data the run's recorded path (here `data`, as ns-train was given it) is looked up beside the run's
    parent folders; where it is gone, the one line names it."""
    run, data = write_nerfstudio_run(tmp_path, "torch", seed=2)
    result = run_main(main, ["import-nerfstudio", run, "-o", tmp_path / "found", "--json"], capfd)
    assert result.code == 0, result.err
    data.rename(tmp_path / "moved")
    result = run_main(main, ["import-nerfstudio", run, "-o", tmp_path / "out"], capfd)
    assert_refused(result, tmp_path / "out", "the run's dataset (transforms.json) was not found at the path it "
                   "recorded, 'data', as given or under the run's parent folders; give it with --data")


def test_a_config_that_would_run_code_runs_nothing(tmp_path, capfd):
    marker = tmp_path / "ran"
    run, data = write_nerfstudio_run(tmp_path, "torch", config_extra=(
        f"hook: !!python/object/apply:os.system\n- touch {marker}\n"
        f"other: !!python/object/new:subprocess.Popen\n  args: [[touch, {marker}]]\n"))
    result = run_main(main, ["import-nerfstudio", run, "-o", tmp_path / "out", "--data", data], capfd)
    assert result.code in (0, None) and not marker.exists(), result.err


@pytest.mark.parametrize("case, message", [
    ("pickle", "refused: it holds Python objects"),
    ("truncated", "not a readable torch checkpoint"),
    ("not a dict", "not a nerfstudio checkpoint (no pipeline state dict)"),
    ("length", "field.mlp_base.model.params holds"),
    ("shape", "the config implies"),
    ("method", "a nerfacto-huge run; only nerfacto and instant-ngp runs can be imported"),
    ("splatfacto", "a splatfacto run; only nerfacto and instant-ngp runs can be imported"),
    ("old keys", "a nerfstudio 0.3 checkpoint"),
    ("oldest keys", "a nerfstudio 0.1–0.2 checkpoint"),
    ("folding lens", "its distortion folds over inside it"),
    ("linear proposals", "a proposal network with a linear head is not reproduced"),
    ("nan weight", "holds 1 NaN or infinite values; a scene with it cannot render"),
    ("inf weight", "NaN or infinite values; a scene with it cannot render"),
    ("huge scale", "with scale 1e+06, camera"),
    ("far scale", "beyond the far plane (1000): its renders would be empty"),
])
def test_hostile_and_unsupported_runs_are_refused_in_one_line(tmp_path, capfd, case, message):
    implementation = "torch" if case == "shape" else "tcnn"
    shapes = nerfstudio_layout(implementation)
    if case == "length":
        shapes["field.mlp_base.model.params"] = (shapes["field.mlp_base.model.params"][0] - 2,)
    if case == "shape":
        shapes["field.mlp_head.layers.0.weight"] = (64, 62)
    if case == "old keys":
        shapes = {"field.mlp_base_grid.tcnn_encoding.params": (8,), "field.mlp_base_mlp.tcnn_encoding.params": (8,)}
    if case == "oldest keys":
        shapes = {"field.mlp_base.params": (8,), "field.mlp_head.params": (8,)}
    extra = {"method": {"method": "nerfacto-huge", "model": "other.BigModel"},
             "splatfacto": {"method": "splatfacto", "model": "nerfstudio.models.splatfacto.SplatfactoModel"}}.get(case, {})
    run, data = write_nerfstudio_run(tmp_path, implementation, shapes=shapes, **extra)
    checkpoint = run / "nerfstudio_models" / "step-000000099.ckpt"
    if case == "pickle":
        torch.save({"pipeline": shutil.rmtree}, checkpoint)  # a global that is not a tensor: never resolved
    if case == "truncated":
        checkpoint.write_bytes(checkpoint.read_bytes()[:5000])
    if case == "not a dict":
        torch.save([1, 2, 3], checkpoint)
    if case == "folding lens":
        transforms = data / "transforms.json"
        transforms.write_text(transforms.read_text().replace('"k1": 0.0', '"k1": -5.0'))
    if case == "linear proposals":
        config = run / "config.yml"
        config.write_text(config.read_text().replace("use_linear: false", "use_linear: true", 1))
    if case in ("nan weight", "inf weight"):
        state = torch.load(checkpoint, weights_only=False)
        name = "_model.field.mlp_head.tcnn_encoding.params" if case == "nan weight" else "_model.field.mlp_base.model.params"
        state["pipeline"][name][0] = torch.nan if case == "nan weight" else torch.inf
        torch.save(state, checkpoint)
    if case in ("huge scale", "far scale"):  # cameras 3.2 from the centre before the scale (0.3 as written): 1265 at 400
        transforms = run / "dataparser_transforms.json"
        transforms.write_text(transforms.read_text().replace('"scale": 0.3', '"scale": 1e6' if case == "huge scale"
                                                             else '"scale": 400.0'))
    refused_import(tmp_path, capfd, run, data, message)


def test_each_set_of_outputs_runs_a_graph_pruned_to_it(imported):
    """onnxruntime runs every node whatever is fetched; a proposal density runs its own network alone, and
    equals the whole graph's output bit for bit."""
    import onnxruntime as ort
    from noisenerf.runtime.onnx_file import parse_model, pruned_model
    from noisenerf.runtime.session import read_model_file
    _, _, _, folder = imported
    file = read_model_file(folder / "model.onnx")
    pruned = parse_model(pruned_model(file, ("sigma_proposal0",)), "pruned")
    assert [port.name for port in pruned.outputs] == ["sigma_proposal0"]
    assert len(pruned.nodes) < len(file.nodes) / 2
    assert not any("density_linears" in name or "proposals.1" in name for node in pruned.nodes for name in node.inputs)
    rng = np.random.default_rng(1)
    points = rng.normal(size=(500, 3)).astype(np.float32)
    feed = {"points": points, "viewdirs": np.zeros_like(points), "noise": np.zeros((500, 32), np.float32)}
    whole = ort.InferenceSession(file.data, providers=["CPUExecutionProvider"]).run(["sigma_proposal0"], feed)[0]
    assert np.array_equal(load_model(folder / "model.onnx").field.proposal_density(0)(points), whole)


# ---- nerfstudio's own numbers (runs nerfstudio 1.1.5 trained: tests/goldens/nerfacto_{torch,opencv,fisheye}) ---


@pytest.fixture(scope="module", params=NERFSTUDIO_RUNS, ids=lambda goldens: goldens.name)
def nerfstudio_trained(request, tmp_path_factory):
    """Each goldens' run rebuilt as nerfstudio wrote it (its config.yml and dataparser_transforms.json as they
    are, the checkpoint's model tensors in a step-*.ckpt with numpy-scalar optimizer state), imported and
    exported; and nerfstudio's numbers: a pinhole capture, one with OpenCV distortion (k1 k2 p1 p2), a fisheye."""
    import json
    from safetensors.numpy import load_file
    goldens = request.param
    folder = tmp_path_factory.mktemp(goldens.name)
    run, data = nerfstudio_run_from_goldens(folder, goldens)
    assert main(["import-nerfstudio", str(run), "-o", str(folder / "scene"), "--data", str(data)]) in (0, None)
    assert main(["export", str(folder / "scene"), "-o", str(folder / "model.onnx")]) in (0, None)
    return load_model(folder / "model.onnx"), load_file(goldens / "golden.safetensors"), \
        json.loads((goldens / "golden.json").read_text()), folder


def test_field_outputs_are_nerfstudios(nerfstudio_trained):
    """Density, colour and proposal densities at points inside, around and far outside the unit cube."""
    model, golden, _, _ = nerfstudio_trained
    points, directions = golden["points"], golden["points_directions"]
    rgb, sigma = model.field(points, directions)
    assert np.abs(rgb - golden["points_rgb"]).max() < 1e-5
    assert np.allclose(sigma, golden["points_density"][:, 0], rtol=1e-4, atol=1e-12)
    for i in range(2):
        assert np.allclose(model.field.proposal_density(i)(points), golden[f"points_prop{i}_density"][:, 0],
                           rtol=1e-4, atol=1e-12)


def test_proposal_sampler_is_nerfstudios(nerfstudio_trained):
    """The field's bins on nerfstudio's own rays (float32 noise, amplified where a CDF is steep: measured
    5.9e-5 relative), the field at nerfstudio's own samples, and the composited colour (measured 3.8e-6 and
    2.9e-5 on two runs: the bins' noise moves the samples)."""
    from noisenerf.runtime.proposal import midpoints, proposal_edges, render_proposal_rays
    from noisenerf.runtime.rays import RayBatch
    model, golden, _, _ = nerfstudio_trained
    rays = RayBatch(golden["rays_origins"], golden["rays_directions"], golden["rays_directions"])
    starts, ends = golden["final_starts"].reshape(8, -1), golden["final_ends"].reshape(8, -1)
    sampler = model.sampler()
    edges = proposal_edges(rays, sampler)
    assert np.allclose(edges[:, :-1], starts, rtol=2e-4, atol=1e-6) and np.allclose(edges[:, 1:], ends, rtol=2e-4)
    theirs, _ = midpoints(rays, np.concatenate([starts, ends[:, -1:]], 1))
    _, sigma = model.field(theirs.reshape(-1, 3), np.repeat(golden["rays_directions"], starts.shape[1], 0))
    assert np.allclose(sigma.reshape(8, -1), golden["final_density"].reshape(8, -1), rtol=1e-4, atol=1e-9)
    colours, _ = render_proposal_rays(rays, model.field, sampler)
    assert np.abs(colours - golden["rays_rgb"]).max() < 1e-4


def golden_view(folder, info, split: str) -> int:
    """The scene camera of a goldens camera: its frame's place in file-name order (nerfstudio's)."""
    import json
    frames = sorted(json.loads((folder / "data" / "transforms.json").read_text())["frames"],
                    key=lambda frame: frame["file_path"])
    return [frame["file_path"] for frame in frames].index(info["cameras"][split]["file_path"])


def test_lens_rays_are_nerfstudios(nerfstudio_trained):
    """The rays nerfstudio's Cameras generate through the lens at the image's corners and centre: ours equal them
    within float32 (the pinhole run has none to check beyond its pinhole rays)."""
    from noisenerf.runtime.camera import pixel_rays
    model, golden, info, folder = nerfstudio_trained
    if "lens_directions" not in golden:
        assert "lens" not in info and model.cameras[0].lens is None
        return
    camera = model.cameras[golden_view(folder, info, "train")]
    assert camera.lens is not None and camera.lens.model == {1: "opencv", 2: "fisheye"}[int(golden["lens_camera_type"][0])]
    assert np.allclose(camera.lens.coefficients, golden["lens_distortion_params"][0], atol=1e-7)
    y, x = golden["lens_pixels_yx"].T
    origins, directions = pixel_rays(camera, x + 0.5, y + 0.5)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    assert np.abs(directions - golden["lens_directions"]).max() < 2e-6
    assert np.abs(directions - golden["lens_directions_pinhole"]).max() > 1e-3  # the lens did bend them
    assert np.allclose(origins, golden["lens_origins"], atol=1e-6)


@pytest.mark.parametrize("split", ["train", "eval", "train13"])
def test_ordinary_render_is_nerfstudios_eval_render(nerfstudio_trained, split):
    """`noisenerf-reveal MODEL --view I` against nerfstudio's get_outputs_for_camera of the same camera, I
    being the frame's place in file-name order: equal within float32 noise (the bins above)."""
    model, golden, info, folder = nerfstudio_trained
    from noisenerf.runtime.api import render
    if split not in info["cameras"]:
        assert folder.name.startswith("nerfacto_torch")  # the first run's goldens have two cameras
        return
    view = golden_view(folder, info, split)
    camera = model.cameras[view]
    assert np.allclose(camera.matrix()[:3], golden[f"{split}_camera_to_worlds"], atol=1e-5)
    assert np.allclose([camera.fx, camera.fy, camera.cx, camera.cy],
                       [golden[f"{split}_{k}"][0] for k in ("fx", "fy", "cx", "cy")], rtol=1e-6)
    image = render(folder / "model.onnx", view).image
    difference = np.abs(image - golden[f"{split}_render_rgb"])  # measured: at most 2.3e-4, 103 dB
    assert difference.max() < 1e-3 and difference.mean() < 1e-5


def test_photos_hidden_in_nerfstudios_run_reveal_exactly(nerfstudio_trained, shared_data, tmp_path, capfd):
    """Two photos (an ImageNet and a CelebA-HQ one, 40 px wide) at two of the run's cameras: exact through
    onnxruntime and the Python API."""
    _, _, _, folder = nerfstudio_trained
    photos = (shared_data / "secrets" / "imagenet" / "n01440764_tench.JPEG",
              shared_data / "secrets" / "celeba_hq" / "female_039913.jpg")
    assert_photos_hide_exactly(folder, photos, (7, 22), tmp_path, capfd)


def test_the_python_api_imports_as_the_command_line_does(tmp_path):
    import noisenerf
    run, data = write_nerfstudio_run(tmp_path, "torch", seed=3)
    report = noisenerf.import_nerfstudio(run, tmp_path / "scene", data=data)
    assert (report["implementation"], report["cameras"]) == ("torch", 7)
    with pytest.raises(noisenerf.UserError, match="not a nerfstudio run directory"):
        noisenerf.import_nerfstudio(tmp_path / "nothing", tmp_path / "other", data=data)
    assert not (tmp_path / "other").exists()
