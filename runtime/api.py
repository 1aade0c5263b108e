"""The recipient's library: `noisenerf.reveal` and `noisenerf.render`, what `noisenerf-reveal` does, in a call.

    result = noisenerf.reveal("model.onnx", "secret.bundle", passphrase=None)
    result.kind, result.exact, result.sha256, result.pixels (an image) or result.bytes, result.name (a file)
    result.save("out.png")                      # as noisenerf-reveal -o writes it
    view = noisenerf.render("model.onnx", view=3)   # an ordinary render: view.image (float), view.pixels

The reveal's order of steps lives here (the CLI parses, calls, prints; web/src/index.js `reveal` is the same
API in JavaScript): the bundle is read and checked, a sealed one's tag checked under the passphrase before
anything renders, then the model (graph and fingerprint), the bundle against the model, every tile; a
payload is opened from the revealed pixels. Every refusal is one UserError whose message is the CLI's line.
Models and bundles are paths or their bytes. Progress, where wanted, is a callback taking runtime.progress's
`ProgressEvent(stage, done, total, unit, detail)`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
import numpy as np

from noisenerf.runtime.bundle import Bundle, BundleFile, bundle_bytes, read_bundle_file, secret_digest
from noisenerf.runtime.arguments import (checked_callback, checked_int, checked_path, checked_source, checked_text,
                                         optional, wrong)
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import check_output_path, refuse_lossy, write_bytes
from noisenerf.runtime.images import to_uint8, write_image, written_format
from noisenerf.runtime.model import Model, check_bundle, check_fingerprint, load_model
from noisenerf.runtime.payload import INEXACT, open_payload, seal_of
from noisenerf.runtime.progress import Counter, ProgressFn
from noisenerf.runtime.sealing import NOT_SEALED, Keys, unseal_keys

Source = str | os.PathLike | bytes
NO_PASSPHRASE = ("the bundle is sealed: give its passphrase with --passphrase-file F, NOISENERF_PASSPHRASE, "
                 "or at the prompt (stdin a terminal)")
# how a revealed image's file holds its 8-bit values, by the pixel type written (runtime.images.encoded)
WRITTEN_AS = {"uint8": "8-bit values", "uint16": "8-bit values scaled exactly to 16 bits (v*257)",
              "float": "8-bit values as floats (v/255)"}


@dataclass(frozen=True)
class ReadBundle:
    """A bundle as read: its file (runtime.bundle.BundleFile), the bytes a sealed one's tag is checked on, and an
    unmasked one's checked contents (a masked one's are checked once its model is open: `opened`)."""

    file: BundleFile
    data: bytes
    checked: Bundle | None

    @property
    def payload_marker(self) -> dict | None:
        return self.file.payload_marker

    @property
    def sealed(self) -> bool:
        return self.payload_marker is not None and seal_of(self.payload_marker) is not None

    def opened(self, model: Model) -> Bundle:
        """The bundle's contents, checked against `model`; a masked bundle's unmasked with it, once the model is
        the one it names (another's would unmask to junk)."""
        if self.checked is None:
            check_fingerprint(model, self.file.model_fingerprint)
        bundle = self.checked or self.file.bundle(model.mask_secret)
        check_bundle(model, bundle)
        return bundle


def read_bundle(bundle: Source | ReadBundle) -> ReadBundle:
    """A bundle (a path, or its bytes) read once and checked (runtime.bundle), all of it unless it is masked."""
    if isinstance(bundle, ReadBundle):
        return bundle
    data, name = bundle_bytes(checked_source(bundle, "bundle"))
    file = read_bundle_file(data, name)
    return ReadBundle(file, data, None if file.mask_salt is not None else file.bundle())


@dataclass(frozen=True)
class RevealResult:
    """A revealed secret: an image (kind "image": its 8-bit `pixels`) or a file (kind "file": its `bytes` and
    original `name`, which is never used as a path). `exact`: the 8-bit pixels hash to the bundle's digest (a
    payload is refused unless they do); `sha256`: of the pixels' bytes (an image) or of the file's bytes."""

    kind: str
    exact: bool
    sha256: str
    width: int  # of the image; for a file, of the secret it travelled in
    height: int
    secret_size: tuple[int, int] = (0, 0)  # (width, height) of the secret the bundle hides (a payload's record)
    pixels: np.ndarray | None = None  # (height, width, 3) uint8, kind "image"
    bytes: bytes | None = None  # kind "file"
    name: str | None = None  # a payload's original file name, if it had one
    sealed: bool = False
    payload: bool = False  # whether it travelled as a payload record (a file, or a sealed image)
    tiles: int = 0
    rays: int = 0
    samples: int = 0
    timings: dict[str, float] = field(default_factory=dict)  # seconds: load, render

    def payload_report(self) -> dict:
        """What --json says of a payload: kind, size, digest, name (and an image's size)."""
        size = len(self.bytes) if self.kind == "file" else self.pixels.nbytes
        return {"kind": self.kind, "bytes": size, "sha256": self.sha256, "name": self.name,
                **({"width": self.width, "height": self.height} if self.kind == "image" else {})}

    def save(self, path: str | os.PathLike, force: bool = False) -> dict:
        """Write it as `noisenerf-reveal -o PATH` does: a file's bytes whatever the extension; an image as
        PATH's extension says (.png 8-bit, .tif 16-bit, .exr float, the 8-bit values scaled exactly so that
        `exact` describes the file; lossy formats refused). Atomic; an existing file only with force.
        -> how the file holds the values ({"written": ...} for an image, else {})."""
        path = checked_path(path, "path")
        if self.kind == "file":
            write_bytes(path, self.bytes, replace=force)
            return {}
        output = checked_image_output(path, force)
        write_image(output, self.pixels, replace=force)
        return {"written": WRITTEN_AS[written_format(output)[1]]}


@dataclass(frozen=True)
class RenderResult:
    """An ordinary (noise-free) render of one of the model's cameras."""

    view: int
    image: np.ndarray  # (height, width, 3) float32 in [0, 1]
    skip: bool  # whether empty space was skipped (never for a model with a fine network: hierarchical)
    hierarchical: bool
    rays: int
    samples: int  # evaluated
    samples_dense: int  # what a render without skipping evaluates
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def pixels(self) -> np.ndarray:
        """(height, width, 3) uint8, round half up."""
        return to_uint8(self.image)

    def save(self, path: str | os.PathLike, force: bool = False) -> None:
        """Write the render by PATH's extension (.png, .jpg, .tif, .exr), atomically."""
        output = check_output_path(checked_path(path, "path"), force=force)
        write_image(output, self.image, replace=force)


def checked_image_output(path: str | os.PathLike, force: bool):
    """A revealed image's output, refused before any work: a missing or unwritable folder, an existing file
    without force (or anything not a regular file), an unknown format, a lossy one (`exact` is judged on the
    8-bit pixels, so they must be the pixels written)."""
    output = check_output_path(path, force=force)
    written_format(output)  # refuses an unknown extension
    refuse_lossy(output)
    return output


def passphrase_bytes(passphrase: str | bytes | None) -> bytes | None:
    if passphrase is None or isinstance(passphrase, bytes):
        return passphrase
    if isinstance(passphrase, str):
        return passphrase.encode()
    raise wrong("passphrase", "a str or bytes", passphrase)


def unseal(read: ReadBundle, passphrase: bytes | None) -> Keys | None:
    """A sealed bundle's keys, its tag checked before anything is rendered; None for an unsealed one. A
    passphrase given for a bundle that is not sealed is refused: a sealed bundle stripped of its seal reads
    exactly so, and revealing it would pass its ciphertext off as the secret."""
    if not read.sealed:
        if passphrase is not None:
            raise UserError(NOT_SEALED, code="seal.not_sealed")
        return None
    if passphrase is None:
        raise UserError(NO_PASSPHRASE, code="seal.no_passphrase")
    return unseal_keys(read.data, seal_of(read.payload_marker), passphrase)


def open_model(model: Source | Model, device: str, threads: int | None) -> Model:
    if isinstance(model, Model):
        return model
    return load_model(checked_source(model, "model"), device=checked_text(device, "device"),
                      threads=optional(checked_int, threads, "threads"))


def reveal(model: Source | Model, bundle: Source | ReadBundle, passphrase: str | bytes | None = None, *, device: str = "cpu",
           threads: int | None = None, progress: ProgressFn | None = None) -> RevealResult:
    """Reveal the secret `bundle` holds in `model` (paths, or their bytes; a loaded Model or read bundle is reused).
    passphrase: a sealed bundle's (refused for one that is not sealed). An image comes back whether exact or
    not (see `exact`); a payload only when every byte checks, else a UserError."""
    from noisenerf.runtime.reveal import reveal_tiles

    start = time.perf_counter()
    progress = optional(checked_callback, progress, "progress")
    read = read_bundle(bundle)
    keys = unseal(read, passphrase_bytes(passphrase))
    model = open_model(model, device, threads)
    bundle = read.opened(model)
    loaded = time.perf_counter()
    rays = Counter(progress, "render", bundle.width * bundle.height, "ray")
    revealed = reveal_tiles(bundle, model.render_config, model.fields(), progress=rays)
    counts = {"secret_size": (bundle.width, bundle.height), "tiles": len(bundle.tiles),
              "rays": bundle.width * bundle.height,
              "samples": sum(t.rect[2] * t.rect[3] * t.sampling.n_samples for t in bundle.tiles),
              "timings": {"load": loaded - start, "render": time.perf_counter() - loaded}}
    if bundle.payload_marker is None:
        return RevealResult("image", revealed.exact, secret_digest(revealed.pixels), bundle.width, bundle.height,
                            pixels=revealed.pixels, **counts)
    if not revealed.exact:
        raise UserError(INEXACT, code="payload.inexact")
    record = open_payload(revealed.pixels, bundle.payload_marker, model.fingerprint, keys)
    common = {"exact": True, "sha256": record.sha256, "name": record.name.decode("utf-8", "replace") or None,
              "sealed": keys is not None, "payload": True, **counts}
    if record.kind == "image":
        return RevealResult("image", width=record.width, height=record.height, pixels=record.pixels(), **common)
    return RevealResult("file", width=bundle.width, height=bundle.height, bytes=record.body, **common)


def render(model: Source | Model, view: int, *, skip: bool = True, device: str = "cpu", threads: int | None = None,
           progress: ProgressFn | None = None) -> RenderResult:
    """An ordinary render of dataset camera `view` of `model`. skip: empty-space skipping and early termination
    (off: every sample inside the scene's box). A model with a fine network renders hierarchically, as
    nerf-pytorch does, and never skips; an imported nerfacto scene renders as nerfstudio does at eval
    (runtime.proposal) and never skips."""
    from noisenerf.runtime.render import render_view

    start = time.perf_counter()
    view, progress = checked_int(view, "view"), optional(checked_callback, progress, "progress")
    model = open_model(model, device, threads)
    camera = model.camera(view)
    loaded = time.perf_counter()
    sampler = model.sampler(skip)
    image, stats = render_view(camera, model.render_config, model.field, sampler,
                               progress=Counter(progress, "render", camera.width * camera.height, "ray"))
    return RenderResult(view, image, sampler.skips, sampler.hierarchical, stats.n_rays,
                        stats.n_samples_evaluated, stats.n_samples_dense,
                        {"load": loaded - start, "render": time.perf_counter() - loaded})
