"""`noisenerf-reveal`: the recipient's command line. Runtime only (numpy + onnxruntime), never torch.

    noisenerf-reveal MODEL.onnx SECRET.bundle -o OUT.png [--json]    reveal a secret, tiles stitched
    noisenerf-reveal MODEL.onnx --view I -o OUT.png [--json]         an ordinary render of dataset view I

OUT's extension picks the format: .png 8-bit (the very pixels the bundle's digest is checked on), .tif
16-bit, .exr float; a reveal refuses JPEG (lossy: the pixels written would not be the ones checked), an
ordinary --view render may be one. `exact` says whether the revealed 8-bit pixels hash to the bundle's
secret digest; an inexact reveal still exits 0 (the image is written), bad input exits 2 with one line on
stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from noisenerf.cli.common import FAILURES, OneLineParser, failure, quiet_warnings
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import json_text

if TYPE_CHECKING:
    from noisenerf.runtime.model import Model

PROG = "noisenerf-reveal"


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("model", help="the .onnx model the secret was hidden in")
    parser.add_argument("bundle", nargs="?", help="the secret .bundle to reveal")
    parser.add_argument("--view", type=int, help="render dataset view I instead of revealing a bundle")
    parser.add_argument("-o", "--output", required=True, help="image to write (.png, .tif or .exr)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--no-skip", action="store_true",
                        help="with --view: no empty-space skipping or early termination inside the scene's box "
                             "(comparison; models with a fine network render hierarchically and never skip)")
    parser.add_argument("--threads", type=int, help="onnxruntime threads (default and most: the cores there are)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")
    return parser


def progress_bar(total: int):
    """Rays done, on stderr, shown only on a terminal."""
    from tqdm import tqdm

    return tqdm(total=total, unit="ray", unit_scale=True, file=sys.stderr, disable=None, leave=False)


def reveal_secret(model: Model, bundle_path: str) -> tuple[np.ndarray, dict]:
    """Render and stitch a bundle's tiles -> float image (h, w, 3), report."""
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.model import check_bundle
    from noisenerf.runtime.reveal import reveal

    bundle = load_bundle(bundle_path)
    check_bundle(model, bundle)
    rays = sum(tile.rect[2] * tile.rect[3] for tile in bundle.tiles)
    with progress_bar(rays) as bar:
        revealed = reveal(bundle, model.render_config, model.fields(), progress=bar)
    return revealed.image, {"exact": revealed.exact, "width": bundle.width, "height": bundle.height,
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


def run(args: argparse.Namespace) -> dict:
    """Everything but argument parsing and printing; bad input raises UserError before any output."""
    from noisenerf.runtime.images import write_image
    from noisenerf.runtime.model import load_model

    start = time.perf_counter()
    output = checked_output(args.output, args.force, reveal=args.bundle is not None)
    model = load_model(args.model, device=args.device, threads=args.threads)
    loaded = time.perf_counter()
    if args.bundle is not None:
        image, report = reveal_secret(model, args.bundle)
    else:
        image, report = render_dataset_view(model, args.view, skip=not args.no_skip)
    rendered = time.perf_counter()
    write_image(output, image)
    done = time.perf_counter()
    timings = {"load": loaded - start, "render": rendered - loaded, "write": done - rendered}
    return {**report, "output": str(output), "seconds": round(done - start, 3),
            "timings": {name: round(seconds, 3) for name, seconds in timings.items()}}


def summary_lines(report: dict) -> list[str]:
    size = f"{report['width']}x{report['height']}"
    seconds = f"{report['seconds']} s (render {report['timings']['render']} s)"
    if "exact" in report:
        return [f"exact: {json.dumps(report['exact'])}",
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
        with quiet_warnings():
            report = run(args)
    except FAILURES as error:
        return failure(PROG, error)
    print(json_text(report) if args.json else "\n".join(summary_lines(report)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
