"""Hiding a payload: a file's bytes, or a sealed image, become an ordinary secret that the exact method hides.

The record (runtime.payload) is turned into pixels, sealed first when there is a passphrase
(runtime.sealing), hidden by `hide` like any secret, and a sealed bundle is then tagged. Only the exact
method reproduces every byte, so payloads are refused with --method paper; a hide that is not exact
leaves no bundle (run.hide raises InexactResult, and never takes allow_inexact with a payload).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import check_output_path
from noisenerf.runtime.payload import Record, payload_secret
from noisenerf.runtime.progress import ProgressFn
from noisenerf.runtime.sealing import Seal, derive_keys, new_seal
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.scene import Scene
from noisenerf.train.hide.tiling import tile_rects

# The exact hide's rate for payload pixels on 2 CPU cores, the basis of the time a hide announces (measured
# on a random 1 MiB file: docs/usage.md, "Hide a file").
PAYLOAD_PIXELS_PER_SECOND = 18_000


def capacity(secret: np.ndarray, tile_size: int) -> dict:
    """What a payload's secret costs: its size, pixels, tiles, and the hide time to expect on 2 cores."""
    height, width = secret.shape[:2]
    return {"width": width, "height": height, "pixels": width * height,
            "tiles": len(tile_rects(width, height, tile_size)),
            "expected_seconds": round(width * height / PAYLOAD_PIXELS_PER_SECOND, 1)}


def hide_payload(scene: Scene, record: Record, output: Path, config: HideConfig, device: torch.device,
                 passphrase: bytes | None = None, seal: Seal | None = None, force: bool = False,
                 progress: ProgressFn | None = None, announce: Callable[[dict], None] | None = None,
                 workers: int | None = None, executor: str = "local", ray_address: str | None = None,
                 verbose: bool = False) -> dict:
    """Hide a record; sealed under `passphrase` when one is given, with `seal` (default: a fresh one,
    random salt and nonce; tests pass a fixed one). announce(capacity) is called before the hide starts;
    workers, executor and ray_address as run.hide takes them."""
    if config.method != "exact":
        raise UserError("a file or sealed payload needs --method exact (the paper's method does not reproduce "
                        "every byte)")
    output = check_output_path(output, force=force)
    sealing = None
    if passphrase is not None:
        seal = seal or new_seal()
        sealing = (seal, derive_keys(passphrase, seal))
    secret, marker = payload_secret(record, config.tile_size, scene.fingerprint(), sealing)
    room = {**capacity(secret, config.tile_size), "kind": record.kind, "bytes": len(record.body)}
    if announce is not None:
        announce(room)
    report = hide(scene, secret, output, config, device, force=force, progress=progress, payload_marker=marker,
                  workers=workers, executor=executor, ray_address=ray_address, verbose=verbose,
                  seal_keys=None if sealing is None else sealing[1])
    return {**report, "bundle_bytes": output.stat().st_size, "payload": record.report(),
            "sealed": sealing is not None, "capacity": room}
