"""Write golden numbers for nerfstudio's ``instant-ngp`` method (NGPModel), computed by nerfstudio itself on CPU.

NOT part of noisenerf and never run by CI.  Usage, with the venv described in
``tools/nerfstudio_train_tiny.py`` (nerfstudio 1.1.5, nerfacc 0.5.2, CPU torch)::

    /work/nsvenv/bin/python tools/nerfstudio_ngp_goldens.py \\
        --data /work/nsrun2/data_default --outputs /work/nsrun2/outputs tests/goldens/ngp_torch

``--data`` is a nerfstudio-data dataset as ``tools/nerfstudio_train_tiny.py`` writes it
(the default lego 64-px one).

instant-ngp cannot train here: its sampler (nerfacc ``OccGridEstimator.sampling`` ->
``traverse_grids``), ``nerfacc.pack_info`` and the packed ``render_weight_from_density``
need nerfacc's CUDA extension.  So the run is nerfstudio's own ``ns-train instant-ngp``
set-up up to the first training iteration, with a tiny config:

1. the ``ns-train`` command line below is parsed by nerfstudio's own tyro CLI (a method
   table holding nerfstudio 1.1.5's ``instant-ngp`` entry, rebuilt from nerfstudio's
   classes with configs/method_configs.py's values), ``config.save_config()`` writes
   config.yml (``yaml.dump`` of the TrainerConfig), as ``nerfstudio.scripts.train.main`` does;
2. ``train_loop``'s steps: ``_set_random_seed(machine.seed)``, ``config.setup()``,
   ``trainer.setup()`` (seeded random init of the field), the dataparser transform saved
   as ``Trainer.train`` does;
3. the occupancy grid is filled by nerfstudio's own BEFORE_TRAIN_ITERATION callback at
   step 0 (``NGPModel.get_training_callbacks`` -> nerfacc
   ``OccGridEstimator.update_every_n_steps`` -> ``_update``, pure torch: warm-up branch,
   every cell, one uniformly jittered point per cell (torch RNG, seeded), occ = field
   density * render_step_size, binaries = occs > min(mean(occs), 0.01));
4. no training iteration runs (CUDA); ``Trainer.save_checkpoint(0)`` writes the checkpoint.

The goldens are then computed from the run reloaded by nerfstudio's ``eval_setup`` (so
the checkpoint round-trips), model in eval mode.  Nothing here recomputes nerfstudio or
nerfacc; per-ray numbers come only from the nerfacc functions that run on CPU
(``nerfacc.grid._ray_aabb_intersect``, ``nerfacc.grid._query``, batched
``render_weight_from_density`` / ``render_visibility_from_density``) and nerfstudio's
renderers, at sample intervals chosen here (uniform, stated in golden.json) -- NOT
the marcher's samples.

Writes into OUT_DIR:
  weights.safetensors  the checkpoint's ``pipeline`` tensors under ``_model.field.`` and
                       ``_model.occupancy_grid.``, exact keys AND dtypes (bool binaries,
                       int32 resolution, int64 field buffers); metadata ``original_dtypes``
  golden.safetensors   field outputs at 64 points, occupancy-update samples, per-ray CPU numbers
  golden.json          versions, commands, seeds, config, facts, shapes, notes
  config.yml, dataparser_transforms.json, transforms.json   copies (no images)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import nerfstudio_goldens  # noqa: E402  (shared with the nerfacto goldens)
import nerfstudio_train_tiny  # noqa: E402  (installs the import-time stand-ins)

POINT_SEED = nerfstudio_goldens.POINT_SEED  # the points are the nerfacto goldens' (seeded_points)
HASH_SEED = 5  # --hash-table-scale: torch.Generator seed of the re-drawn hash table
OCC_UPDATE_SEED = 7  # torch seed right before the occupancy update (its per-cell jitter)
OCC_SAMPLE_SEED = 99  # which cells' update samples are kept in the golden
OCC_SAMPLES_PER_LEVEL = 64
PIXELS_YX = [(32, 32), (20, 40), (45, 25), (10, 10), (60, 3), (28, 50), (38, 31), (0, 63)]
RAY_N = 512  # per-ray uniform intervals [near + i dt, near + (i+1) dt], dt = render_step_size (not the marcher's)
TRAIN_CAMERA_INDEX = 0
TIMESTAMP = "2026-01-01_000000"


def _ngp_method_config():
    """nerfstudio 1.1.5's ``method_configs["instant-ngp"]`` (configs/method_configs.py:251-273),
    built from nerfstudio's own classes with the same values."""
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
    from nerfstudio.models.instant_ngp import InstantNGPModelConfig
    from nerfstudio.pipelines.dynamic_batch import DynamicBatchPipelineConfig

    return nerfstudio_train_tiny.method_config(
        "instant-ngp",
        DynamicBatchPipelineConfig,
        VanillaDataManagerConfig,
        InstantNGPModelConfig(eval_num_rays_per_chunk=8192),
        {"fields": nerfstudio_train_tiny.adam_exponential(1e-2, 0.0001, 200000)},
        1 << 12,
    )


def _add_ngp_to_method_table() -> None:
    mc = sys.modules["nerfstudio.configs.method_configs"]
    if "instant-ngp" not in mc.method_configs:
        mc.method_configs["instant-ngp"] = _ngp_method_config()
        mc.descriptions["instant-ngp"] = "Implementation of Instant-NGP. Recommended real-time model for unbounded scenes."
        mc.AnnotatedBaseConfigUnion = nerfstudio_train_tiny.method_union(mc.method_configs, mc.descriptions)


def make_run(args) -> tuple[Path, list[str], dict]:
    """ns-train instant-ngp up to its first training iteration (see the module docstring)."""
    import torch
    import tyro
    from nerfstudio.engine.callbacks import TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed

    _add_ngp_to_method_table()
    mc = sys.modules["nerfstudio.configs.method_configs"]
    ns_args = [
        "ns-train",
        "instant-ngp",
        "--machine.device-type", "cpu",
        "--machine.seed", str(args.seed),
        "--pipeline.model.log2-hashmap-size", str(args.log2_hashmap_size),
        "--pipeline.model.grid-resolution", str(args.grid_resolution),
        "--pipeline.model.grid-levels", str(args.grid_levels),
        "--max-num-iterations", "1",
        "--steps-per-save", "1",
        "--vis", "tensorboard",
        "--output-dir", str(args.outputs),
        "--experiment-name", args.experiment,
        "--timestamp", TIMESTAMP,
        "nerfstudio-data", "--data", str(args.data),
    ]
    config = tyro.cli(mc.AnnotatedBaseConfigUnion, args=ns_args[1:])
    # nerfstudio.scripts.train.main
    config.set_timestamp()
    config.save_config()
    # nerfstudio.scripts.train.train_loop
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    # Trainer.train: dataparser transform, then step 0's BEFORE_TRAIN_ITERATION callbacks
    base_dir = config.get_base_dir()
    trainer.pipeline.datamanager.train_dataparser_outputs.save_dataparser_transform(
        base_dir / "dataparser_transforms.json"
    )
    trainer.pipeline.train()
    model = trainer.pipeline.model
    grid = model.occupancy_grid
    if args.hash_table_scale > 0:
        # nerfstudio's init draws the hash table from U(-1e-3, 1e-3): an almost constant field (density 0.9446 +- 2e-4).
        # Re-draw it U(-s, s), seeded, so that field values, occupancy and weights vary (an untrained but non-trivial field).
        table = model.field.mlp_base.model[0].hash_table
        gen = torch.Generator().manual_seed(HASH_SEED)
        with torch.no_grad():
            table.copy_((torch.rand(table.shape, generator=gen) * 2.0 - 1.0) * args.hash_table_scale)
    # record the update's own sample points (nerfacc draws them; we only watch occ_eval_fn's input)
    seen: list = []
    orig_density_fn = model.field.density_fn

    def watching_density_fn(positions, times=None):
        out = orig_density_fn(positions, times)
        seen.append((positions.detach().clone(), out.detach().clone()))
        return out

    model.field.density_fn = watching_density_fn
    torch.manual_seed(OCC_UPDATE_SEED)
    t0 = time.time()
    for callback in trainer.callbacks:
        callback.run_callback_at_location(0, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    occ_time = time.time() - t0
    del model.field.density_fn
    assert len(seen) == grid.levels, len(seen)
    trainer.step = 0
    trainer.save_checkpoint(0)
    update = {
        "levels": [(p, d) for p, d in seen],
        "seconds": occ_time,
        "render_step_size": float(model.config.render_step_size),
    }
    (args.outputs / "ns_ngp_command.txt").write_text(
        "python tools/nerfstudio_ngp_goldens.py " + " ".join(sys.argv[1:]) + "\n" + " ".join(ns_args) + "\n"
    )
    return base_dir, ns_args, update


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--data", type=Path, default=Path("/work/nsrun2/data_default"))
    ap.add_argument("--outputs", type=Path, default=Path("/work/nsrun2/outputs"))
    ap.add_argument("--experiment", default="lego64_ngp")
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--log2-hashmap-size", type=int, default=12)
    ap.add_argument("--grid-resolution", type=int, default=32)
    ap.add_argument("--grid-levels", type=int, default=4)
    ap.add_argument(
        "--hash-table-scale",
        type=float,
        default=10.0,
        help="re-draw the field's hash table U(-s, s) (seeded) after nerfstudio's init; 0 keeps nerfstudio's U(-1e-3, 1e-3)",
    )
    args = ap.parse_args()
    args.outputs = args.outputs.resolve()
    args.data = args.data.resolve()
    out_dir = args.out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)

    import numpy as np
    import torch

    torch.set_num_threads(nerfstudio_train_tiny.NUM_THREADS)
    t_start = time.time()
    run_dir, ns_args, update = make_run(args)
    t_run = time.time() - t_start

    import nerfacc
    from nerfacc.grid import _query, _ray_aabb_intersect
    from nerfacc.volrend import render_visibility_from_density, render_weight_from_density
    from nerfstudio.cameras.rays import Frustums, RaySamples
    from nerfstudio.field_components.field_heads import FieldHeadNames

    config, pipeline, ckpt_path, step, raw = nerfstudio_goldens.load_run(run_dir)
    model = pipeline.model
    mcfg = config.pipeline.model
    field = model.field
    grid = model.occupancy_grid

    # ---- 1. weights (exact dtypes) --------------------------------------------------------------
    weights, orig_dtypes = nerfstudio_goldens.save_checkpoint_tensors(
        raw, ("_model.field.", "_model.occupancy_grid."), out_dir / "weights.safetensors"
    )
    other_keys = sorted(k for k in raw["pipeline"] if k not in weights)
    other_keys_summary = sorted({".".join(k.split(".")[:2]) for k in other_keys})

    # the reloaded model holds exactly the checkpoint's tensors
    sd = model.state_dict()
    reload_max_diff = max(
        float((sd[k[len("_model.") :]].double() - v.double()).abs().max()) if v.numel() else 0.0
        for k, v in weights.items()
    )

    # ---- 2. copies --------------------------------------------------------------------------------
    nerfstudio_goldens.copy_run_files(run_dir, config, out_dir)

    g: dict[str, torch.Tensor] = {}

    # ---- 3. field at seeded points ----------------------------------------------------------------
    gen = torch.Generator().manual_seed(POINT_SEED)
    points, dirs, layout = nerfstudio_goldens.seeded_points(gen)
    g["points"] = points
    g["points_directions"] = dirs
    with torch.no_grad():
        fo = nerfstudio_goldens.field_outputs_at(field, points, dirs)
        g["points_density"] = fo[FieldHeadNames.DENSITY].float()
        g["points_rgb"] = fo[FieldHeadNames.RGB].float()
        g["points_density_fn"] = field.density_fn(points).float()  # what the occupancy update evaluates
        g.update(nerfstudio_goldens.field_stages(field, points, dirs, hash_after_mlp=True))
        # occupancy lookup of the points with nerfacc's own (torch) grid query
        occ_q, occ_sel = _query(points, grid.binaries.float(), grid.aabbs[0])
        g["points_occupancy_query"] = occ_q.float()
        g["points_occupancy_query_in_grid"] = occ_sel.long()

    # ---- 4. occupancy grid: the update's own samples (a seeded subset of cells per level) ----------
    sel_gen = torch.Generator().manual_seed(OCC_SAMPLE_SEED)
    cells_per_lvl = grid.cells_per_lvl
    rows = []
    for lvl, (pos, dens) in enumerate(update["levels"]):
        idx = torch.randperm(cells_per_lvl, generator=sel_gen)[:OCC_SAMPLES_PER_LEVEL]
        rows.append((torch.full_like(idx, lvl), idx, pos[idx], dens.reshape(-1)[idx]))
    g["occ_update_level"] = torch.cat([r[0] for r in rows]).long()
    g["occ_update_cell"] = torch.cat([r[1] for r in rows]).long()
    g["occ_update_position"] = torch.cat([r[2] for r in rows]).float()
    g["occ_update_density"] = torch.cat([r[3] for r in rows]).float()
    occs = grid.occs
    lvl_t, cell_t = g["occ_update_level"], g["occ_update_cell"]
    g["occ_update_occs"] = occs[lvl_t * cells_per_lvl + cell_t].float()
    thre = float(torch.clamp(occs.mean(), max=0.01))
    binaries_rule_ok = bool(torch.equal(grid.binaries, (occs > torch.clamp(occs.mean(), max=0.01)).view(grid.binaries.shape)))
    occs_rule_max_diff = float(
        (g["occ_update_occs"] - g["occ_update_density"] * float(mcfg.render_step_size or update["render_step_size"]))
        .abs()
        .max()
    )

    # ---- 5. per-ray numbers from what runs on CPU ----------------------------------------------------
    dm = pipeline.datamanager
    cam = dm.train_dataset.cameras[TRAIN_CAMERA_INDEX : TRAIN_CAMERA_INDEX + 1]
    bundle_full = cam.generate_rays(camera_indices=0, keep_shape=True)
    ys = torch.tensor([p[0] for p in PIXELS_YX])
    xs = torch.tensor([p[1] for p in PIXELS_YX])
    bundle = bundle_full[ys, xs]
    n_rays = len(PIXELS_YX)
    g["rays_pixel_yx"] = torch.tensor(PIXELS_YX, dtype=torch.int64)
    g["rays_origins"] = bundle.origins.float()
    g["rays_directions"] = bundle.directions.float()
    g["train_camera_to_worlds"] = cam.camera_to_worlds[0].float()
    with torch.no_grad():
        tmin, tmax, hits = _ray_aabb_intersect(bundle.origins, bundle.directions, grid.aabbs)
        g["rays_aabb_tmin"] = tmin.float()
        g["rays_aabb_tmax"] = tmax.float()
        g["rays_aabb_hit"] = hits.long()
        dt = float(model.config.render_step_size)
        t0 = float(mcfg.near_plane)
        edges = t0 + dt * torch.arange(RAY_N + 1, dtype=torch.float64)
        edges = edges.float()
        alpha_thre_eff = min(float(mcfg.alpha_thre), float(grid.occs.mean()))
        starts = edges[:-1].expand(n_rays, RAY_N).contiguous()
        ends = edges[1:].expand(n_rays, RAY_N).contiguous()
        rs = RaySamples(
            frustums=Frustums(
                origins=bundle.origins[:, None, :].expand(n_rays, RAY_N, 3),
                directions=bundle.directions[:, None, :].expand(n_rays, RAY_N, 3),
                starts=starts[..., None],
                ends=ends[..., None],
                pixel_area=bundle.pixel_area[:, None, :].expand(n_rays, RAY_N, 1),
            ),
            camera_indices=bundle.camera_indices[:, None, :].expand(n_rays, RAY_N, 1),
        )
        fo = field.forward(rs, compute_normals=False)
        sig = fo[FieldHeadNames.DENSITY][..., 0]
        rgb = fo[FieldHeadNames.RGB]
        w, trans, alphas = render_weight_from_density(starts, ends, sig)
        vis = render_visibility_from_density(
            starts, ends, sig, early_stop_eps=1e-4, alpha_thre=alpha_thre_eff
        )
        mids = rs.frustums.get_positions()  # (starts + ends) / 2 along the ray
        occ_mid, _ = _query(mids.reshape(-1, 3), grid.binaries.float(), grid.aabbs[0])
        g["rays_t_starts"] = starts.float()
        g["rays_t_ends"] = ends.float()
        g["rays_sample_density"] = sig.float()
        g["rays_sample_rgb"] = rgb.float()
        g["rays_sample_weights"] = w.float()
        g["rays_sample_transmittance"] = trans.float()
        g["rays_sample_alphas"] = alphas.float()
        g["rays_sample_visible"] = vis.long()
        g["rays_sample_occupancy_query"] = occ_mid.reshape(n_rays, RAY_N).float()
        g["rays_rgb"] = model.renderer_rgb(rgb=rgb, weights=w[..., None]).float()
        g["rays_accumulation"] = model.renderer_accumulation(weights=w[..., None]).float()
        g["rays_depth"] = model.renderer_depth(weights=w[..., None], ray_samples=rs).float()

    # ---- 6. nerfstudio's own eval path on CPU: does it run? -----------------------------------------
    eval_path = {}
    for name, fn in {
        "model.get_outputs_for_camera (VolumetricSampler -> OccGridEstimator.sampling -> traverse_grids)": lambda: model.get_outputs_for_camera(cam),
        "nerfacc.ray_aabb_intersect (CUDA)": lambda: nerfacc.ray_aabb_intersect(bundle.origins, bundle.directions, grid.aabbs),
        "nerfacc.pack_info (CPU tensor)": lambda: nerfacc.pack_info(torch.zeros(3, dtype=torch.long), 1),
    }.items():
        try:
            with torch.no_grad():
                fn()
            eval_path[name] = "runs"
        except Exception as e:  # noqa: BLE001
            eval_path[name] = f"fails: {type(e).__name__}: {str(e).splitlines()[0][:160]}"

    g = nerfstudio_goldens.save_golden_tensors(g, out_dir)

    # ---- golden.json --------------------------------------------------------------------------------
    import torchmetrics
    from importlib.metadata import version

    binaries = grid.binaries
    info = {
        "generator": "tools/nerfstudio_ngp_goldens.py (calls nerfstudio and nerfacc; no nerfstudio/nerfacc code copied)",
        "versions": {
            "nerfstudio": version("nerfstudio"),
            "nerfacc": version("nerfacc"),
            "torch": torch.__version__,
            "numpy": np.__version__,
            "torchmetrics": torchmetrics.__version__,
            "python": sys.version.split()[0],
            "tinycudann": "not installed: NerfactoField(implementation='tcnn') falls back to torch",
        },
        "commands": {
            "goldens_and_run": (args.outputs / "ns_ngp_command.txt").read_text().strip(),
            "ns_train_equivalent": " ".join(ns_args),
        },
        "run_dir": str(run_dir),
        "checkpoint": ckpt_path.name,
        "checkpoint_step": int(step),
        "trained": False,
        "timings_s": {"run_setup_and_occupancy_update": round(t_run, 2), "occupancy_update": round(update["seconds"], 2)},
        "seeds": {
            "machine_seed": int(config.machine.seed),
            "occupancy_update_torch_seed": OCC_UPDATE_SEED,
            "occupancy_sample_subset_seed": OCC_SAMPLE_SEED,
            "hash_table_redraw": (
                f"mlp_base.model.0.hash_table = (torch.rand(shape, generator=torch.Generator().manual_seed({HASH_SEED})) * 2 - 1)"
                f" * {args.hash_table_scale}, after trainer.setup()"
                if args.hash_table_scale > 0
                else "none (nerfstudio's init)"
            ),
            "points_seed": POINT_SEED,
            "torch_threads": nerfstudio_train_tiny.NUM_THREADS,
        },
        "dataparser": {
            "dataparser_scale": float(dm.train_dataparser_outputs.dataparser_scale),
            "dataparser_transform": dm.train_dataparser_outputs.dataparser_transform.tolist(),
            "scene_box_aabb": dm.train_dataparser_outputs.scene_box.aabb.tolist(),
            "num_train_images": len(dm.train_dataset),
        },
        "model": {
            "config_values": {
                "grid_resolution": mcfg.grid_resolution,
                "grid_levels": mcfg.grid_levels,
                "max_res": mcfg.max_res,
                "log2_hashmap_size": mcfg.log2_hashmap_size,
                "alpha_thre": mcfg.alpha_thre,
                "cone_angle": mcfg.cone_angle,
                "render_step_size_in_config_yml": None,
                "render_step_size_used": float(model.config.render_step_size),
                "near_plane": mcfg.near_plane,
                "far_plane": mcfg.far_plane,
                "use_appearance_embedding": mcfg.use_appearance_embedding,
                "background_color": mcfg.background_color,
                "disable_scene_contraction": mcfg.disable_scene_contraction,
                "enable_collider": mcfg.enable_collider,
                "eval_num_rays_per_chunk": mcfg.eval_num_rays_per_chunk,
            },
            "field": {
                "class": type(field).__name__,
                "num_levels": int(field.num_levels),
                "base_res": field.base_res,
                "max_res": int(field.max_res),
                "log2_hashmap_size": int(field.log2_hashmap_size),
                "features_per_level": 2,
                "hidden_dim": 64,
                "num_layers": 2,
                "geo_feat_dim": field.geo_feat_dim,
                "hidden_dim_color": 64,
                "num_layers_color": 3,
                "appearance_embedding_dim": field.appearance_embedding_dim,
                "use_average_appearance_embedding": field.use_average_appearance_embedding,
                "average_init_density": field.average_init_density,
                "spatial_distortion": repr(field.spatial_distortion),
                "aabb": field.aabb.tolist(),
                "hash_encoding_class": type(field.mlp_base.model[0]).__name__ if hasattr(field.mlp_base, "model") else None,
            },
            "occupancy_grid": {
                "resolution": grid.resolution.tolist(),
                "levels": grid.levels,
                "aabbs": grid.aabbs.tolist(),
                "cells_per_level": cells_per_lvl,
                "occupied_per_level": [int(binaries[i].sum()) for i in range(grid.levels)],
                "occs_mean": float(occs.mean()),
                "binarize_threshold_min_mean_0.01": thre,
                "binaries_equal_occs_gt_threshold": binaries_rule_ok,
                "checkpoint_sampler_copy_identical": all(
                    torch.equal(raw["pipeline"][f"_model.sampler.occupancy_grid.{n}"], raw["pipeline"][f"_model.occupancy_grid.{n}"])
                    for n in ("resolution", "aabbs", "occs", "binaries")
                ),
                "occs_equal_density_times_step_max_abs_diff_on_kept_samples": occs_rule_max_diff,
                "update": "nerfstudio BEFORE_TRAIN_ITERATION callback at step 0 -> nerfacc OccGridEstimator._update "
                "warm-up branch: every cell, x = aabb_min + (cell + U[0,1)^3)/res * (aabb_max - aabb_min), "
                "occs = max(0 * 0.95, density_fn(x) * render_step_size), binaries = occs > min(mean(occs), 0.01)",
            },
        },
        "checkpoint_other_keys": other_keys_summary,
        "reload_max_abs_diff": reload_max_diff,
        "points": {
            "layout": layout,
            "appearance": "eval: zeros (NGP's field has use_average_appearance_embedding False)",
        },
        "rays": {
            "camera": f"train {TRAIN_CAMERA_INDEX}",
            "pixels_yx": PIXELS_YX,
            "pixel_center_offset": 0.5,
            "aabb_intersection": "nerfacc.grid._ray_aabb_intersect (torch twin of the CUDA one) with the 4 level aabbs, "
            "near -inf, far inf, miss inf",
            "intervals": f"NOT the marcher's: {RAY_N} contiguous intervals per ray, edges near_plane + i * render_step_size "
            f"(float64, then float32), i = 0..{RAY_N}; no cone-angle growth, no occupancy skipping",
            "weights": "nerfacc.render_weight_from_density batched (the CPU path; nerfstudio's eval uses the packed path, "
            "same formula)",
            "visible": "nerfacc.render_visibility_from_density batched, early_stop_eps 1e-4, alpha_thre = "
            f"min(config alpha_thre, occs.mean()) = {alpha_thre_eff} as OccGridEstimator.sampling computes it in training "
            "(nerfstudio's eval passes no sigma_fn, so no such pruning happens at eval; for reference only)",
            "occupancy_query": "nerfacc.grid._query of each interval midpoint (0 = the marcher would skip it)",
            "rgb": "nerfstudio RGBRenderer (eval: nan_to_num, background 'random' => no background added, clamp [0,1])",
        },
        "cpu_eval_path": eval_path,
        "notes": NOTES,
        "tensors": {k: {"shape": list(v.shape), "dtype": str(v.dtype).replace("torch.", "")} for k, v in g.items()},
        "weights": {k: {"shape": list(v.shape), "dtype": orig_dtypes[k]} for k, v in weights.items()},
    }
    nerfstudio_goldens.write_golden_json(info, out_dir)
    print(json.dumps({k: info[k] for k in ("model", "cpu_eval_path", "timings_s", "reload_max_abs_diff")}, indent=1, default=str))


NOTES = [
    "Untrained: the field is nerfstudio's seeded random init (machine.seed via nerfstudio.scripts.train._set_random_seed "
    "before config.setup()), its hash table then re-drawn U(-s, s) (seeds.hash_table_redraw) because nerfstudio's "
    "U(-1e-3, 1e-3) init gives an almost constant density; only the occupancy grid was then filled, by nerfstudio's own "
    "step-0 callback, and the checkpoint saved by Trainer.save_checkpoint.",
    "NGPModel builds NerfactoField with appearance_embedding_dim = 0 if use_appearance_embedding else 32 "
    "(nerfstudio/models/instant_ngp.py:107, inverted): the default (False) gets a 32-dim appearance embedding, "
    "zeros at eval (use_average_appearance_embedding False).",
    "config.yml has render_step_size null (saved before the model exists); NGPModel.populate_modules computes "
    "||aabb_max - aabb_min|| / 1000 (instant_ngp.py:116-118) and stores it in the in-memory config only.",
    "At eval nerfstudio's VolumetricSampler passes sigma_fn=None (ray_samplers.py:417) so OccGridEstimator.sampling "
    "skips the alpha_thre / early_stop_eps pruning (occ_grid.py:180); samples = traverse_grids' intervals only; "
    "stratified = self.training = False.",
    "Compositing at eval: packed render_weight_from_density (instant_ngp.py:193), RGBRenderer with background "
    "'random' returns the composite without background (black), nan_to_num before and clamp to [0,1] after; "
    "depth = sum w * (start+end)/2 / (acc + 1e-10), clipped to [min, max] of the midpoints.",
    "The checkpoint also holds _model.sampler.occupancy_grid.{resolution,aabbs,occs,binaries}, identical copies "
    "(VolumetricSampler keeps the OccGridEstimator as a submodule), _model.scene_aabb (6,), "
    "_model.device_indicator_param and _model.lpips.*; weights.safetensors keeps only _model.field.* and "
    "_model.occupancy_grid.*. The occupancy binaries golden IS weights.safetensors' _model.occupancy_grid.binaries "
    "(bool [levels, res, res, res], binaries[l, x, y, z], cell id = l*res^3 + (x*res + y)*res + z).",
    "weights.safetensors keeps the checkpoint's dtypes (occupancy_grid.binaries bool, resolution int32, field "
    "max_res/num_levels/log2_hashmap_size int64); occupancy_grid.grid_coords / grid_indices are non-persistent "
    "buffers and not in the checkpoint.",
]


if __name__ == "__main__":
    main()
