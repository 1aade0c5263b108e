"""Write golden numbers for the nerfacto (torch implementation) importer, computed by nerfstudio itself.

NOT part of noisenerf and never run by CI.  Usage, with the venv described in
``tools/nerfstudio_train_tiny.py`` (nerfstudio 1.1.5, CPU torch)::

    /work/nsvenv/bin/python tools/nerfstudio_goldens.py RUN_DIR tests/goldens/nerfacto_torch
    /work/nsvenv/bin/python tools/nerfstudio_goldens.py RUN_DIR tests/goldens/nerfacto_opencv \
        --extra-train-cameras 13   # lens runs (tools/nerfstudio_train_tiny.py --camera-model ...)

RUN_DIR is a nerfstudio run directory (``.../nerfacto/<timestamp>`` holding
``config.yml``, ``dataparser_transforms.json`` and ``nerfstudio_models/``).
The run is loaded with nerfstudio's own ``eval_setup``; the only help it needs
under torch >= 2.6 is an allowlist for the numpy scalars in the checkpoint's
optimizer/scheduler state (``torch.load`` keeps ``weights_only=True``).  Every
number written comes out of nerfstudio's modules (cameras, collider, proposal
sampler, fields, renderers); nothing is recomputed here.

Writes into OUT_DIR:
  weights.safetensors  the checkpoint's ``pipeline`` tensors under ``_model.field.`` and
                       ``_model.proposal_networks.`` (exact keys, float32; original dtypes in the metadata)
  golden.safetensors   cameras, renders, per-ray proposal-sampler stages, field outputs at points
  golden.json          versions, commands, seeds, frames, downscale, shapes, notes

``--extra-train-cameras I,J`` also renders train cameras I, J (keys ``train{I}_*``,
golden.json ``cameras.train{I}``).  For a capture with a lens (nonzero distortion or
a fisheye camera type) it also writes ``lens_*`` tensors and golden.json ``lens``:
nerfstudio's rays for the corner pixels with the lens, without it
(``disable_distortion``) and of a pinhole camera with the same fx fy cx cy, the
train cameras' distortion params as nerfstudio's Cameras hold them
([k1, k2, k3, k4, p1, p2]), and the largest gap between nerfstudio's rays (every
pixel of train camera 0, as pinhole image coordinates) and OpenCV's undistortPoints
of the same pixel centres (the model the images were warped with).
  config.yml, dataparser_transforms.json, transforms.json   copies (no images)
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import nerfstudio_train_tiny  # noqa: E402  (installs the import-time stand-ins)

PIXELS_YX = [(32, 32), (20, 40), (45, 25), (10, 10), (60, 3), (28, 50), (38, 31), (0, 63)]
POINT_SEED = 1234
N_POINTS = 64
TRAIN_CAMERA_INDEX = 0  # index into nerfstudio's train dataset (sorted by file name)
EVAL_CAMERA_INDEX = 0  # index into nerfstudio's eval dataset


NOTES = [
    "Frames: nerfstudio's nerfstudio-data parser argsorts frames by image file name before the train/eval split "
    "(eval_mode 'fraction', train_split_fraction 0.9: i_train = linspace(0, n-1, ceil(0.9 n)).astype(int), "
    "eval = the rest); here the file order equals the sorted order.",
    "Cameras: c2w_ns = dataparser_transform (3x4) @ c2w_file (4x4), then the translation column times scale; "
    "OpenGL camera axes; rays through pixel centres (+0.5), y flipped, z = -1, rotated, normalised; origins = c2w_ns[:, 3].",
    "Collider at eval: near 0 (NearFarCollider reset_near_plane; training used 0.05), far 1000.",
    "Proposal sampler at eval: deterministic, anneal exponent 1.0 (the training anneal is not saved).",
    "Field at eval: appearance input = mean of the train appearance embeddings for every camera; "
    "the camera optimizer's pose_adjustment is ignored at eval.",
    "Direction input of the torch SH: (d + 1) / 2 fed to nerfstudio's SH polynomial as is (no remap to [-1, 1]).",
    "Points outside the open (0,1)^3 after contraction ((p+2)/4) are zeroed before the hash grid and get density 0.",
    "Compositing: sum w*rgb + (1 - sum w) * rgb_of_last_sample, then clamp to [0, 1] at eval; deltas are bin widths.",
    "weights.safetensors holds float32 copies; original dtypes (int64 for max_res/num_levels/log2_hashmap_size) are in "
    "its metadata 'original_dtypes' and in golden.json 'weights'.",
]


LENS_BUILT_BY = (
    "; then warped through the {model} lens: each pixel centre (index + 0.5) undistorted with OpenCV "
    "(cv2.undistortPoints / cv2.fisheye.undistortPoints, 100 iterations, eps 1e-12) takes the colour of the "
    "64-px pinhole image (same fl, cx, cy) there, cv2.remap bilinear, replicated border (edge pixels are white)"
)
LENS_NOTES = [
    "Lens: nerfstudio's Cameras hold distortion_params as [k1, k2, k3, k4, p1, p2] (camera_utils.get_distortion_params); "
    "OPENCV maps to CameraType.PERSPECTIVE (1), OPENCV_FISHEYE to CameraType.FISHEYE (2) (cameras.py "
    "CAMERA_MODEL_TO_TYPE).",
    "Lens rays (cameras.py _generate_rays_from_coords): ((x+0.5-cx)/fx, (y+0.5-cy)/fy) undistorted by "
    "camera_utils.radial_and_tangential_undistort (10 Newton steps from the distorted point, a step skipped where "
    "|det| <= 1e-3), d = 1 + k1 r + k2 r^2 + k3 r^3 + k4 r^4 with r = x^2 + y^2; then y negated (OpenGL). "
    "Perspective: direction (x, y, -1). Fisheye: theta = |(x, y)| clipped to [0, pi], direction "
    "(x sin(theta)/theta, y sin(theta)/theta, -cos(theta)); the same Newton solve on the fisheye's k1..k4 is "
    "OpenCV's theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8). Then rotated by c2w and "
    "normalised. Eval renders (get_outputs_for_camera) use these rays; see 'lens' for corner rays with and "
    "without the lens.",
]


def safe_globals():
    """The numpy names ``torch.load(weights_only=True)`` must allow (torch >= 2.6) in a nerfstudio
    checkpoint's optimizer/scheduler state."""
    import numpy as np

    names = []
    for modname in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            mod = __import__(modname, fromlist=["scalar"])
            names.append(mod.scalar)
        except Exception:  # pragma: no cover - depends on the numpy version
            pass
    names.append(np.dtype)
    names.append(type(np.dtype(np.float64)))  # numpy.dtypes.Float64DType
    return names


def load_run(run_dir: Path):
    """nerfstudio's own ``eval_setup`` of RUN_DIR/config.yml (test mode, model in eval mode) and the raw
    checkpoint (``torch.load`` with ``weights_only=True``, ``safe_globals()`` allowed).
    Returns config, pipeline, checkpoint path, step, raw checkpoint."""
    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    with torch.serialization.safe_globals(safe_globals()):
        config, pipeline, ckpt_path, step = eval_setup(run_dir / "config.yml", test_mode="test")
        raw = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    pipeline.model.eval()
    return config, pipeline, ckpt_path, step, raw


def save_checkpoint_tensors(raw: dict, prefixes: tuple[str, ...], path: Path, dtype=None):
    """The checkpoint's ``pipeline`` tensors whose keys start with one of ``prefixes`` (exact keys), cast to
    ``dtype`` if one is given, saved to ``path`` with their original dtypes in the metadata
    ``original_dtypes``.  Returns the tensors and the original dtypes."""
    from safetensors.torch import save_file

    weights, orig_dtypes = {}, {}
    for k, v in raw["pipeline"].items():
        if k.startswith(prefixes):
            orig_dtypes[k] = str(v.dtype).replace("torch.", "")
            v = v.detach() if dtype is None else v.detach().to(dtype)
            weights[k] = v.contiguous().clone()
    save_file(weights, str(path), metadata={"original_dtypes": json.dumps(orig_dtypes)})
    return weights, orig_dtypes


def copy_run_files(run_dir: Path, config, out_dir: Path) -> tuple[Path, Path]:
    """Copy the run's config.yml and dataparser_transforms.json and its dataset's transforms.json into
    ``out_dir``.  Returns the dataset path and its transforms.json."""
    shutil.copy(run_dir / "config.yml", out_dir / "config.yml")
    shutil.copy(run_dir / "dataparser_transforms.json", out_dir / "dataparser_transforms.json")
    data_path = Path(config.pipeline.datamanager.dataparser.data)
    tj = data_path if data_path.suffix == ".json" else data_path / "transforms.json"
    shutil.copy(tj, out_dir / "transforms.json")
    return data_path, tj


def seeded_points(gen):
    """``N_POINTS`` points and unit directions drawn from the torch generator ``gen`` (float32), and the
    layout text for golden.json: points near the object, inside the box, between the box and the
    contraction's edge, far away."""
    import torch

    n_in, n_mid = 24, 24
    n_far = N_POINTS - n_in - n_mid
    p_in = torch.rand(n_in, 3, generator=gen) * 2.0 - 1.0
    p_in[: n_in // 2] *= 0.3  # half of them near the object (lego spans ~±0.25 after the dataparser)
    v = torch.randn(n_mid, 3, generator=gen)
    v = v / v.abs().amax(dim=-1, keepdim=True)  # on the inf-norm unit sphere
    p_mid = v * (1.0 + 3.0 * torch.rand(n_mid, 1, generator=gen))  # inf-norm in [1, 4)
    u = torch.randn(n_far, 3, generator=gen)
    u = u / u.norm(dim=-1, keepdim=True)
    p_far = u * (10.0 ** (1.0 + 2.0 * torch.rand(n_far, 1, generator=gen)))  # |p| in [10, 1000)
    points = torch.cat([p_in, p_mid, p_far]).float()
    dirs = torch.randn(N_POINTS, 3, generator=gen)
    dirs = (dirs / dirs.norm(dim=-1, keepdim=True)).float()
    layout = (
        f"{n_in // 2} in [-0.3,0.3]^3, {n_in - n_in // 2} in [-1,1]^3, {n_mid} with inf-norm in [1,4), "
        f"{n_far} with |p| in [10,1000)"
    )
    return points, dirs, layout


def field_outputs_at(field, points, dirs):
    """nerfstudio's ``field.forward`` (no normals) at ``points`` seen along ``dirs``: zero-length ray samples,
    pixel area 1, camera index 0."""
    import torch
    from nerfstudio.cameras.rays import Frustums, RaySamples

    n = points.shape[0]
    rs = RaySamples(
        frustums=Frustums(
            origins=points,
            directions=dirs,
            starts=torch.zeros(n, 1),
            ends=torch.zeros(n, 1),
            pixel_area=torch.ones(n, 1),
        ),
        camera_indices=torch.zeros(n, 1, dtype=torch.long),
    )
    return field.forward(rs, compute_normals=False)


def field_stages(field, points, dirs, hash_after_mlp: bool = False) -> dict:
    """Intermediate values of a nerfacto field (``NerfactoField``, torch) at ``points``, from its own
    sub-modules: the contraction ((p + 2) / 4, zeroed outside the open (0,1)^3), the hash features
    (when the base MLP exposes its encoding), the base MLP's density before activation and geometric
    features, the SH direction encoding.  ``hash_after_mlp`` lists the hash features after the MLP's
    outputs (the order the ngp_torch golden has them in)."""
    from nerfstudio.fields.base_field import get_normalized_directions

    contracted = (field.spatial_distortion(points) + 2.0) / 4.0
    selector = ((contracted > 0.0) & (contracted < 1.0)).all(dim=-1)
    contracted = contracted * selector[..., None]
    out = {"points_contracted": contracted.float(), "points_selector": selector.long()}
    enc = field.mlp_base.model[0] if hasattr(field.mlp_base, "model") else None
    hash_features = {"points_field_hash_features": enc(contracted).float()} if enc is not None else {}
    h = field.mlp_base(contracted)
    mlp = {
        "points_field_density_before_activation": h[..., :1].float(),
        "points_field_geo_features": h[..., 1:].float(),
    }
    out.update({**mlp, **hash_features} if hash_after_mlp else {**hash_features, **mlp})
    out["points_field_sh"] = field.direction_encoding(get_normalized_directions(dirs)).float()
    return out


def save_golden_tensors(g: dict, out_dir: Path) -> dict:
    """Write ``g`` (float32 and int64 tensors only) as OUT_DIR/golden.safetensors; returns the saved copies."""
    import torch
    from safetensors.torch import save_file

    g = {k: v.detach().contiguous().clone() for k, v in g.items()}
    for k, v in g.items():
        assert v.dtype in (torch.float32, torch.int64), (k, v.dtype)
    save_file(g, str(out_dir / "golden.safetensors"))
    return g


def write_golden_json(info: dict, out_dir: Path) -> None:
    """Write OUT_DIR/golden.json and make every file in OUT_DIR mode 0644."""
    (out_dir / "golden.json").write_text(json.dumps(info, indent=1, default=str) + "\n")
    for f in out_dir.iterdir():
        f.chmod(0o644)


LENS_PIXELS_YX = [(0, 0), (0, 63), (63, 0), (63, 63), (32, 32)]


def _parse_args():
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--extra-train-cameras", default="", help="comma-separated train dataset indices to render too")
    return ap.parse_args()


def _has_lens(cameras) -> bool:
    from nerfstudio.cameras.cameras import CameraType

    dist = cameras.distortion_params
    lens = dist is not None and bool((dist != 0).any())
    return lens or bool((cameras.camera_type != CameraType.PERSPECTIVE.value).any())


def _lens_check(cameras, idx: int, transforms: dict):
    """nerfstudio's rays of a lens camera vs the same pixels without the lens, and vs OpenCV."""
    import cv2
    import numpy as np
    import torch
    from nerfstudio.cameras.cameras import Cameras, CameraType

    cam = cameras[idx : idx + 1]
    ys = torch.tensor([p[0] for p in LENS_PIXELS_YX])
    xs = torch.tensor([p[1] for p in LENS_PIXELS_YX])
    full = cam.generate_rays(camera_indices=0, keep_shape=True)
    no_lens = cam.generate_rays(camera_indices=0, keep_shape=True, disable_distortion=True)
    pinhole_cam = Cameras(
        camera_to_worlds=cam.camera_to_worlds,
        fx=cam.fx,
        fy=cam.fy,
        cx=cam.cx,
        cy=cam.cy,
        width=cam.width,
        height=cam.height,
        camera_type=CameraType.PERSPECTIVE,
    )
    pinhole = pinhole_cam.generate_rays(camera_indices=0, keep_shape=True)
    g = {
        "lens_pixels_yx": torch.tensor(LENS_PIXELS_YX, dtype=torch.int64),
        "lens_directions": full.directions[ys, xs].float(),
        "lens_directions_disable_distortion": no_lens.directions[ys, xs].float(),
        "lens_directions_pinhole": pinhole.directions[ys, xs].float(),
        "lens_origins": full.origins[ys, xs].float(),
        "lens_distortion_params": cameras.distortion_params.float(),
        "lens_camera_type": cameras.camera_type[..., 0].long(),
    }
    # every pixel: nerfstudio's ray in the camera frame (OpenGL) -> pinhole image coords (OpenCV, y down)
    R = cam.camera_to_worlds[0, :3, :3].double()
    d_cam = full.directions.double().reshape(-1, 3) @ R  # R^T d
    x_ns = d_cam[:, 0] / -d_cam[:, 2]
    y_ns = d_cam[:, 1] / d_cam[:, 2]
    h, w = int(cam.height[0]), int(cam.width[0])
    K = np.array([[float(cam.fx[0]), 0, float(cam.cx[0])], [0, float(cam.fy[0]), float(cam.cy[0])], [0, 0, 1.0]])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xx + 0.5, yy + 0.5], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if transforms.get("camera_model") == "OPENCV_FISHEYE":
        D = np.array([transforms.get(k, 0.0) for k in ("k1", "k2", "k3", "k4")])
        und = cv2.fisheye.undistortPoints(pts, K, D, criteria=crit).reshape(-1, 2)
        opencv_fn = "cv2.fisheye.undistortPoints"
    else:
        D = np.array([transforms.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")])
        und = cv2.undistortPoints(pts, K, D, criteria=crit).reshape(-1, 2)
        opencv_fn = "cv2.undistortPoints"
    gap = np.abs(np.stack([x_ns.numpy(), y_ns.numpy()], -1) - und)
    info = {
        "camera": f"train {idx}",
        "pixel_center_offset": 0.5,
        "camera_type": int(cam.camera_type[0].item()),
        "distortion_params_k1k2k3k4p1p2": cam.distortion_params[0].tolist(),
        "corners": [
            {
                "pixel_yx": list(p),
                "direction_ns": g["lens_directions"][i].tolist(),
                "direction_ns_disable_distortion": g["lens_directions_disable_distortion"][i].tolist(),
                "direction_pinhole_same_intrinsics": g["lens_directions_pinhole"][i].tolist(),
                "angle_to_pinhole_deg": float(
                    torch.rad2deg(
                        torch.arccos(
                            (g["lens_directions"][i].double() * g["lens_directions_pinhole"][i].double())
                            .sum()
                            .clamp(-1, 1)
                        )
                    )
                ),
            }
            for i, p in enumerate(LENS_PIXELS_YX)
        ],
        "rays_vs_opencv": {
            "opencv": opencv_fn + " (100 iterations, eps 1e-12), the model the images were warped with",
            "max_abs_normalized": float(gap.max()),
            "max_abs_px": float((gap * np.array([K[0, 0], K[1, 1]])).max()),
        },
    }
    return g, info


def main() -> None:
    import numpy as np
    import torch

    args = _parse_args()
    run_dir = args.run_dir.resolve()
    out_dir = args.out_dir.resolve()
    extra_train = [int(i) for i in args.extra_train_cameras.split(",") if i.strip()]
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(nerfstudio_train_tiny.NUM_THREADS)

    import nerfstudio
    from nerfstudio.field_components.field_heads import FieldHeadNames

    config, pipeline, ckpt_path, step, raw = load_run(run_dir)
    model = pipeline.model
    dm = pipeline.datamanager
    mcfg = config.pipeline.model

    # ---- 1. weights ---------------------------------------------------------------------------
    weights, orig_dtypes = save_checkpoint_tensors(
        raw, ("_model.field.", "_model.proposal_networks."), out_dir / "weights.safetensors", dtype=torch.float32
    )

    # ---- 2. copies ------------------------------------------------------------------------------
    data_path, tj = copy_run_files(run_dir, config, out_dir)

    # ---- 3. goldens -----------------------------------------------------------------------------
    g: dict[str, torch.Tensor] = {}
    train_files = [str(p) for p in dm.train_dataparser_outputs.image_filenames]
    eval_files = [str(p) for p in dm.eval_dataparser_outputs.image_filenames]
    cams = {
        "train": (dm.train_dataset.cameras, TRAIN_CAMERA_INDEX, dm.train_dataset, train_files),
        "eval": (dm.eval_dataset.cameras, EVAL_CAMERA_INDEX, dm.eval_dataset, eval_files),
    }
    for i in extra_train:
        cams[f"train{i}"] = (dm.train_dataset.cameras, i, dm.train_dataset, train_files)
    cam_info = {}
    for name, (cameras, idx, dataset, files) in cams.items():
        cam = cameras[idx : idx + 1].to(model.device)
        g[f"{name}_camera_to_worlds"] = cam.camera_to_worlds[0].float()
        for attr in ("fx", "fy", "cx", "cy"):
            g[f"{name}_{attr}"] = getattr(cam, attr)[0].float()
        g[f"{name}_width"] = cam.width[0].long()
        g[f"{name}_height"] = cam.height[0].long()
        with torch.no_grad():
            outputs = model.get_outputs_for_camera(cam)
        rgb = outputs["rgb"].float()
        g[f"{name}_render_rgb"] = rgb
        g[f"{name}_render_accumulation"] = outputs["accumulation"].float()
        g[f"{name}_render_depth"] = outputs["depth"].float()
        gt = dataset.get_image_float32(idx)[..., :3].float()
        mse = torch.mean((rgb - gt) ** 2).item()
        cam_info[name] = {
            "dataset_index": idx,
            "file_path": Path(files[idx]).relative_to(data_path).as_posix(),
            "camera_type": int(cam.camera_type[0].item()),
            "distortion_params": cam.distortion_params[0].tolist() if cam.distortion_params is not None else None,
            "render_mean_rgb": rgb.mean(dim=(0, 1)).tolist(),
            "gt_mean_rgb": gt.mean(dim=(0, 1)).tolist(),
            "psnr_vs_gt_db": -10.0 * float(np.log10(mse)),
        }

    # ---- per-ray stages for 8 pixels of the train camera ---------------------------------------
    cameras, idx, _, _ = cams["train"]
    cam = cameras[idx : idx + 1].to(model.device)
    bundle_full = cam.generate_rays(camera_indices=0, keep_shape=True)
    ys = torch.tensor([p[0] for p in PIXELS_YX])
    xs = torch.tensor([p[1] for p in PIXELS_YX])
    bundle = bundle_full[ys, xs]  # (8,) RayBundle
    g["rays_pixel_yx"] = torch.tensor(PIXELS_YX, dtype=torch.int64)
    g["rays_origins"] = bundle.origins.float()
    g["rays_directions"] = bundle.directions.float()
    g["rays_camera_indices"] = bundle.camera_indices.long()
    with torch.no_grad():
        bundle = model.collider(bundle)
        g["rays_nears"] = bundle.nears.float()
        g["rays_fars"] = bundle.fars.float()
        ray_samples, weights_list, ray_samples_list = model.proposal_sampler(bundle, density_fns=model.density_fns)
        for s, rs in enumerate(ray_samples_list):
            g[f"stage{s}_starts"] = rs.frustums.starts[..., 0].float()
            g[f"stage{s}_ends"] = rs.frustums.ends[..., 0].float()
            g[f"stage{s}_spacing_starts"] = rs.spacing_starts[..., 0].float()
            g[f"stage{s}_spacing_ends"] = rs.spacing_ends[..., 0].float()
            g[f"stage{s}_prop{s}_density"] = model.density_fns[s](rs.frustums.get_positions())[..., 0].float()
            g[f"stage{s}_weights"] = weights_list[s][..., 0].float()
        g["final_starts"] = ray_samples.frustums.starts[..., 0].float()
        g["final_ends"] = ray_samples.frustums.ends[..., 0].float()
        g["final_spacing_starts"] = ray_samples.spacing_starts[..., 0].float()
        g["final_spacing_ends"] = ray_samples.spacing_ends[..., 0].float()
        fo = model.field.forward(ray_samples, compute_normals=False)
        w = ray_samples.get_weights(fo[FieldHeadNames.DENSITY])
        g["final_density"] = fo[FieldHeadNames.DENSITY][..., 0].float()
        g["final_rgb"] = fo[FieldHeadNames.RGB].float()
        g["final_weights"] = w[..., 0].float()
        g["rays_rgb"] = model.renderer_rgb(rgb=fo[FieldHeadNames.RGB], weights=w).float()
        g["rays_accumulation"] = model.renderer_accumulation(weights=w).float()
        g["rays_depth"] = model.renderer_depth(weights=w, ray_samples=ray_samples).float()
        # the same rays through nerfstudio's full forward (collider + get_outputs)
        fwd = model.forward(ray_bundle=bundle_full[ys, xs])
    rays_vs_forward = float((fwd["rgb"] - g["rays_rgb"]).abs().max())
    rays_vs_render = float((g["train_render_rgb"][ys, xs] - g["rays_rgb"]).abs().max())

    # ---- lens: nerfstudio's rays with and without the distortion --------------------------------
    lens_info = None
    transforms = json.loads(tj.read_text())
    if _has_lens(dm.train_dataset.cameras):
        with torch.no_grad():
            lg, lens_info = _lens_check(dm.train_dataset.cameras, TRAIN_CAMERA_INDEX, transforms)
        g.update(lg)

    # ---- field outputs at random points ---------------------------------------------------------
    gen = torch.Generator().manual_seed(POINT_SEED)
    points, dirs, layout = seeded_points(gen)
    g["points"] = points
    g["points_directions"] = dirs
    with torch.no_grad():
        fo = field_outputs_at(model.field, points, dirs)
        g["points_density"] = fo[FieldHeadNames.DENSITY].float()
        g["points_rgb"] = fo[FieldHeadNames.RGB].float()
        for i, fn in enumerate(model.density_fns):
            g[f"points_prop{i}_density"] = fn(points).float()
        # intermediate values of the nerfacto field, from its own sub-modules
        field = model.field
        g.update(field_stages(field, points, dirs))
        g["field_mean_appearance_embedding"] = field.embedding_appearance.mean(dim=0).float()

    g = save_golden_tensors(g, out_dir)

    # ---- golden.json -----------------------------------------------------------------------------
    import nerfacc
    import torchmetrics

    dp = dm.dataparser
    train_log = run_dir.parents[2] / "ns_train_command.txt"  # written by nerfstudio_train_tiny.py
    info = {
        "generator": "tools/nerfstudio_goldens.py (calls nerfstudio; no nerfstudio code copied)",
        "versions": {
            "nerfstudio": nerfstudio.__version__ if hasattr(nerfstudio, "__version__") else _dist_version("nerfstudio"),
            "torch": torch.__version__,
            "numpy": np.__version__,
            "nerfacc": getattr(nerfacc, "__version__", _dist_version("nerfacc")),
            "torchmetrics": torchmetrics.__version__,
            "python": sys.version.split()[0],
        },
        "commands": {
            "train": train_log.read_text().strip() if train_log.exists() else None,
            "goldens": " ".join(["python", "tools/nerfstudio_goldens.py", *sys.argv[1:]]),
        },
        "run_dir": str(run_dir),
        "checkpoint": ckpt_path.name,
        "checkpoint_step": int(step),
        "seeds": {
            "machine_seed": int(config.machine.seed),
            "data_worker_seed": nerfstudio_train_tiny.WORKER_SEED,
            "points_seed": POINT_SEED,
            "torch_threads_goldens": nerfstudio_train_tiny.NUM_THREADS,
            "torch_threads_training": "see commands.train (NS_TINY_THREADS, default 1)",
        },
        "dataparser": {
            "downscale_factor": int(dp.downscale_factor),
            "dataparser_scale": float(dm.train_dataparser_outputs.dataparser_scale),
            "dataparser_transform": dm.train_dataparser_outputs.dataparser_transform.tolist(),
            "scene_box_aabb": dm.train_dataparser_outputs.scene_box.aabb.tolist(),
            "train_file_paths": [Path(f).relative_to(data_path).as_posix() for f in train_files],
            "eval_file_paths": [Path(f).relative_to(data_path).as_posix() for f in eval_files],
        },
        "model": {
            "implementation": mcfg.implementation,
            "log2_hashmap_size": mcfg.log2_hashmap_size,
            "num_levels": mcfg.num_levels,
            "base_res": mcfg.base_res,
            "max_res": mcfg.max_res,
            "features_per_level": mcfg.features_per_level,
            "hidden_dim": mcfg.hidden_dim,
            "hidden_dim_color": mcfg.hidden_dim_color,
            "appearance_embed_dim": mcfg.appearance_embed_dim,
            "use_average_appearance_embedding": mcfg.use_average_appearance_embedding,
            "average_init_density": mcfg.average_init_density,
            "proposal_net_args_list": mcfg.proposal_net_args_list,
            "num_proposal_samples_per_ray": list(mcfg.num_proposal_samples_per_ray),
            "num_nerf_samples_per_ray": mcfg.num_nerf_samples_per_ray,
            "proposal_initial_sampler": mcfg.proposal_initial_sampler,
            "background_color": mcfg.background_color,
            "near_plane_train": mcfg.near_plane,
            "far_plane": mcfg.far_plane,
            "collider_near_at_eval": float(g["rays_nears"].flatten()[0]),
            "proposal_sampler_anneal_at_eval": float(model.proposal_sampler._anneal),
            "camera_optimizer_mode": mcfg.camera_optimizer.mode,
        },
        "dataset": {
            "transforms_json": "transforms.json (copy; images not kept)",
            "frames_in_file_order": [
                {"file_path": f["file_path"], "source": f.get("source_file_path")}
                for f in json.loads(tj.read_text())["frames"]
            ],
            "built_by": "tools/nerfstudio_train_tiny.py build_dataset: NeRF-Synthetic lego train split, "
            "frames i*100//30, RGBA composited on white at 800 px, PIL BOX-downscaled to 64 px, RGB PNG"
            + (LENS_BUILT_BY.format(model=transforms.get("camera_model")) if lens_info else ""),
        },
        "notes": NOTES + (LENS_NOTES if lens_info else []),
        "cameras": cam_info,
        "rays": {
            "camera": "train",
            "pixels_yx": PIXELS_YX,
            "pixel_center_offset": 0.5,
            "max_abs_diff_vs_model_forward": rays_vs_forward,
            "max_abs_diff_vs_full_render": rays_vs_render,
        },
        "points": {
            "layout": layout,
            "appearance": "eval mode: mean of the train appearance embeddings",
        },
        **({"lens": lens_info} if lens_info else {}),
        "tensors": {k: {"shape": list(v.shape), "dtype": str(v.dtype).replace("torch.", "")} for k, v in g.items()},
        "weights": {k: {"shape": list(v.shape), "original_dtype": orig_dtypes[k]} for k, v in weights.items()},
    }
    write_golden_json(info, out_dir)
    print(json.dumps({"cameras": cam_info, "rays": info["rays"], "lens": lens_info}, indent=1))


def _dist_version(name: str) -> str:
    from importlib.metadata import version

    return version(name)


if __name__ == "__main__":
    main()
