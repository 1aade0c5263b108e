"""The hashgrid preset's variants fitted on lego at 200 px on the CPU, 2 cores each, 8 at once (a 16-core machine).

Not run by CI. Usage: OUT=results/ python tools/hashgrid_preset_sweep.py MINUTES DATA_DIR, DATA_DIR holding lego
(NeRF-Synthetic format). Each variant writes NAME.json (steps, test PSNR, SSIM) into OUT. docs/field-kinds.md has the
figures this measured.
"""
import dataclasses
import json
import os
import sys
from pathlib import Path
import multiprocessing as mp

VARIANTS = {  # changes to the hashgrid preset (its lr_final was 3e-4 when docs/field-kinds.md's figures were measured)
    "preset": {},
    "final3e-4": {"lr_final": 3e-4},
    "table19": {"field": {"log2_table": 19}},
    "batch2048": {"batch_rays": 2048},
    "samples192": {"n_samples": 192},
    "samples96": {"n_samples": 96},
    "res2048": {"field": {"per_level_scale": 1.3819128799677762}},
    "table19_final3e-4": {"field": {"log2_table": 19}, "lr_final": 3e-4},
}


def run(name, cores, minutes, out, data):
    os.sched_setaffinity(0, cores)
    import torch
    torch.set_num_threads(2)
    from noisenerf.train.scene.datasets import load_dataset
    from noisenerf.train.scene.fit import PRESETS, Budget, fit
    change = VARIANTS[name]
    preset = PRESETS["hashgrid"]
    config = dataclasses.replace(preset, **{k: v for k, v in change.items() if k != "field"},
                                 field=dataclasses.replace(preset.field, **change.get("field", {})))
    dataset = load_dataset(data, resolution=200)
    report = fit(dataset, Path(f"/tmp/sweep/{name}"), config, Budget(minutes=minutes), torch.device("cpu"),
                 curve_seconds=1e9, checkpoint_seconds=1e9)
    result = {"name": name, "steps": report["steps"], "psnr": report["test"]["psnr"], "ssim": report["test"]["ssim"],
              "seconds": report["seconds"]}
    print(json.dumps(result), flush=True)
    (Path(out) / f"{name}.json").write_text(json.dumps(result))


if __name__ == "__main__":
    minutes, out = float(sys.argv[1]), os.environ["OUT"]
    Path("/tmp/sweep").mkdir(exist_ok=True)
    print("cpus", os.cpu_count(), open("/proc/cpuinfo").read().split("model name")[1].split("\n")[0], flush=True)
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=run, args=(name, {2 * i, 2 * i + 1}, minutes, out, sys.argv[2])) for i, name in enumerate(VARIANTS)]
    for p in procs:
        p.start()
    for p in procs:
        p.join()
