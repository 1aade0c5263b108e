"""A file hidden as a payload, plain and sealed, and revealed as `noisenerf-reveal` does."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from noisenerf.runtime.api import reveal
from noisenerf.runtime.payload import Record
from noisenerf.runtime.sealing import ScryptParams, derive_keys, new_seal
from noisenerf.train.hide.payload import hide_payload
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, timed

BENCH_PASSPHRASE = b"noisenerf bench"


@dataclass(frozen=True, kw_only=True)
class Payload(Measured):
    kdf: ScryptParams  # the default parameters the KDF was timed with


def measure_payload(context: BenchContext) -> Payload:
    """A file of payload_bytes random bytes (what compressed or encrypted data looks like) hidden and
    revealed, plain and sealed, and the KDF's time with its default parameters."""
    config = context.config
    record = Record("file", np.random.default_rng(config.seed).bytes(config.payload_bytes), name=b"payload.bin")
    seal = new_seal()
    _, kdf_seconds = timed(derive_keys, BENCH_PASSPHRASE, seal)
    rows = []
    for sealed in (False, True):
        path = context.work / "payload.bundle"
        report, hide_seconds = timed(hide_payload, context.scene, record, path, HideConfig(view=config.view),
                                     torch.device("cpu"), passphrase=BENCH_PASSPHRASE if sealed else None,
                                     force=True)
        # what `noisenerf-reveal` does with it, without writing: unseal, reveal, open
        opened, reveal_seconds = timed(reveal, context.model, path, BENCH_PASSPHRASE if sealed else None)
        room = report["capacity"]
        rows.append({"sealed": sealed, "payload_bytes": config.payload_bytes,
                     "secret": f"{room['width']}x{room['height']}", "pixels": room["pixels"], "tiles": room["tiles"],
                     "hide_seconds": hide_seconds, "reveal_seconds": reveal_seconds,
                     "bundle_bytes": report["bundle_bytes"], "exact": opened.bytes == record.body,
                     "kdf_seconds": kdf_seconds})
    return Payload(rows, kdf=seal.kdf)


def describe_payload(context: BenchContext, measured: Payload) -> list[str]:
    rows, kdf = measured.rows, measured.kdf
    lines = [f"A file of {context.config.payload_bytes:,} random bytes hidden with `noisenerf hide --file` (plain) "
             f"and sealed (`--passphrase-file`), revealed with the runtime (what `noisenerf-reveal` does, file write "
             f"aside). scrypt with the default parameters (n = 2^{kdf.log2_n}, r = {kdf.r}, p = {kdf.p}, "
             f"{kdf.memory >> 20} MiB) takes **{rows[0]['kdf_seconds']:.2f} s** here; sealed hides and reveals "
             "include it.", "",
             "| payload | secret | pixels | tiles | hide s | reveal s | bundle bytes | byte-exact |", "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {'sealed' if r['sealed'] else 'plain'} | {r['secret']} | {r['pixels']:,} | {r['tiles']} | "
              f"{r['hide_seconds']:.1f} | {r['reveal_seconds']:.1f} | {r['bundle_bytes']:,} | {r['exact']} |" for r in rows]
    lines += ["", "A sealed payload fills its size bucket (whole tiles beyond one tile), so it hides more pixels than "
              "the plain one."]
    return lines
