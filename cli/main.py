"""`noisenerf`: the sender's command line (fit, import, hide, export, demo, bench).

Every subcommand imports its machinery lazily, so `--help` is instant and a missing torch is one clear
line. Bad input is one line on stderr and exit code 2; `--json` prints one JSON object on stdout.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from noisenerf.api import resolve_device
from noisenerf.cli.common import (FAILURES, OneLineParser, TerminalProgress, failure, payload_line, quiet_warnings,
                                  read_passphrase)
from noisenerf.runtime.layouts import LAYOUTS
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import json_text
from noisenerf.train.hide.methods import METHODS
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.tiling import DEFAULT_TILE_SIZE
from noisenerf.train.scene.presets import DEFAULT_PRESETS, PRESET_KINDS

PROG = "noisenerf"


def size_argument(text: str, flag: str) -> tuple[int, int]:
    """WIDTHxHEIGHT (e.g. 4032x3024), each 1 to 5 digits."""
    match = re.fullmatch(r"([1-9][0-9]{0,4})x([1-9][0-9]{0,4})", text)
    if match is None:
        raise UserError(f"{flag} takes WIDTHxHEIGHT, e.g. 4032x3024; got {text!r:.40}")
    return int(match[1]), int(match[2])


def view_argument(text: str) -> int:
    """--paper-scene's VIEW: a camera index, 0 to 99999."""
    if re.fullmatch(r"[0-9]{1,5}", text) is None:
        raise UserError(f"--paper-scene takes a scene directory and a camera index; got view {text!r:.40}")
    return int(text)


def fields_presets(text: str) -> tuple[str, ...]:
    """--fields-presets: fit presets by name, comma-separated, each known and named once."""
    names = tuple(text.split(","))
    unknown = [name for name in names if name not in PRESET_KINDS]
    if unknown or not names or len(set(names)) != len(names):
        raise UserError(f"--fields-presets takes distinct presets from {', '.join(PRESET_KINDS)}, comma-separated; "
                        f"got {text!r:.60}")
    return names


def emit(report: dict, as_json: bool, lines: list[str]) -> None:
    """The result: one JSON object on stdout with --json, else readable lines."""
    if as_json:
        print(json_text(report))
    else:
        print("\n".join(lines))


def cmd_fit(args) -> None:
    from noisenerf import api

    with TerminalProgress(quiet=args.quiet) as bar:
        report = api.fit(args.data_dir, args.output, field=args.field, preset=args.preset, resolution=args.resolution,
                         minutes=args.minutes, iters=args.iters, seed=args.seed, skip=not args.no_skip,
                         appearance=args.appearance, all_test_views=args.all_test_views,
                         device=args.device, progress=bar)
    test, skipped = report["test"], report["skipped_frames"]
    left = test["held_out"] - test["views"]
    emit(report, args.json, [f"scene: {report['scene']}", f"steps: {report['steps']} in {report['seconds']} s",
                             f"test PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f} over {test['views']} of "
                             f"{test['held_out']} held-out views" + (f" ({left} more would have taken the closing "
                                                                     "renders past a tenth of the training time: "
                                                                     "--all-test-views)" if left else "")]
         + ([f"left out {len(skipped)} frames whose images are missing ({', '.join(skipped[:3])}"
             f"{', …' if len(skipped) > 3 else ''})"] if skipped else []))


def cmd_import(args) -> None:
    from noisenerf.train.scene.import_nerf_pytorch import import_nerf_pytorch

    scene = import_nerf_pytorch(Path(args.checkpoint), Path(args.config), Path(args.output),
                                data_dir=Path(args.data_dir) if args.data_dir else None, force=args.force)
    emit({"scene": args.output, "fingerprint": scene.fingerprint()}, args.json,
         [f"scene: {args.output}", f"fingerprint: {scene.fingerprint()}"])


def cmd_import_nerfstudio(args) -> None:
    from noisenerf import api

    report = api.import_nerfstudio(args.run_dir, args.output, data=args.data, force=args.force)
    emit(report, args.json, [f"scene: {args.output} ({report['method']}, {report['implementation']} implementation, "
                             f"{report['cameras']} cameras in nerfstudio's frame order)",
                             f"fingerprint: {report['fingerprint']}"])


def cmd_import_ingp(args) -> None:
    from noisenerf import api

    report = api.import_ingp(args.snapshot, args.output, data=args.data, force=args.force)
    emit(report, args.json, [f"scene: {args.output} (hashgrid: {report['levels']} levels x {report['features']} "
                             f"features, 2^{report['log2_table']} entries; {report['cameras']} cameras)",
                             f"fingerprint: {report['fingerprint']}"])


def cmd_hide(args) -> None:
    from noisenerf import api

    passphrase = sealing_passphrase(args)
    device = api.resolve_device(args.device)
    # every method's settings as the flags say (the bundle records those of the method that runs)
    settings = tuple(s for method in METHODS.values() for s in method.from_arguments(args, device.type))
    with TerminalProgress(quiet=args.quiet) as bar:
        report = api.hide(args.scene_dir, args.secret, args.output, file=args.file, passphrase=passphrase,
                          method=args.method, layout=args.layout, dtype=args.dtype, samples=args.samples,
                          tile_size=args.tile_size, view=args.view, seed=args.seed, settings=settings,
                          workers=args.workers, executor=args.executor, ray_address=args.ray_address,
                          device=args.device, force=args.force, allow_inexact=args.allow_inexact, progress=bar,
                          announce=None if args.quiet else announce_capacity(args.tile_size),
                          warn=lambda line: print(f"{PROG}: warning: {line}", file=sys.stderr),
                          verbose=args.verbose)
    report.pop("warnings", None)  # said on stderr
    if METHODS[args.method].exact and not report["exact"]:
        off = [f"tile {k}: {t['inexact_pixels']} px off by up to {t['max_error']}"
               for k, t in enumerate(report["tiles"]) if t["inexact_pixels"]]
        print(f"{PROG}: warning: the bundle is not exact (--allow-inexact): {'; '.join(off)}", file=sys.stderr)
    margin = f" (every value {report['margin_levels']:.3f} levels or more inside its bin)" if report["exact"] else ""
    lines = [f"bundle: {report['bundle']} ({report['bundle_bytes']} bytes, {report['bytes_per_pixel']:.1f} B/px)",
             f"tiles: {len(report['tiles'])}, exact fraction {report['exact_fraction']:.6f}, "
             f"exact: {str(report['exact']).lower()}{margin}", f"seconds: {report['seconds']}"]
    if "payload" in report:
        lines.insert(1, payload_line(report["payload"], report["sealed"]))
    emit(report, args.json, lines)


def sealing_passphrase(args) -> bytes | None:
    """The passphrase a sealed hide uses (--seal or --passphrase-file asks for sealing), else None."""
    if not (args.seal or args.passphrase_file is not None):
        return None
    passphrase = read_passphrase(args.passphrase_file, confirm=True)
    if passphrase is None:
        raise UserError("--seal needs a passphrase: --passphrase-file F, NOISENERF_PASSPHRASE, or a terminal to "
                        "prompt on")
    return passphrase


def announce_capacity(tile_size: int):
    """A payload's size and the time to expect, on stderr before its hide starts."""
    def announce(room: dict) -> None:
        print(f"{PROG}: {room['kind']} payload of {room['bytes']} bytes -> {room['width']}x{room['height']} secret "
              f"({room['pixels']} px, {room['tiles']} tiles of at most {tile_size} px); expect about "
              f"{room['expected_seconds']} s of hiding on 2 CPU cores", file=sys.stderr, flush=True)
    return announce


def cmd_export(args) -> None:
    from noisenerf import api

    report = api.export_model(args.scene_dir, args.output, force=args.force)
    emit(report, args.json, [f"model: {args.output}", *(f"{k}: {v}" for k, v in report.items())])


def cmd_demo(args) -> None:
    from noisenerf.cli.demo import run_demo

    with TerminalProgress(quiet=args.quiet) as bar:
        report = run_demo(Path(args.output), resolve_device(args.device), progress=bar)
    emit(report, args.json, report["summary"])


def cmd_bench(args) -> None:
    from noisenerf.cli.bench import BenchConfig, run_bench

    if args.payload_bytes < 0:
        raise UserError("--payload-bytes must be 0 or more")
    if args.paper_changes_secrets is not None and args.paper_changes_secrets < 1:
        raise UserError("--paper-changes-secrets must be at least 1")
    config = BenchConfig(scene=args.scene, secret=args.secret, data=args.data, photos=tuple(args.photos),
                         view=args.view, small_width=args.small_width, twok_rows=args.twok_rows,
                         paper_width=args.paper_width, paper_iters=args.paper_iters,
                         paper_scenes=tuple((folder, view_argument(view)) for folder, view in args.paper_scene),
                         paper_secrets=tuple(args.paper_secrets),
                         paper_changes_secrets=args.paper_changes_secrets, speed_width=args.speed_width, payload_bytes=args.payload_bytes,
                         browser_size=args.browser_size, cluster_size=args.cluster_size,
                         cluster_tile=args.cluster_tile, cluster_photo=size_argument(args.cluster_photo, "--cluster-photo"),
                         big_secret=size_argument(args.big_secret, "--big-secret"),
                         fields_minutes=args.fields_minutes, fields_resolution=args.fields_resolution,
                         fields_presets=fields_presets(args.fields_presets),
                         nerfstudio_run=args.nerfstudio_run, nerfstudio_data=args.nerfstudio_data,
                         nerfstudio_golden=args.nerfstudio_golden, ingp_snapshot=args.ingp_snapshot,
                         device=str(resolve_device(args.device)),
                         experiments=tuple(args.only.split(",")) if args.only else None)
    command = "noisenerf " + " ".join(sys.argv[1:]) if sys.argv[0].endswith("noisenerf") else "noisenerf bench ..."
    sections = run_bench(config, Path(args.output), args.stress, command,
                         progress=lambda line: print(line, file=sys.stderr, flush=True))
    emit({"report": str(Path(args.output) / "BENCHMARKS.md"), "sections": {s.name: s.rows for s in sections}},
         args.json, [f"report: {Path(args.output) / 'BENCHMARKS.md'}"])


def cmd_make_dataset(args) -> None:
    from noisenerf.train.scene.procedural import write_procedural_dataset

    path = write_procedural_dataset(Path(args.output), size=args.size, seed=args.seed)
    emit({"dataset": str(path)}, args.json, [f"dataset: {path}"])


def device_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU), cpu, or cuda")


def fit_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data_dir")
    p.add_argument("-o", "--output", required=True, help="scene directory to write (resumes if it holds a checkpoint)")
    p.add_argument("--field", choices=tuple(DEFAULT_PRESETS),
                   help="field kind: hashgrid (Instant-NGP's hash grid, NeRF-Synthetic's default), nerfacto (nerfstudio's, "
                        "the default for LLFF and captures) or mlp (the standard NeRF MLP, preset small)")
    p.add_argument("--preset", choices=tuple(PRESET_KINDS),
                   help="small or paper (mlp kind), hashgrid, nerfacto or nerfacto-big (default: the field kind's)")
    p.add_argument("--resolution", type=int, help="image width in pixels (default: the dataset's)")
    p.add_argument("--minutes", type=float, help="training wall-time budget (progress-curve renders excluded)")
    p.add_argument("--iters", type=int, help="step budget (deterministic for a seed on CPU)")
    p.add_argument("--seed", type=int)
    p.add_argument("--no-skip", action="store_true", help="no occupancy grid or early termination (comparison)")
    p.add_argument("--appearance", action="store_true",
                   help="nerfacto: learn a per-image appearance embedding (photos whose exposure differs), its mean "
                        "folded into the saved field")
    p.add_argument("--all-test-views", action="store_true",
                   help="render every held-out view for the closing test PSNR (default: as many as a tenth of the "
                        "training time allows, the first always)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    device_argument(p)


def import_nerf_pytorch_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint")
    p.add_argument("--config", required=True, help="the nerf-pytorch config .txt the checkpoint was trained with")
    p.add_argument("--data-dir", help="dataset folder (default: the config's datadir)")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--force", action="store_true", help="replace an earlier scene in the output folder")


def import_nerfstudio_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", help="outputs/<experiment>/<method>/<timestamp>: config.yml, dataparser_transforms.json, "
                                   "nerfstudio_models/")
    p.add_argument("--data", help="the dataset folder holding transforms.json (default: the run's recorded path)")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--force", action="store_true", help="replace an earlier scene in the output folder")


def import_ingp_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("snapshot", help="an Instant-NGP NeRF snapshot: .ingp (compressed) or .msgpack")
    p.add_argument("--data", help="the capture folder holding transforms.json (default: the snapshot's cameras)")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--force", action="store_true", help="replace an earlier scene in the output folder")


def hide_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene_dir")
    p.add_argument("secret", nargs="?", help="PNG/JPEG/TIFF/EXR; RGBA is composited over white")
    p.add_argument("--file", help="hide this file's bytes instead of an image (revealed byte for byte)")
    p.add_argument("--seal", action="store_true",
                   help="encrypt under a passphrase from NOISENERF_PASSPHRASE or a hidden prompt")
    p.add_argument("--passphrase-file", help="seal with the passphrase in this file (implies --seal)")
    p.add_argument("-o", "--output", required=True, help="the bundle file to write")
    p.add_argument("--view", type=int, default=0, help="scene camera of the first tile")
    p.add_argument("--tile-size", type=int, default=DEFAULT_TILE_SIZE, help="secrets larger than this are cut into tiles")
    # choices and defaults from the torch-free methods and settings (train/hide/methods.py, settings.py), so that
    # --help is instant; each method turns these flags into its settings (Method.from_arguments)
    p.add_argument("--method", choices=tuple(METHODS), default=HideConfig.method)
    p.add_argument("--layout", choices=tuple(LAYOUTS), help="; ".join(
        f"{name} method: {' or '.join(method.layouts)} (default {method.layouts[0]})" for name, method in METHODS.items()))
    p.add_argument("--dtype", choices=tuple(dict.fromkeys(d for layout in LAYOUTS.values() for d in layout.dtypes)),
                   help="; ".join(f"{name}: {' or '.join(layout.dtypes)} (default {layout.dtypes[0]})"
                                  for name, layout in LAYOUTS.items()))
    p.add_argument("--samples", type=int, help="samples per ray of the secret view (" + ", ".join(
        f"{name}: {method.default_samples}" for name, method in METHODS.items()) + ")")
    for method in METHODS.values():  # each method's own flags
        method.add_arguments(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, help="exact method on a CPU: processes its parts are spread over "
                   "(default: every core this process may use; the bundle is the same for any number)")
    p.add_argument("--executor", choices=("local", "ray"), default="local",  # executors.EXECUTORS (torch-free here)
                   help="where the jobs run: local (this machine's processes) or ray (a Ray cluster; the bundle "
                        "is the same; needs pip install 'noisenerf[cluster]')")
    p.add_argument("--ray-address", help="the Ray cluster to use (default: RAY_ADDRESS, else a local cluster "
                   "started for the hide)")
    p.add_argument("--force", action="store_true", help="overwrite an existing bundle")
    p.add_argument("--allow-inexact", action="store_true",
                   help="exact method: write the bundle even if some pixels are off (says so on stderr); by "
                        "default such a hide exits 3 and writes none")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verbose", action="store_true", help="--executor ray: let Ray's own log lines through to stderr "
                                                          "(off: our lines are the only ones)")
    device_argument(p)


def export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene_dir")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--force", action="store_true", help="overwrite an existing model file")


def demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="noisenerf-demo", help="folder for the demo's files")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    device_argument(p)


def bench_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene directory (the README's Benchmarks section fits it)")
    p.add_argument("--secret", required=True, help="the secret image most experiments hide")
    p.add_argument("--data", help="dataset whose test views the skipping experiment renders and the fields one fits")
    p.add_argument("--photos", nargs="*", default=[], help="secrets hidden at native size (photos experiment)")
    p.add_argument("--view", type=int, default=0, help="scene camera the secrets are hidden at")
    p.add_argument("--small-width", type=int, default=48, help="secret width for the paper-mode curves on a CPU")
    p.add_argument("--paper-width", type=int, help="paper-quality secret width (default: 400 on CUDA, --small-width on CPU)")
    p.add_argument("--speed-width", type=int, default=64,
                   help="paper_speed: the width of the square secrets hidden with and without skipping")
    p.add_argument("--paper-iters", type=int, default=300, help="paper-mode iterations (the paper's 300)")
    p.add_argument("--paper-scene", nargs=2, action="append", default=[], metavar=("SCENE", "VIEW"),
                   help="paper_quality, paper_changes: a scene and the view its secrets are hidden at (repeat it; "
                        "default: --scene at --view)")
    p.add_argument("--paper-secrets", nargs="*", default=[],
                   help="paper_quality, paper_changes: the photos hidden (default: the first three --photos)")
    p.add_argument("--paper-changes-secrets", type=int, metavar="N",
                   help="paper_changes: switch each change off on the first N of those photos only (default: all)")
    p.add_argument("--twok-rows", type=int, default=1, help="tile rows of the 2048² secret actually hidden (1-4)")
    p.add_argument("--payload-bytes", type=int, default=1 << 20, help="size of the payload experiment's file")
    p.add_argument("--browser-size", type=int, default=2048, help="side of the browser experiment's tiled secret")
    p.add_argument("--cluster-size", type=int, default=512, help="side of the cluster experiment's multi-tile secret")
    p.add_argument("--cluster-tile", type=int, default=128, help="its tile size")
    p.add_argument("--cluster-photo", default="4032x3024", help="WxH of the photo the cluster experiment hides through Ray")
    p.add_argument("--big-secret", default="7680x4320", help="WxH of the secret the big_secret experiment hides and reveals")
    p.add_argument("--fields-minutes", type=float, default=15.0, help="fields: each field kind's fit, in minutes")
    p.add_argument("--fields-resolution", type=int, default=200, help="fields: the width the kinds are fitted at")
    p.add_argument("--fields-presets", default="small,hashgrid,nerfacto",
                   help="fields: the fit presets compared, comma-separated")
    p.add_argument("--nerfstudio-run", help="nerfstudio: a nerfacto or instant-ngp run directory to import")
    p.add_argument("--nerfstudio-data", help="nerfstudio: its dataset folder (transforms.json)")
    p.add_argument("--nerfstudio-golden", help="nerfstudio: tools/nerfstudio_goldens.py's folder for that run")
    p.add_argument("--ingp-snapshot", help="ingp: an Instant-NGP NeRF snapshot (.ingp, .msgpack) to import")
    p.add_argument("--only", help="comma-separated experiments, run with those they need (default: all)")
    device_argument(p)
    p.add_argument("--stress", action="store_true", help="also run the full numerical stress suite")
    p.add_argument("-o", "--output", default="bench", help="folder for BENCHMARKS.md, CSVs and plots")


def make_dataset_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)


COMMANDS = (  # (command, handler, help, its arguments)
    ("fit", cmd_fit, "fit a NeRF to a NeRF-Synthetic, LLFF or capture (transforms.json) dataset",
     fit_arguments),
    ("import-nerf-pytorch", cmd_import, "convert a nerf-pytorch checkpoint into a scene directory",
     import_nerf_pytorch_arguments),
    ("import-nerfstudio", cmd_import_nerfstudio, "convert a nerfstudio nerfacto or instant-ngp run directory into a scene directory",
     import_nerfstudio_arguments),
    ("import-ingp", cmd_import_ingp, "convert an Instant-NGP NeRF snapshot (.ingp, .msgpack) into a scene directory",
     import_ingp_arguments),
    ("hide", cmd_hide, "hide a secret image (or any file) in a scene; writes the secret bundle",
     hide_arguments),
    ("export", cmd_export, "export a scene's frozen field as one ONNX file with a noise input",
     export_arguments),
    ("demo", cmd_demo, "hide, export and reveal on the embedded demo scene and a generated secret",
     demo_arguments),
    ("bench", cmd_bench, "measure everything BENCHMARKS.md reports; writes it with CSVs and plots",
     bench_arguments),
    ("make-dataset", cmd_make_dataset, "write the procedural NeRF-Synthetic-format dataset",
     make_dataset_arguments),
)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog=PROG, description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, handler, help_text, add_arguments in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(handler=handler)
        p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with quiet_warnings():
            args.handler(args)
    except FAILURES as error:
        return failure(PROG, error)
    except ModuleNotFoundError as error:
        if error.name not in ("torch", "onnx"):
            raise
        print(f"{PROG}: error: '{args.command}' needs {error.name}: pip install 'noisenerf[train]'", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted (progress so far is checkpointed; run again to resume)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
