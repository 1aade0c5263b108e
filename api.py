"""The sender's library: `noisenerf.fit`, `noisenerf.hide`, `noisenerf.export_model` (the train extra), what
`noisenerf fit | hide | export` do, in a call; the recipient's half is runtime/api.py.

    noisenerf.fit("data/lego", "scenes/lego", preset="small", minutes=15)
    noisenerf.hide("scenes/lego", "secret.png", "secret.bundle")            # or an (h, w, 3) uint8 array
    noisenerf.hide("scenes/lego", output="note.bundle", file="note.txt", passphrase="…")
    noisenerf.export_model("scenes/lego", "lego.onnx")

Each returns the report `--json` prints; nothing is printed (progress goes to a `progress` callback taking
runtime.progress's ProgressEvent); every refusal is a UserError whose message is the command line's line (an exact
hide left inexact: InexactResult). torch is imported only when a function is called, so `import noisenerf`
stays the recipient's.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Callable

import numpy as np

from noisenerf.runtime.arguments import (checked_callback, checked_flag, checked_int, checked_number, checked_path,
                                         checked_source, checked_text, optional, wrong)
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.progress import ProgressFn

PathLike = str | os.PathLike
DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:[0-9]{1,2})?")


def resolve_device(name: str):
    """'auto' picks CUDA when torch sees a GPU; an explicit 'cuda' without one is refused, and so is any
    name but auto, cpu, cuda and cuda:N."""
    if not DEVICE_PATTERN.fullmatch(name):
        raise UserError(f"unknown --device {name[:40]!r} (expected auto, cpu, cuda or cuda:N)")
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda requested but torch sees no CUDA device")
    return torch.device(name)


def fit(data: PathLike, output: PathLike, *, field: str | None = None, preset: str | None = None,
        resolution: int | None = None, minutes: float | None = None, iters: int | None = None,
        seed: int | None = None, skip: bool = True, appearance: bool = False, all_test_views: bool = False,
        device: str = "auto", progress: ProgressFn | None = None) -> dict:
    """Fit a scene to the dataset at `data` (NeRF-Synthetic, LLFF or a capture's transforms.json) into the
    folder `output`, for exactly one of `minutes` or `iters`; run again to resume from its checkpoint. field:
    the kind (`mlp`, `hashgrid`), fitted with its default preset unless `preset` names another of its kind;
    neither: the dataset kind's (presets.DEFAULT_FIELDS: `hashgrid` for NeRF-Synthetic, `nerfacto` for LLFF
    and captures). appearance: a nerfacto fit learns a per-image appearance
    embedding (for photos whose exposure differs), its mean folded into the saved field. The closing test renders
    stop at a tenth of the training time (train.scene.fit.TEST_SHARE; the first held-out view always), or render
    every held-out view with `all_test_views`. -> fit's report (test PSNR under test.psnr, over test.views of
    test.held_out)."""
    data, output, progress = checked_path(data, "data"), checked_path(output, "output"), \
        optional(checked_callback, progress, "progress")
    field, preset, device = optional(checked_text, field, "field"), optional(checked_text, preset, "preset"), \
        checked_text(device, "device")
    resolution, iters, seed = (optional(checked_int, value, name) for value, name in
                               ((resolution, "resolution"), (iters, "iters"), (seed, "seed")))
    minutes, skip = optional(checked_number, minutes, "minutes"), checked_flag(skip, "skip")
    appearance, all_test_views = checked_flag(appearance, "appearance"), checked_flag(all_test_views, "all_test_views")

    from noisenerf.runtime.files import check_output_directory
    from noisenerf.train.scene.presets import DEFAULT_FIELDS, DEFAULT_PRESETS, PRESET_KINDS

    if (minutes is None) == (iters is None):
        raise UserError("give exactly one of --minutes M or --iters N")
    if (iters is not None and iters < 1) or (minutes is not None and minutes <= 0):
        raise UserError("--minutes and --iters must be positive")
    if field is not None and field not in DEFAULT_PRESETS:
        raise UserError(f"unknown field kind {field!r:.40} (expected one of {', '.join(DEFAULT_PRESETS)})")
    if preset is not None and preset not in PRESET_KINDS:
        raise UserError(f"unknown preset {preset!r:.40} (expected one of {', '.join(PRESET_KINDS)})")
    if field is not None and preset is not None and PRESET_KINDS[preset] != field:
        raise UserError(f"preset {preset} fits the {PRESET_KINDS[preset]} kind, not {field}")
    chosen_kind = field or (PRESET_KINDS[preset] if preset else None)  # None: the dataset's kind decides, below
    if appearance and chosen_kind not in (None, "nerfacto"):
        raise UserError(f"--appearance is for nerfacto fits, not {chosen_kind}")
    from noisenerf.train.scene.datasets import load_dataset
    from noisenerf.train.scene.fit import APPEARANCE_DIM, PRESETS, TEST_SHARE, Budget, fit as fit_scene

    torch_device = resolve_device(device)
    check_output_directory(output)
    dataset = load_dataset(data, resolution=resolution)
    preset = preset or DEFAULT_PRESETS[field or DEFAULT_FIELDS[dataset.kind]]
    config = PRESETS[preset]
    if appearance and config.proposal is None:
        raise UserError(f"--appearance is for nerfacto fits; a {dataset.kind} dataset fits the "
                        f"{PRESET_KINDS[preset]} kind unless --field nerfacto")
    if seed is not None or not skip:
        config = dataclasses.replace(config, seed=config.seed if seed is None else seed,
                                     skipping=config.skipping and skip)
    if appearance:
        config = dataclasses.replace(config, proposal=dataclasses.replace(config.proposal,
                                                                          appearance_dim=APPEARANCE_DIM))
    return fit_scene(dataset, Path(output), config, Budget(iters, minutes), torch_device,
                     test_share=None if all_test_views else TEST_SHARE, progress=progress)


def hide(scene, secret: PathLike | np.ndarray | None = None, output: PathLike | None = None, *,
         file: PathLike | bytes | None = None, file_name: str = "", passphrase: str | bytes | None = None,
         method: str = "exact", layout: str | None = None, dtype: str | None = None, samples: int | None = None,
         tile_size: int | None = None, view: int = 0, seed: int = 0, settings: tuple = (),
         workers: int | None = None, executor: str = "local", ray_address: str | None = None, device: str = "auto",
         force: bool = False, allow_inexact: bool = False, progress: ProgressFn | None = None,
         announce: Callable[[dict], None] | None = None, warn: Callable[[str], None] | None = None,
         verbose: bool = False) -> dict:
    """Hide a secret image (a path, or an (h, w, 3) uint8 array) or a file (`file`: a path, or bytes named
    `file_name`) in `scene` (a scene folder or a loaded Scene), writing the bundle to `output`; sealed when a
    passphrase is given. settings: the method's settings dataclasses (train/hide/settings.py; its defaults
    where none); tile_size: HideConfig's default where None. announce(capacity) is told a payload's size and
    expected time, warn(line) each warning about the secret read from a path (what it kept of it), both before
    the hide starts; verbose lets Ray's own log lines through to stderr. -> hide's report; an image read from a
    path adds `precision` and `warnings`."""
    from noisenerf.runtime.images import load_secret, precision_note
    from noisenerf.runtime.payload import Record, image_record, read_payload_file
    from noisenerf.train.hide.methods import METHODS
    from noisenerf.train.hide.plan import HideConfig
    from noisenerf.train.hide.settings import part_pixels_for
    from noisenerf.train.scene.scene import Scene, load_scene

    if output is None:
        raise UserError("hide needs an output bundle (-o)")
    output = checked_path(output, "output")
    if not isinstance(scene, (str, os.PathLike, Scene)):
        raise wrong("scene", "a scene folder (str or os.PathLike) or a Scene", scene)
    if secret is not None and not isinstance(secret, (str, os.PathLike, np.ndarray)):
        raise wrong("secret", "a path (str or os.PathLike) or an (h, w, 3) uint8 array", secret)
    file = optional(checked_source, file, "file")
    file_name, method, executor, device = (checked_text(value, name) for value, name in (
        (file_name, "file_name"), (method, "method"), (executor, "executor"), (device, "device")))
    layout, dtype, ray_address = (optional(checked_text, value, name) for value, name in (
        (layout, "layout"), (dtype, "dtype"), (ray_address, "ray_address")))
    samples, tile_size, workers = (optional(checked_int, value, name) for value, name in (
        (samples, "samples"), (tile_size, "tile_size"), (workers, "workers")))
    view, seed = checked_int(view, "view"), checked_int(seed, "seed")
    force, allow_inexact, verbose = (checked_flag(value, name) for value, name in (
        (force, "force"), (allow_inexact, "allow_inexact"), (verbose, "verbose")))
    progress, announce, warn = (optional(checked_callback, value, name) for value, name in (
        (progress, "progress"), (announce, "announce"), (warn, "warn")))
    if not isinstance(settings, (tuple, list)) or not all(dataclasses.is_dataclass(s) for s in settings):
        raise wrong("settings", "a tuple of settings dataclasses", settings)
    if passphrase is not None and not isinstance(passphrase, (str, bytes)):
        raise wrong("passphrase", "a str or bytes", passphrase)
    if (secret is None) == (file is None):
        raise UserError("give exactly one of SECRET_IMAGE or --file PAYLOAD")
    if workers is not None and workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    if ray_address is not None and executor != "ray":
        raise UserError("--ray-address is for --executor ray")
    if method not in METHODS:
        raise UserError(f"unknown method {method!r:.40} (expected one of {', '.join(METHODS)})")
    if executor == "ray":  # before the scene loads: a missing extra is one line at once
        from noisenerf.train.hide.ray_executor import import_ray

        import_ray()
    passphrase = passphrase.encode() if isinstance(passphrase, str) else passphrase
    from noisenerf.train.hide.run import PAYLOAD_IS_EXACT

    if allow_inexact and (file is not None or passphrase is not None):
        raise UserError(PAYLOAD_IS_EXACT)
    torch_device = resolve_device(device)
    config = HideConfig(method=method, layout=layout, dtype=dtype, n_samples=samples, view=view, seed=seed,
                        part_pixels=part_pixels_for(torch_device.type), settings=tuple(settings),
                        **({} if tile_size is None else {"tile_size": tile_size}))
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    notes = {}
    if isinstance(secret, (str, os.PathLike)):
        secret, warnings, bits = load_secret(secret)
        notes = {"precision": precision_note(bits), "warnings": warnings}
        for warning in warnings if warn is not None else ():
            warn(warning)
    elif secret is not None:
        secret = checked_pixels(secret)
    if file is not None or passphrase is not None:
        from noisenerf.train.hide.payload import hide_payload

        if isinstance(file, bytes):
            record = Record("file", file, name=os.fsencode(file_name))
        else:
            record = read_payload_file(file) if file is not None else image_record(secret)
        return {**hide_payload(scene, record, Path(output), config, torch_device, passphrase=passphrase,
                               force=force, progress=progress, announce=announce, workers=workers,
                               executor=executor, ray_address=ray_address, verbose=verbose), **notes}
    from noisenerf.train.hide.run import hide as hide_secret

    return {**hide_secret(scene, secret, Path(output), config, torch_device, force=force, progress=progress,
                          workers=workers, allow_inexact=allow_inexact, executor=executor,
                          ray_address=ray_address, verbose=verbose), **notes}


def checked_pixels(secret) -> np.ndarray:
    """An in-memory secret: (h, w, 3) or (h, w) uint8, as a contiguous (h, w, 3) array."""
    pixels = np.asarray(secret)
    if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[-1] != 3):
        raise UserError(f"a secret array must be (h, w, 3) or (h, w) uint8, got {pixels.shape} {pixels.dtype}")
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=-1)
    return np.ascontiguousarray(pixels)


def import_nerfstudio(run: PathLike, output: PathLike, *, data: PathLike | None = None, force: bool = False) -> dict:
    """Import a nerfstudio nerfacto or instant-ngp run directory (config.yml, dataparser_transforms.json,
    nerfstudio_models/) as the scene folder `output`; `data`: the dataset holding transforms.json (default:
    the path the run recorded); force: replace an earlier scene in `output` (a folder holding anything else is
    refused). -> what `noisenerf import-nerfstudio --json` prints."""
    from noisenerf.train.scene.import_nerfstudio import import_nerfstudio as import_run

    run, output, data = checked_path(run, "run"), checked_path(output, "output"), optional(checked_path, data, "data")
    force = checked_flag(force, "force")
    scene = import_run(Path(run), Path(output), data=Path(data) if data is not None else None, force=force)
    return {"scene": str(output), "fingerprint": scene.fingerprint(),
            "method": "nerfacto" if scene.config.coarse.proposals else "instant-ngp",
            "implementation": scene.config.coarse.implementation, "cameras": len(scene.config.cameras)}


def import_ingp(snapshot: PathLike, output: PathLike, *, data: PathLike | None = None, force: bool = False) -> dict:
    """Import an Instant-NGP NeRF snapshot (`.ingp`, `.msgpack`) as the hashgrid scene folder `output`; `data`:
    the capture folder holding transforms.json whose cameras to keep (default: the cameras the snapshot
    carries); force: replace an earlier scene in `output`. -> what `noisenerf import-ingp --json` prints."""
    from noisenerf.train.scene.import_ingp import import_ingp as import_snapshot

    snapshot, output = checked_path(snapshot, "snapshot"), checked_path(output, "output")
    data, force = optional(checked_path, data, "data"), checked_flag(force, "force")
    scene = import_snapshot(Path(snapshot), Path(output), data=Path(data) if data is not None else None, force=force)
    field = scene.config.coarse
    return {"scene": str(output), "fingerprint": scene.fingerprint(), "cameras": len(scene.config.cameras),
            "levels": field.levels, "features": field.features, "log2_table": field.log2_table}


def export_model(scene: PathLike, output: PathLike, *, force: bool = False) -> dict:
    """Export a scene folder's frozen fields to one ONNX file with a `noise` input port; written only once
    onnx.checker, the torch-against-onnxruntime probe and the fingerprint check pass; an existing `output` is
    replaced only with force. -> export's report."""
    from noisenerf.export.onnx_export import export_scene

    scene, output, force = checked_path(scene, "scene"), checked_path(output, "output"), checked_flag(force, "force")
    return export_scene(Path(scene), Path(output), force=force)
