"""Train a tiny nerfacto run with nerfstudio itself (CPU, torch implementation).

NOT part of noisenerf and never run by CI.  It produces the real nerfstudio run
directory from which ``tools/nerfstudio_goldens.py`` writes the golden files in
``tests/goldens/nerfacto_torch/``.  Run it with a separate venv that holds
nerfstudio 1.1.5 (see the golden's ``golden.json`` for the exact versions)::

    python3.11 -m venv /work/nsvenv
    /work/nsvenv/bin/pip install torch==2.13.0            # the CPU build
    /work/nsvenv/bin/pip install --no-deps nerfstudio==1.1.5 nerfacc==0.5.2 viser==0.2.7 \
        pytorch_msssim tensorly splines
    BUILD_NO_CUDA=1 /work/nsvenv/bin/pip install --no-deps --no-build-isolation gsplat==1.4.0
    /work/nsvenv/bin/pip install numpy jaxtyping rich PyYAML tyro pillow imageio appdirs \
        requests pyquaternion pathos torchmetrics tensorboard opencv-python-headless \
        matplotlib safetensors websockets msgspec scikit-image scipy tqdm trimesh \
        nodeenv psutil yourdfpy plyfile rawpy
    /work/nsvenv/bin/python tools/nerfstudio_train_tiny.py \
        --scene /work/shared/data/scenes/blender/lego --data /work/nsrun/data \
        --outputs /work/nsrun/outputs  # 1000 iterations x 256 rays, ~7.5 min on 1 thread

(The viewer, splatfacto and process_data modules are imported by the trainer at
module level: viser, gsplat (python only), pytorch_msssim, tensorly, splines and
rawpy are only there to satisfy those imports.)

Step 1 writes a nerfstudio-data dataset (``transforms.json`` as ns-process-data
writes it, OPENCV camera model with zero distortion, RGB PNGs composited on
white, downscaled).  With ``--camera-model`` / ``--k1 ..`` it writes a distorted
capture instead, top-level keys exactly as ns-process-data's
``parse_colmap_camera_params`` writes them (OPENCV: w h fl_x fl_y cx cy k1 k2 p1 p2;
OPENCV_FISHEYE: w h fl_x fl_y cx cy k1 k2 k3 k4; then camera_model), and its images
really distorted: each pixel centre (index + 0.5, nerfstudio's convention) is
undistorted with ``cv2.undistortPoints`` / ``cv2.fisheye.undistortPoints`` (100
iterations, eps 1e-12) and takes the colour the undistorted pinhole image (the
64-px image the default writes, same fl/cx/cy) has there (``cv2.remap``, bilinear,
replicated border: points outside the pinhole frame, a pixel or a few at the
corners, take the nearest edge colour, white for lego)::

    /work/nsvenv/bin/python tools/nerfstudio_train_tiny.py --data /work/nsrun2/data_opencv \
        --outputs /work/nsrun2/outputs --experiment lego64_opencv \
        --camera-model OPENCV --k1 -0.12 --k2 0.03 --p1 0.001 --p2 -0.0015
    /work/nsvenv/bin/python tools/nerfstudio_train_tiny.py --data /work/nsrun2/data_fisheye \
        --outputs /work/nsrun2/outputs --experiment lego64_fisheye \
        --camera-model OPENCV_FISHEYE --k1 0.05 --k2 -0.01 --k3 0.002 --k4 -0.0005

(Use one ``--outputs`` per experiment if the goldens tool should read each run's
``ns_train_command.txt``, which is written into ``--outputs`` itself.)

Step 2 runs nerfstudio's own ``ns-train`` entry point
(``nerfstudio.scripts.train.entrypoint``) as
``ns-train nerfacto --machine.device-type cpu --pipeline.model.implementation torch ...
nerfstudio-data --data DIR``.

No nerfstudio code is copied here.  Three import-time stand-ins are installed
because nerfstudio imports these at module level although a CPU nerfacto run
never needs them (research/nerfacto-import.md §7.7.1):

* ``torchvision``: an empty module (only used for image dumps; the real wheel
  would pull a CUDA torch);
* ``nerfstudio.configs.method_configs``: a table holding only nerfstudio 1.1.5's
  ``nerfacto`` entry, rebuilt from nerfstudio's own config classes with the same
  values (the real table imports every method, gsplat's CUDA build among them);
* torchmetrics' LPIPS backbone: AlexNet ``features`` with random weights instead
  of the ImageNet download (LPIPS only scores eval images; the checkpoint
  carries the same ``_model.lpips.*`` keys and shapes as a real run).

Plus, for bit-reproducible runs: one torch thread, and the train-ray worker
process (``ParallelDataManager``'s ``DataProcessor``, started with "spawn" and
left unseeded by nerfstudio) is seeded with ``machine.seed`` before it samples.
"""

from __future__ import annotations

import argparse
import importlib.machinery
import json
import math
import os
import sys
import types
from pathlib import Path

NUM_THREADS = int(os.environ.get("NS_TINY_THREADS", "1"))
WORKER_SEED = int(os.environ.get("NS_TINY_WORKER_SEED", "42"))


def _stub_module(name: str) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__spec__ = importlib.machinery.ModuleSpec(name, None)
    sys.modules[name] = mod
    return mod


def _alexnet_features_random():
    """torchvision's alexnet().features layout, random weights (no download)."""
    from torch import nn

    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


def adam_exponential(lr: float, lr_final: float, max_steps: int) -> dict:
    """One ``optimizers`` entry of nerfstudio 1.1.5's method configs: Adam (eps 1e-15), exponential decay."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    return {
        "optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=max_steps),
    }


def method_config(method_name: str, pipeline_cls, datamanager_cls, model, optimizers: dict, viewer_rays: int):
    """The ``TrainerConfig`` that nerfstudio 1.1.5's configs/method_configs.py writes for ``nerfacto`` and
    ``instant-ngp`` (the values the two share fixed; the pipeline and datamanager classes, the model
    config, the optimizers and the viewer's rays per chunk given), built from nerfstudio's own classes."""
    from nerfstudio.configs.base_config import ViewerConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    from nerfstudio.engine.trainer import TrainerConfig

    return TrainerConfig(
        method_name=method_name,
        steps_per_eval_batch=500,
        steps_per_save=2000,
        max_num_iterations=30000,
        mixed_precision=True,
        pipeline=pipeline_cls(
            datamanager=datamanager_cls(
                dataparser=NerfstudioDataParserConfig(),
                train_num_rays_per_batch=4096,
                eval_num_rays_per_batch=4096,
            ),
            model=model,
        ),
        optimizers=optimizers,
        viewer=ViewerConfig(num_rays_per_chunk=viewer_rays),
        vis="viewer",
    )


def method_union(methods: dict, descriptions: dict):
    """``AnnotatedBaseConfigUnion`` of a method table, as nerfstudio's configs/method_configs.py builds it."""
    import tyro

    return tyro.conf.SuppressFixed[
        tyro.conf.FlagConversionOff[
            tyro.extras.subcommand_type_from_defaults(defaults=methods, descriptions=descriptions)
        ]
    ]


def _nerfacto_method_configs():
    """nerfstudio 1.1.5's ``method_configs["nerfacto"]`` (configs/method_configs.py),
    built from nerfstudio's own classes with the same values."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManagerConfig
    from nerfstudio.models.nerfacto import NerfactoModelConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    nerfacto = method_config(
        "nerfacto",
        VanillaPipelineConfig,
        ParallelDataManagerConfig,
        NerfactoModelConfig(
            eval_num_rays_per_chunk=1 << 15,
            average_init_density=0.01,
            camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"),
        ),
        {
            "proposal_networks": adam_exponential(1e-2, 0.0001, 200000),
            "fields": adam_exponential(1e-2, 0.0001, 200000),
            "camera_opt": adam_exponential(1e-3, 1e-4, 5000),
        },
        1 << 15,
    )
    return {"nerfacto": nerfacto}, {
        "nerfacto": "Recommended real-time model tuned for real captures. This model will be continually updated."
    }


_INSTALLED = False


def install_standins() -> None:
    """Install the import-time stand-ins (idempotent).  Runs at import of this
    module, so the spawned data worker (which re-imports ``__main__``) gets them too."""
    global _INSTALLED
    if _INSTALLED:
        return
    _INSTALLED = True
    import torch

    torch.set_num_threads(NUM_THREADS)

    # torchmetrics decides "torchvision available?" lazily; settle it (False) before the stub exists.
    import torchmetrics.utilities.imports as tm_imports

    bool(tm_imports._TORCHVISION_AVAILABLE)

    if "torchvision" not in sys.modules:
        tv = _stub_module("torchvision")
        tv_utils = _stub_module("torchvision.utils")
        tv.utils = tv_utils

        def _no_image_dumps(*_a, **_k):
            raise RuntimeError("torchvision stand-in: image dumps are not available")

        tv_utils.save_image = _no_image_dumps
        tv_utils.make_grid = _no_image_dumps

    import torchmetrics.functional.image.lpips as tm_lpips_f
    import torchmetrics.image.lpip as tm_lpips

    tm_lpips_f._TORCHVISION_AVAILABLE = True
    tm_lpips._TORCHVISION_AVAILABLE = True

    def _get_tv_model_features(net: str, pretrained: bool = False):
        if net != "alexnet":
            raise RuntimeError(f"LPIPS stand-in only provides alexnet, not {net}")
        return _alexnet_features_random()

    tm_lpips_f._get_tv_model_features = _get_tv_model_features

    # method_configs stand-in: only nerfacto.
    if "nerfstudio.configs.method_configs" not in sys.modules:
        mc = _stub_module("nerfstudio.configs.method_configs")
        methods, descriptions = _nerfacto_method_configs()
        mc.method_configs = methods
        mc.descriptions = descriptions
        mc.all_methods = methods
        mc.all_descriptions = descriptions
        mc.AnnotatedBaseConfigUnion = method_union(methods, descriptions)
        import nerfstudio.configs as ns_configs

        ns_configs.method_configs = mc

    # Seed the spawned train-ray worker (nerfstudio leaves it unseeded).
    from nerfstudio.data.datamanagers import parallel_datamanager as pdm

    if not getattr(pdm.DataProcessor.run, "_ns_tiny_seeded", False):
        _orig_run = pdm.DataProcessor.run

        def run(self):
            import random

            import numpy as np

            torch.set_num_threads(NUM_THREADS)
            random.seed(WORKER_SEED)
            np.random.seed(WORKER_SEED)
            torch.manual_seed(WORKER_SEED)
            return _orig_run(self)

        run._ns_tiny_seeded = True
        pdm.DataProcessor.run = run


# ---------------------------------------------------------------------------------------------
# dataset


def lens_params(camera_model: str, coeffs: dict[str, float]) -> dict[str, float]:
    """The distortion keys ns-process-data writes for ``camera_model``, in its order
    (nerfstudio/process_data/colmap_utils.py ``parse_colmap_camera_params``)."""
    if camera_model == "OPENCV":
        keys, zero = ("k1", "k2", "p1", "p2"), ("k3", "k4")
    elif camera_model == "OPENCV_FISHEYE":
        keys, zero = ("k1", "k2", "k3", "k4"), ("p1", "p2")
    else:
        raise ValueError(f"camera model {camera_model!r}: only OPENCV and OPENCV_FISHEYE")
    bad = [k for k in zero if coeffs.get(k, 0.0) != 0.0]
    if bad:
        raise ValueError(f"{camera_model} has no {', '.join(bad)}")
    return {k: float(coeffs.get(k, 0.0)) for k in keys}


def distort_image(pinhole, fl: float, c: float, camera_model: str, lens: dict[str, float]):
    """The pinhole image (H, W, 3 uint8; focal fl, centre c, both axes) seen through the lens:
    each output pixel centre (index + 0.5) is undistorted with OpenCV and takes the pinhole
    image's colour at the undistorted point (bilinear). -> (image, info)"""
    import cv2
    import numpy as np

    h, w = pinhole.shape[:2]
    K = np.array([[fl, 0.0, c], [0.0, fl, c], [0.0, 0.0, 1.0]])
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs + 0.5, ys + 0.5], axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if camera_model == "OPENCV":
        d = np.array([lens["k1"], lens["k2"], lens["p1"], lens["p2"]])
        und = cv2.undistortPoints(pts, K, d, criteria=crit).reshape(-1, 2)
        # forward check with OpenCV's own projection
        obj = np.concatenate([und, np.ones((und.shape[0], 1))], axis=1).reshape(-1, 1, 3)
        back = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
    else:
        d = np.array([lens["k1"], lens["k2"], lens["k3"], lens["k4"]])
        und = cv2.fisheye.undistortPoints(pts, K, d, criteria=crit).reshape(-1, 2)
        obj = np.concatenate([und, np.ones((und.shape[0], 1))], axis=1).reshape(-1, 1, 3)
        back = cv2.fisheye.projectPoints(obj, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
    map_x = (fl * und[:, 0] + c - 0.5).reshape(h, w).astype(np.float32)
    map_y = (fl * und[:, 1] + c - 0.5).reshape(h, w).astype(np.float32)
    img = cv2.remap(pinhole, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    outside = (map_x < -0.5) | (map_x > w - 0.5) | (map_y < -0.5) | (map_y > h - 0.5)
    info = {
        "reprojection_max_abs_px": float(np.abs(back - pts.reshape(-1, 2)).max()),
        "pixels_outside_pinhole_frame": int(outside.sum()),
        "undistorted_px_range": [float(map_x.min()) + 0.5, float(map_x.max()) + 0.5],
    }
    return img, info


def build_dataset(
    scene: Path,
    out: Path,
    n_frames: int,
    size: int,
    camera_model: str = "OPENCV",
    coeffs: dict[str, float] | None = None,
) -> dict:
    """lego train split (NeRF-Synthetic, RGBA, OpenGL c2w) -> nerfstudio-data dataset.
    With a lens (``camera_model`` OPENCV_FISHEYE, or nonzero ``coeffs``) the images are the
    pinhole ones warped through it (``distort_image``)."""
    import numpy as np
    from PIL import Image

    lens = lens_params(camera_model, coeffs or {})
    warp = camera_model != "OPENCV" or any(v != 0.0 for v in lens.values())
    warp_infos = []

    meta = json.loads((scene / "transforms_train.json").read_text())
    frames_in = meta["frames"]
    picks = [i * len(frames_in) // n_frames for i in range(n_frames)]
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    focal = 0.5 * size / math.tan(0.5 * float(meta["camera_angle_x"]))
    frames = []
    for k, i in enumerate(picks):
        src = frames_in[i]
        rel = src["file_path"]
        path = scene / (rel if rel.endswith(".png") else rel + ".png")
        rgba = np.asarray(Image.open(path).convert("RGBA"), dtype=np.float64) / 255.0
        rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])  # composite on white
        full = Image.fromarray(np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8), "RGB")
        small = full.resize((size, size), Image.Resampling.BOX)
        if warp:
            arr, info = distort_image(np.asarray(small), focal, size / 2.0, camera_model, lens)
            small = Image.fromarray(arr, "RGB")
            warp_infos.append(info)
        name = f"frame_{k + 1:05d}.png"
        small.save(out / "images" / name)
        frames.append(
            {
                "file_path": f"images/{name}",
                "transform_matrix": src["transform_matrix"],
                "colmap_im_id": k + 1,
                "source_file_path": rel,
            }
        )
    transforms = {
        "w": size,
        "h": size,
        "fl_x": focal,
        "fl_y": focal,
        "cx": size / 2.0,
        "cy": size / 2.0,
        **lens,
        "camera_model": camera_model,
        "frames": frames,
    }
    (out / "transforms.json").write_text(json.dumps(transforms, indent=4))
    if warp:
        print(
            "lens warp:",
            json.dumps(
                {
                    "camera_model": camera_model,
                    **lens,
                    "reprojection_max_abs_px": max(i["reprojection_max_abs_px"] for i in warp_infos),
                    "pixels_outside_pinhole_frame_per_image": warp_infos[0]["pixels_outside_pinhole_frame"],
                    "undistorted_px_range": warp_infos[0]["undistorted_px_range"],
                }
            ),
            flush=True,
        )
    return transforms


install_standins()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=Path("/work/shared/data/scenes/blender/lego"))
    ap.add_argument("--data", type=Path, default=Path("/work/nsrun/data"))
    ap.add_argument("--outputs", type=Path, default=Path("/work/nsrun/outputs"))
    ap.add_argument("--experiment", default="lego64")
    ap.add_argument("--timestamp", default=None, help="default: nerfstudio's own {yyyy-mm-dd_hhmmss}")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--iters", type=int, default=1000)
    ap.add_argument("--rays", type=int, default=256)
    ap.add_argument("--log2-hashmap-size", type=int, default=12)
    ap.add_argument("--prop-log2-hashmap-size", type=int, default=12)
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--camera-model", default="OPENCV", choices=["OPENCV", "OPENCV_FISHEYE"])
    for k in ("k1", "k2", "k3", "k4", "p1", "p2"):
        ap.add_argument(f"--{k}", type=float, default=0.0, help="lens coefficient (default 0)")
    ap.add_argument("--skip-data", action="store_true")
    ap.add_argument("--dry-run", action="store_true", help="print the ns-train command only")
    args = ap.parse_args()

    if not args.skip_data:
        coeffs = {k: getattr(args, k) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
        build_dataset(args.scene, args.data, args.frames, args.size, args.camera_model, coeffs)

    ns_args = [
        "ns-train",
        "nerfacto",
        "--machine.device-type", "cpu",
        "--machine.seed", str(args.seed),
        "--pipeline.model.implementation", "torch",
        "--pipeline.model.log2-hashmap-size", str(args.log2_hashmap_size),
        "--pipeline.model.proposal-net-args-list.0.log2-hashmap-size", str(args.prop_log2_hashmap_size),
        "--pipeline.model.proposal-net-args-list.1.log2-hashmap-size", str(args.prop_log2_hashmap_size),
        "--pipeline.datamanager.train-num-rays-per-batch", str(args.rays),
        "--max-num-iterations", str(args.iters),
        "--steps-per-save", str(args.iters),
        "--steps-per-eval-batch", str(10 * args.iters),
        "--steps-per-eval-image", str(10 * args.iters),
        "--steps-per-eval-all-images", str(10 * args.iters),
        "--vis", "tensorboard",
        "--output-dir", str(args.outputs),
        "--experiment-name", args.experiment,
    ]
    if args.timestamp:
        ns_args += ["--timestamp", args.timestamp]
    ns_args += ["nerfstudio-data", "--data", str(args.data)]
    print("RUN:", " ".join(ns_args), flush=True)
    if args.dry_run:
        return
    args.outputs.mkdir(parents=True, exist_ok=True)
    # read by tools/nerfstudio_goldens.py for golden.json (kept outside nerfstudio's run directory)
    (args.outputs / "ns_train_command.txt").write_text(
        "python tools/nerfstudio_train_tiny.py " + " ".join(sys.argv[1:]) + "\n" + " ".join(ns_args) + "\n"
    )
    sys.argv = ns_args
    from nerfstudio.scripts.train import entrypoint

    entrypoint()


if __name__ == "__main__":
    main()
