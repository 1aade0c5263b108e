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
from typing import TYPE_CHECKING

from noisenerf.cli.common import (FAILURES, OneLineParser, TerminalProgress, failure, passphrase_given, payload_line,
                                  quiet_warnings, read_passphrase)
from noisenerf.runtime.files import json_text

if TYPE_CHECKING:
    from noisenerf.runtime.api import RevealResult

PROG = "noisenerf-reveal"


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


def reveal_report(result: RevealResult) -> dict:
    """--json's object for a reveal, but for where it was written."""
    report = {"exact": result.exact, "width": result.secret_size[0], "height": result.secret_size[1],
              "tiles": result.tiles, "rays": result.rays, "samples": result.samples}
    if result.payload:
        report.update(sealed=result.sealed, payload=result.payload_report())
    return report


def run(args: argparse.Namespace) -> dict:
    """Everything but argument parsing and printing; bad input raises UserError before any output. The output
    is checked before any work, so a bad one costs nothing."""
    from noisenerf.runtime import api
    from noisenerf.runtime.files import check_output_path

    start = time.perf_counter()
    if args.view is not None:
        check_output_path(args.output, force=args.force)
        with TerminalProgress() as bar:
            result = api.render(args.model, args.view, skip=not args.no_skip, device=args.device,
                                threads=args.threads, progress=bar)
        rendered = time.perf_counter()
        result.save(args.output, force=args.force)
        report = {"view": result.view, "width": result.image.shape[1], "height": result.image.shape[0],
                  "skip": result.skip, "hierarchical": result.hierarchical, "rays": result.rays,
                  "samples": result.samples, "samples_dense": result.samples_dense}
    else:
        read = api.read_bundle(args.bundle)
        if read.payload_marker is None:  # an image: its format is known now (a sealed image's once decrypted)
            api.checked_image_output(args.output, args.force)
        else:
            check_output_path(args.output, force=args.force)
        ask = read.sealed or passphrase_given(args.passphrase_file)
        passphrase = read_passphrase(args.passphrase_file) if ask else None
        with TerminalProgress() as bar:
            result = api.reveal(args.model, read, passphrase, device=args.device, threads=args.threads,
                                progress=bar)
        rendered = time.perf_counter()
        report = {**reveal_report(result), **result.save(args.output, force=args.force)}
    done = time.perf_counter()
    timings = {**result.timings, "write": done - rendered}
    return {**report, "output": str(args.output), "seconds": round(done - start, 3),
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
