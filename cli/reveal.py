"""`noisenerf-reveal`: the recipient's command line. Runtime only (numpy + onnxruntime), never torch.

    noisenerf-reveal MODEL.onnx SECRET.bundle -o OUT.png [--json]    reveal a secret, tiles stitched
    noisenerf-reveal MODEL.onnx X.bundle -o OUT [--passphrase-file F] reveal a payload: OUT gets its bytes
    noisenerf-reveal MODEL.onnx --view I -o OUT.png [--json]         an ordinary render of dataset view I

OUT's extension picks the format: .png 8-bit, .tif 16-bit, .exr float. A reveal writes the very 8-bit
pixels the bundle's digest is checked on, in a .tif or .exr scaled exactly (v·257, v/255), so `exact`
describes the file written (--json's `written` says how it holds them); it refuses JPEG (lossy: the pixels
written would not be the ones checked). An ordinary --view render writes its float render, and may be a
JPEG. `exact` says whether the revealed 8-bit pixels hash to the bundle's secret digest; an inexact reveal
still exits 0 (the image is written), bad input exits 2 with one line on stderr.

A payload bundle (`noisenerf hide --file`, or sealed) is all or nothing: OUT is written, whatever its
extension, with exactly the payload's bytes (a sealed image, known only once opened, is written as an
image by OUT's extension), or nothing is written and the reveal exits 2: when the revealed pixels do not
reproduce the payload's SHA-256, and for a sealed bundle without a passphrase, with a wrong one, or with
any byte of the bundle or model changed. The payload's original file name is reported, never used as a
path. The passphrase comes from --passphrase-file, NOISENERF_PASSPHRASE or a hidden prompt, never from
the command line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from noisenerf.cli.common import (FAILURES, OneLineParser, failure, passphrase_given, payload_line, quiet_warnings,
                                  read_passphrase)
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import json_text

if TYPE_CHECKING:
    from noisenerf.runtime.bundle import Bundle
    from noisenerf.runtime.model import Model
    from noisenerf.runtime.reveal import Revealed
    from noisenerf.runtime.sealing import Keys

PROG = "noisenerf-reveal"
# how a revealed image's file holds its 8-bit values, by the pixel type written (runtime.images.encoded)
WRITTEN_AS = {"uint8": "8-bit values", "uint16": "8-bit values scaled exactly to 16 bits (v*257)",
              "float": "8-bit values as floats (v/255)"}


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("model", help="the .onnx model the secret was hidden in")
    parser.add_argument("bundle", nargs="?", help="the secret .bundle to reveal")
    parser.add_argument("--view", type=int, help="render dataset view I instead of revealing a bundle")
    parser.add_argument("-o", "--output", required=True,
                        help="image to write (.png, .tif or .exr); for a payload bundle, the file to write")
    parser.add_argument("--passphrase-file", help="a sealed bundle's passphrase, in this file (else "
                        "NOISENERF_PASSPHRASE, else a hidden prompt)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--no-skip", action="store_true",
                        help="with --view: no empty-space skipping or early termination inside the scene's box "
                             "(comparison; models with a fine network render hierarchically and never skip)")
    parser.add_argument("--threads", type=int, help="onnxruntime threads (default and most: the cores there are)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")
    parser.add_argument("--verbose", action="store_true", help="let onnxruntime's own warnings and errors through "
                                                                  "to stderr (off: our one line is the only one)")
    return parser


def progress_bar(total: int):
    """Rays done, on stderr, shown only on a terminal."""
    from tqdm import tqdm

    return tqdm(total=total, unit="ray", unit_scale=True, file=sys.stderr, disable=None, leave=False)


def reveal_secret(model: Model, bundle: Bundle) -> tuple[Revealed, dict]:
    """Render and stitch a bundle's tiles -> the revealed 8-bit image, report."""
    from noisenerf.runtime.model import check_bundle
    from noisenerf.runtime.reveal import reveal

    check_bundle(model, bundle)
    rays = sum(tile.rect[2] * tile.rect[3] for tile in bundle.tiles)
    with progress_bar(rays) as bar:
        revealed = reveal(bundle, model.render_config, model.fields(), progress=bar)
    return revealed, {"exact": revealed.exact, "width": bundle.width, "height": bundle.height,
                            "tiles": len(bundle.tiles), "rays": rays,
                            "samples": sum(tile.rect[2] * tile.rect[3] * tile.sampling.n_samples
                                           for tile in bundle.tiles)}


def render_dataset_view(model: Model, view: int, skip: bool) -> tuple[np.ndarray, dict]:
    """An ordinary render of one of the model's cameras -> float image (h, w, 3), report. A model with a
    fine network renders hierarchically, as nerf-pytorch does, and never skips (see render_rays)."""
    from noisenerf.runtime.render import render_view

    camera = model.camera(view)
    hierarchical = model.coarse is not None
    with progress_bar(camera.width * camera.height) as bar:
        grid = model.grid if skip else model.grid.box_only()
        image, stats = render_view(camera, model.render_config, model.field, grid, early_stop=None if skip else 0.0,
                                   progress=bar, coarse=model.coarse)
    return image, {"view": view, "width": camera.width, "height": camera.height,
                   "skip": skip and not hierarchical, "hierarchical": hierarchical,
                   "rays": stats.n_rays, "samples": stats.n_samples_evaluated,
                   "samples_dense": stats.n_samples_dense}


def checked_output(path: str, force: bool, reveal: bool) -> Path:
    """Refuse an output path before any rendering: missing or unwritable folder, existing file (or anything
    not a regular file), unknown format, and for a reveal a lossy one (the exactness claim is made on the
    8-bit pixels, so they must be the pixels written; an ordinary --view render may be a JPEG)."""
    from noisenerf.runtime.files import check_output_path, refuse_lossy
    from noisenerf.runtime.images import WRITE_FORMATS

    output = check_output_path(path, force=force)
    if (output.suffix.lower() or ".png") not in WRITE_FORMATS:
        raise UserError(f"unknown image extension {output.suffix!r} for {output}; use one of "
                        f"{', '.join(WRITE_FORMATS)}")
    if reveal:
        refuse_lossy(output)
    return output


def unseal(bundle: Bundle, bundle_path: str, passphrase_file: str | None) -> Keys | None:
    """A sealed bundle's keys, its tag checked before anything is rendered; None for an unsealed one. A
    passphrase given for a bundle that is not sealed is refused: a sealed bundle stripped of its seal reads
    exactly so, and revealing it would pass its ciphertext off as the secret."""
    from noisenerf.runtime.payload import seal_of
    from noisenerf.runtime.sealing import NOT_SEALED, unseal_keys

    seal = None if bundle.payload is None else seal_of(bundle.payload)
    if seal is None:
        if passphrase_given(passphrase_file):
            raise UserError(NOT_SEALED)
        return None
    passphrase = read_passphrase(passphrase_file)
    if passphrase is None:
        raise UserError("the bundle is sealed: give its passphrase with --passphrase-file F, NOISENERF_PASSPHRASE, "
                        "or at the prompt (stdin a terminal)")
    return unseal_keys(Path(bundle_path), seal, passphrase)


def write_payload(args: argparse.Namespace, revealed: Revealed, bundle: Bundle, model: Model,
                  keys: Keys | None) -> dict:
    """Open the payload in the revealed pixels and write it to OUT (a file's bytes; a sealed image by
    OUT's extension); nothing is written unless every byte checks. -> the payload's report."""
    from noisenerf.runtime.files import write_bytes
    from noisenerf.runtime.images import write_image
    from noisenerf.runtime.payload import INEXACT, open_payload

    if not revealed.exact:
        raise UserError(INEXACT)
    record = open_payload(revealed.pixels, bundle.payload, model.fingerprint, keys)
    if record.kind == "image":
        write_image(checked_output(args.output, args.force, reveal=True), record.pixels(), replace=args.force)
    else:
        write_bytes(args.output, record.body, replace=args.force)
    return record.report()


def run(args: argparse.Namespace) -> dict:
    """Everything but argument parsing and printing; bad input raises UserError before any output."""
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.files import check_output_path
    from noisenerf.runtime.images import write_image, written_format
    from noisenerf.runtime.model import load_model

    start = time.perf_counter()
    bundle = load_bundle(args.bundle) if args.bundle is not None else None
    payload = bundle is not None and bundle.payload is not None
    output = (check_output_path(args.output, force=args.force) if payload
              else checked_output(args.output, args.force, reveal=bundle is not None))
    keys = unseal(bundle, args.bundle, args.passphrase_file) if bundle is not None else None
    model = load_model(args.model, device=args.device, threads=args.threads)
    loaded = time.perf_counter()
    if bundle is not None:
        revealed, report = reveal_secret(model, bundle)
        image = revealed.pixels  # the very pixels `exact` judged, in every format
        if not payload:
            report["written"] = WRITTEN_AS[written_format(output)[1]]
    else:
        image, report = render_dataset_view(model, args.view, skip=not args.no_skip)
    rendered = time.perf_counter()
    if payload:
        report = {**report, "sealed": keys is not None,
                  "payload": write_payload(args, revealed, bundle, model, keys)}
    else:
        write_image(output, image, replace=args.force)
    done = time.perf_counter()
    timings = {"load": loaded - start, "render": rendered - loaded, "write": done - rendered}
    return {**report, "output": str(output), "seconds": round(done - start, 3),
            "timings": {name: round(seconds, 3) for name, seconds in timings.items()}}


def summary_lines(report: dict) -> list[str]:
    size = f"{report['width']}x{report['height']}"
    seconds = f"{report['seconds']} s (render {report['timings']['render']} s)"
    if "exact" in report:
        return [f"exact: {json.dumps(report['exact'])}",
                *([payload_line(report["payload"], report["sealed"])] if "payload" in report else []),
                f"revealed {size} from {report['tiles']} tiles: {report['rays']} rays, "
                f"{report['samples']} samples in {seconds} -> {report['output']}"]
    return [f"view {report['view']} {size}: {report['rays']} rays, {report['samples']} of "
            f"{report['samples_dense']} samples evaluated in {seconds} -> {report['output']}"]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if (args.bundle is None) == (args.view is None):
        parser.error("give either SECRET.bundle or --view I")
    if args.no_skip and args.view is None:
        parser.error("--no-skip applies to --view renders only (a reveal never skips)")
    try:
        from noisenerf.runtime.session import onnxruntime_logging

        onnxruntime_logging(args.verbose)
        with quiet_warnings():
            report = run(args)
    except FAILURES as error:
        return failure(PROG, error)
    except KeyboardInterrupt:  # at the passphrase prompt, or during a long reveal: nothing was written
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    print(json_text(report) if args.json else "\n".join(summary_lines(report)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
