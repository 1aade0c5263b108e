"""Hostile input: crafted bundles, models, images, paths, partial folders and concurrent runs.

A refusal is always checked the same way (`assert_refused`): exit code 2, exactly one line on stderr, no
traceback, nothing on stdout, and no output file left behind. The allocation cases run the CLI in a
subprocess and bound its peak memory (its own ru_maxrss, from os.wait4). Everything else calls the CLIs'
`main` in-process on inputs built once per session from the tiny scene, model and bundle of `reveal_inputs`.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper
from safetensors.numpy import save_file
from safetensors.torch import load_file as load_torch_file
from safetensors.torch import save_file as save_torch_file

from helpers import Result, assert_refused, bundle_contents, hidden_bundle, rewrite_bundle, run_main, turning_llff
from noisenerf.cli.bench.reliability import stated, streamed, zeros_as_stated
from noisenerf.cli.main import main as noisenerf_main
from noisenerf.cli.reveal import main as reveal_main
from noisenerf.runtime.bundle import METADATA_KEY
from noisenerf.runtime.images import write_image
from noisenerf.runtime.model import METADATA_KEY as MODEL_KEY
from noisenerf.train.hide import exact_solver, resume as resume_module
from noisenerf.train.scene.procedural import write_procedural_dataset

PEAK_MB = 400  # what an allocation case may cost at most, interpreter and libraries included


@dataclass(frozen=True)
class World:
    """Inputs every case starts from: a scene, its model, a valid bundle, a secret and a finished hide."""

    directory: Path
    scene: Path
    model: Path
    bundle: Path
    secret: Path
    hidden: bytes  # the bundle `noisenerf hide` writes for `secret`
    partial: Path  # the parts that run saved, kept


def hide_args(world: World, output: Path, *extra) -> list:
    """`noisenerf hide` of the session's secret into `output`, in 16 px tiles."""
    return ["hide", world.scene, world.secret, "-o", output, "--tile-size", 16, "--quiet", *extra]


@pytest.fixture(scope="session")
def world(reveal_inputs, tmp_path_factory) -> World:
    """Built once: the reveal inputs, an 8x24 secret (tiles of 16x8 and 8x8 px), and one hide of it whose partial
    folder is kept (ResumeStore.clear disabled) for the resume cases."""
    inputs, model, bundle = reveal_inputs
    directory = tmp_path_factory.mktemp("hostile")
    secret = directory / "secret.png"
    write_image(secret, np.random.default_rng(7).integers(0, 256, (8, 24, 3), dtype=np.uint8))
    incomplete = World(directory, inputs / "scene", model, bundle, secret, b"", directory / "kept.bundle.partial")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(resume_module.ResumeStore, "clear", lambda self: None)
        assert noisenerf_main([str(a) for a in hide_args(incomplete, directory / "kept.bundle")]) == 0
    return World(**{**incomplete.__dict__, "hidden": (directory / "kept.bundle").read_bytes()})


# ---- crafted bundles ------------------------------------------------------------------------------

def tile(n: int):
    """A path item picking tile n of a bundle's metadata."""
    return lambda meta: meta["tiles"][n]


def walk(meta, path):
    """The object at `path` in metadata; a callable path item picks a sub-object (see `tile`)."""
    for key in path:
        meta = key(meta) if callable(key) else meta[key]
    return meta


def setter(path, value):
    """A bundle edit setting the item at `path` to `value` (any JSON, NaN and Infinity included)."""
    return lambda meta, tensors: walk(meta, path[:-1]).__setitem__(path[-1], value)


def drop(path):
    """A bundle edit removing the item at `path`."""
    return lambda meta, tensors: walk(meta, path[:-1]).pop(path[-1])


def tensor_edit(function):
    """A bundle edit replacing the first tile's noise with function(noise)."""
    return lambda meta, tensors: tensors.__setitem__("tile_0000", function(tensors["tile_0000"]))


INF, NAN = float("inf"), float("nan")
CAMERA = (tile(0), "camera")
SAMPLING = (tile(0), "sampling")
BUNDLES = {  # case: (edit(meta, tensors), message)
    "width Infinity": (setter(("secret", "width"), INF), "must be an integer"),
    "width 1e300": (setter(("secret", "width"), 1e300), "must be an integer"),
    "width 2.5": (setter(("secret", "width"), 2.5), "must be an integer"),
    "width 32.0": (setter(("secret", "width"), 32.0), "must be an integer"),
    "width true": (setter(("secret", "width"), True), "must be an integer"),
    "width string": (setter(("secret", "width"), "32"), "must be an integer"),
    "width 10**30": (setter(("secret", "width"), 10 ** 30), "between 1 and"),
    "width 0": (setter(("secret", "width"), 0), "between 1 and"),
    "height -5": (setter(("secret", "height"), -5), "between 1 and"),
    "areas do not add up": (setter(("secret", "height"), 13), "do not add up"),
    "rect 16.9": (setter((tile(1), "rect", 2), 16.9), "must be an integer"),
    "rect origin 2.5": (setter((tile(1), "rect", 0), 2.5), "must be an integer"),
    "rect origin negative": (setter((tile(1), "rect", 0), -16), "between 0 and"),
    "rect three numbers": (setter((tile(1), "rect"), [16, 0, 16]), "must hold 4 items"),
    "rect a string": (setter((tile(1), "rect"), "16,0,16,12"), "must be a list"),
    "rect outside": (setter((tile(1), "rect", 0), 24), "outside"),
    "rects overlap": (setter((tile(1), "rect", 0), 8), "overlap"),
    "rect size not camera size": (setter((tile(1), "rect", 3), 11), "camera is"),
    "n_samples 20000": (setter((*SAMPLING, "n_samples"), 20000), "between 1 and 1024"),
    "ray layout n_samples 300": (setter((*SAMPLING, "n_samples"), 300), "at most 256"),
    "n_samples 2.5": (setter((*SAMPLING, "n_samples"), 2.5), "must be an integer"),
    "n_samples Infinity": (setter((*SAMPLING, "n_samples"), INF), "must be an integer"),
    "n_samples 0": (setter((*SAMPLING, "n_samples"), 0), "between 1 and"),
    "n_samples true": (setter((*SAMPLING, "n_samples"), True), "must be an integer"),
    "sampling extra key": (setter((*SAMPLING, "chunk"), 7), "near, far and n_samples"),
    "near NaN": (setter((*SAMPLING, "near"), NAN), "finite"),
    "far below near": (setter((*SAMPLING, "far"), 1.0), "near < far"),
    "sampling missing": (drop(SAMPLING), "near, far and n_samples"),
    "camera width Infinity": (setter((*CAMERA, "width"), INF), "must be an integer"),
    "camera width 1e300": (setter((*CAMERA, "width"), 1e300), "must be an integer"),
    "camera 100000 wide": (setter((*CAMERA, "width"), 100000), "between 1 and"),
    "camera fx 0": (setter((*CAMERA, "fx"), 0), "camera fx"),
    "camera fx NaN": (setter((*CAMERA, "fx"), NAN), "camera fx"),
    "camera cx Infinity": (setter((*CAMERA, "cx"), INF), "camera cx"),
    "camera c2w strings": (setter((*CAMERA, "c2w"), [["a"] * 4] * 4), "c2w"),
    "camera c2w 2x2": (setter((*CAMERA, "c2w"), [[1, 0], [0, 1]]), "c2w"),
    "camera c2w ragged": (setter((*CAMERA, "c2w"), [[1, 0, 0], [0, 1]]), "malformed camera"),
    "camera not an object": (setter(CAMERA, 3), "malformed camera"),
    "view 2.5": (setter((tile(0), "view"), 2.5), "must be an integer"),
    "network unknown": (setter((tile(0), "network"), "medium"), "names network"),
    "network a number": (setter((tile(0), "network"), 5), "network must be a string"),
    "network fine on a one-network model": (setter((tile(0), "network"), "fine"), "needs the fine network"),
    "noise dims 2.5": (setter(("noise", "dims"), 2.5), "must be an integer"),
    "noise dims 10**9": (setter(("noise", "dims"), 10 ** 9), "between 1 and"),
    "noise dims 91": (setter(("noise", "dims"), 91), "noise is"),
    "unknown layout": (setter(("noise", "layout"), "banana"), "unknown noise layout"),
    "unknown dtype": (setter(("noise", "dtype"), "bfloat16"), "unknown noise dtype"),
    "float64 tensor": (tensor_edit(lambda t: t.astype(np.float64)), "F64"),
    "int32 tensor": (tensor_edit(lambda t: t.astype(np.int32)), "noise is int32"),
    "int64 tensor": (tensor_edit(lambda t: t.astype(np.int64)), "I64"),
    "wrong noise shape": (tensor_edit(lambda t: t[:, :, :-1].copy()), "noise is"),
    "NaN noise": (tensor_edit(lambda t: np.where(t > 1, np.nan, t).astype(np.float32)), "NaN"),
    "Infinity noise": (tensor_edit(lambda t: np.where(t > 1, np.inf, t).astype(np.float32)), "NaN or Inf"),
    "tensor missing": (setter((tile(0), "tensor"), "tile_9999"), "is missing"),
    "tensor name a number": (setter((tile(0), "tensor"), 5), "is missing"),
    "no tiles": (setter(("tiles",), []), "empty secret"),
    "tiles an object": (setter(("tiles",), {"a": 1}), "must be a list"),
    "tile a number": (setter(("tiles", 0), 7), "must be a JSON object"),
    "format version 6": (setter(("format_version",), 6), "a newer noisenerf is needed"),
    "format version 0": (setter(("format_version",), 0), "reads formats 1 to 5"),
    "fingerprint a number": (setter(("model_fingerprint",), 12), "must be a string"),
    "another model": (setter(("model_fingerprint",), "f" * 64), "bundle was made for model"),
    "secret missing": (drop(("secret",)), "'secret' and 'noise'"),
    "JSON 40 deep": (setter(("extra",), json.loads("[" * 40 + "]" * 40)), "nested deeper than"),
}


@pytest.mark.parametrize("case", list(BUNDLES))
def test_crafted_bundle_is_refused(world, tmp_path, capfd, case):
    edit, message = BUNDLES[case]
    bad = rewrite_bundle(world.bundle, tmp_path / "bad.bundle", edit, world.model)  # edited unmasked, masked again
    out = tmp_path / "out.png"
    assert_refused(run_main(reveal_main, [world.model, bad, "-o", out], capfd), out, message)


def bf16_bundle(path: Path, source: Path) -> None:
    """The valid bundle with its noise stored as bfloat16 (numpy has no such type)."""
    meta, tensors = bundle_contents(source)
    tensors = {name: torch.from_numpy(noise).to(torch.bfloat16) for name, noise in tensors.items()}
    save_torch_file(tensors, str(path), metadata={METADATA_KEY: json.dumps(meta)})


def raw_metadata_bundle(text: str):
    """A writer of a bundle whose metadata is exactly `text` (beyond what json.dumps could produce)."""
    return lambda path, source: save_file({"tile_0000": np.zeros(1, np.float32)}, str(path),
                                          metadata={METADATA_KEY: text})


FILES = {  # case: (write(path, valid bundle), message)
    "BF16 tensor": (bf16_bundle, "BF16"),
    "JSON 100000 deep": (raw_metadata_bundle("[" * 100_000 + "]" * 100_000), "nested deeper than"),
    "metadata not JSON": (raw_metadata_bundle("{tiles: [}"), "not valid JSON"),
    "metadata a list": (raw_metadata_bundle("[1, 2]"), "must be a JSON object"),
    "no noisenerf metadata": (lambda path, source: save_file({"x": np.zeros(1, np.float32)}, str(path)),
                              "not a noisenerf bundle"),
    "truncated": (lambda path, source: path.write_bytes(source.read_bytes()[:300]), "not a readable"),
    "random bytes": (lambda path, source: path.write_bytes(np.random.default_rng(0).bytes(5000)), "not a readable"),
    "header length 2**64-1": (lambda path, source: path.write_bytes(b"\xff" * 8 + b"{}"), "not a readable"),
    "empty file": (lambda path, source: path.write_bytes(b""), "not a readable"),
    "a directory": (lambda path, source: path.mkdir(), "bundle not found"),
    "a FIFO": (lambda path, source: os.mkfifo(path), "bundle not found"),
}


@pytest.mark.parametrize("case", list(FILES))
def test_broken_bundle_file_is_refused(world, tmp_path, capfd, case):
    write, message = FILES[case]
    write(tmp_path / "bad.bundle", world.bundle)
    out = tmp_path / "out.png"
    assert_refused(run_main(reveal_main, [world.model, tmp_path / "bad.bundle", "-o", out], capfd), out, message)


# ---- crafted models -------------------------------------------------------------------------------

def metadata_edit(function):
    """An edit of a model's noisenerf JSON metadata (as parsed data)."""
    def edit(props: dict) -> None:
        data = json.loads(props[MODEL_KEY])
        function(data)
        props[MODEL_KEY] = json.dumps(data)
    return edit


def meta_set(*path_and_value):
    """A model edit setting the metadata item at path to value: meta_set("grid", "resolution", 2.5)."""
    *path, value = path_and_value
    return metadata_edit(lambda data: setter(tuple(path), value)(data, None))


def write_model(path: Path, source: Path, edit_props=None, graph: onnx.ModelProto | None = None) -> Path:
    """The source model (or another graph, given the source's weights as unused initializers so it passes the
    fingerprint check and meets the port checks) with the source's metadata_props, edited."""
    model = onnx.load(str(source))
    props = {p.key: p.value for p in model.metadata_props}
    if edit_props is not None:
        edit_props(props)
    target = model
    if graph is not None:
        target = onnx.ModelProto()
        target.CopyFrom(graph)
        target.graph.initializer.extend(model.graph.initializer)
    del target.metadata_props[:]
    helper.set_model_props(target, props)
    onnx.save_model(target, str(path))
    return path


NDC = {"tan_half_fov_x": 0.4, "tan_half_fov_y": 0.3, "near_plane": 1.0}
MODELS = {  # case: (edit(props), message)
    "background NaN": (meta_set("render", "background", 0, NAN), "background"),
    "background Infinity": (meta_set("render", "background", 1, INF), "background"),
    "background 5": (meta_set("render", "background", 2, 5.0), "background"),
    "background two values": (meta_set("render", "background", [1.0, 1.0]), "must hold 3 items"),
    "render n_samples 2.5": (meta_set("render", "sampling", "n_samples", 2.5), "must be an integer"),
    "render n_samples 10**6": (meta_set("render", "sampling", "n_samples", 10 ** 6), "between 1 and 1024"),
    "pixel_center NaN": (meta_set("render", "pixel_center", NAN), "pixel_center"),
    "ndc near plane 0": (meta_set("render", "ndc", {**NDC, "near_plane": 0}), "ndc near_plane"),
    "ndc fov NaN": (meta_set("render", "ndc", {**NDC, "tan_half_fov_x": NAN}), "ndc tan_half_fov_x"),
    "camera width Infinity": (meta_set("cameras", 0, "width", INF), "must be an integer"),
    "camera 100000 square": (metadata_edit(lambda d: d["cameras"][0].update(width=100000, height=100000)),
                             "between 1 and"),
    "camera 16384x8192": (metadata_edit(lambda d: d["cameras"][0].update(width=16384, height=8192)),
                          "more than the"),
    "cameras an object": (meta_set("cameras", {"0": 1}), "must be a list"),
    "grid resolution Infinity": (meta_set("grid", "resolution", INF), "must be an integer"),
    "grid resolution 10**6": (meta_set("grid", "resolution", 10 ** 6), "between 1 and 512"),
    "grid resolution 2.5": (meta_set("grid", "resolution", 2.5), "must be an integer"),
    "grid bits too short": (meta_set("grid", "occupancy", "AAAA"), "occupancy holds"),
    "grid bits not base64": (meta_set("grid", "occupancy", "!!!!"), "malformed"),
    "grid aabb NaN": (meta_set("grid", "aabb", 0, NAN), "grid aabb"),
    "grid aabb inverted": (meta_set("grid", "aabb", [1, 1, 1, -1, -1, -1]), "min < max"),
    "noise_dims 2.5": (meta_set("noise_dims", 2.5), "must be an integer"),
    "noise_dims not the graph's": (meta_set("noise_dims", 91), "expected [('points', ('n', 3)), ('viewdirs', ('n', 3)), ('noise', ('n', 91))]"),
    "format version 1": (lambda props: props.update(noisenerf_format_version="1"), "model format version"),
    "metadata not JSON": (lambda props: props.update({MODEL_KEY: "{"}), "not valid JSON"),
    "metadata 100000 deep": (lambda props: props.update({MODEL_KEY: "[" * 100_000 + "]" * 100_000}),
                             "nested deeper than"),
    "no metadata": (lambda props: props.clear(), "not a noisenerf model"),
}


@pytest.mark.parametrize("case", list(MODELS))
def test_crafted_model_metadata_is_refused(world, tmp_path, capfd, case):
    edit, message = MODELS[case]
    model = write_model(tmp_path / "bad.onnx", world.model, edit)
    out = tmp_path / "out.png"
    assert_refused(run_main(reveal_main, [model, world.bundle, "-o", out], capfd), out, message)


def toy_graph(rgb_shape=("n", 3), batch="n", sigma_shape=("n",), rgb_source="points") -> onnx.ModelProto:
    """A stand-in field: rgb = `rgb_source` (points, or points and viewdirs side by side), sigma = mean noise."""
    inputs = [helper.make_tensor_value_info(name, TensorProto.FLOAT, [batch, width])
              for name, width in (("points", 3), ("viewdirs", 3), ("noise", 90))]
    nodes = [helper.make_node("Concat", ["points", "viewdirs"], ["both"], axis=1),
             helper.make_node("Identity", [rgb_source], ["rgb"]),
             helper.make_node("ReduceMean", ["noise"], ["sigma"], axes=[1], keepdims=0)]
    outputs = [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, list(rgb_shape)),
               helper.make_tensor_value_info("sigma", TensorProto.FLOAT, list(sigma_shape))]
    graph = helper.make_graph(nodes, "toy", inputs, outputs)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)


GRAPHS = {  # case: (graph, message): each is refused by runtime/graph.check_graph before any session
    "rgb declared (n, 6)": (toy_graph(rgb_shape=("n", 6), rgb_source="both"), "its outputs are"),
    "a fixed batch of 7": (toy_graph(batch=7, rgb_shape=(7, 3), sigma_shape=(7,)), "its inputs are"),
    "sigma declared (n, 1)": (toy_graph(sigma_shape=("n", 1)), "its outputs are"),
    "rgb (n, 6) declared (n, 3)": (toy_graph(rgb_source="both"), "the model's graph is not the one its scene exports"),
    "no noise input": (helper.make_model(helper.make_graph(
        [helper.make_node("Identity", ["points"], ["rgb"]), helper.make_node("Identity", ["points"], ["sigma"])],
        "toy", [helper.make_tensor_value_info("points", TensorProto.FLOAT, ["n", 3])],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["n", 3]) for n in ("rgb", "sigma")]),
        opset_imports=[helper.make_opsetid("", 13)], ir_version=8), "its inputs are"),
}


@pytest.mark.parametrize("case", list(GRAPHS))
def test_model_with_wrong_ports_is_refused(world, tmp_path, capfd, case):
    graph, message = GRAPHS[case]
    model = write_model(tmp_path / "bad.onnx", world.model, graph=graph)
    out = tmp_path / "out.png"
    assert_refused(run_main(reveal_main, [model, "--view", 0, "-o", out], capfd), out, message)


MODEL_FILES = {
    "truncated": (lambda path, source: path.write_bytes(source.read_bytes()[:500]), "not a loadable ONNX"),
    "random bytes": (lambda path, source: path.write_bytes(np.random.default_rng(1).bytes(4000)), "not a loadable"),
    "a directory": (lambda path, source: path.mkdir(), "model not found"),
    "missing": (lambda path, source: None, "model not found"),
}


@pytest.mark.parametrize("case", list(MODEL_FILES))
def test_broken_model_file_is_refused(world, tmp_path, capfd, case):
    write, message = MODEL_FILES[case]
    write(tmp_path / "bad.onnx", world.model)
    out = tmp_path / "out.png"
    assert_refused(run_main(reveal_main, [tmp_path / "bad.onnx", world.bundle, "-o", out], capfd), out, message)


# ---- junk files: refused for their first bytes, whatever their size -------------------------------

JUNK_BYTES = 64 << 20
READ_AT_MOST = 64 << 10  # bytes of a junk file a refusal may read
JUNK = {  # (role, content): (the refusal's code, the message's words)
    ("model", "zeros"): ("onnx.malformed", "not a loadable ONNX model"),
    ("model", "random"): ("onnx.malformed", "not a loadable ONNX model"),
    ("bundle", "zeros"): ("bundle.not_safetensors", "not a readable safetensors bundle"),
    ("bundle", "random"): ("bundle.not_safetensors", "not a readable safetensors bundle"),
}


@pytest.fixture(scope="module")
def junk_files(tmp_path_factory) -> dict[str, Path]:
    """64 MiB of zeros (a sparse file) and 64 MiB of random bytes."""
    folder = tmp_path_factory.mktemp("junk")
    files = {"zeros": folder / "zeros.bin", "random": folder / "random.bin"}
    with files["zeros"].open("wb") as out:
        out.truncate(JUNK_BYTES)
    files["random"].write_bytes(np.random.default_rng(11).bytes(JUNK_BYTES))
    return files


def count_reads(monkeypatch, watched: Path) -> list[int]:
    """Count the bytes read from `watched` through Path.open and Path.read_bytes (how runtime/ reads files) into the
    returned one-item list; a read past READ_AT_MOST fails at once (it would have read the junk file's body)."""
    counted, real_open, real_read_bytes = [0], Path.open, Path.read_bytes

    def spend(count: int) -> None:
        counted[0] += count
        assert counted[0] <= READ_AT_MOST, f"read {counted[0]} bytes of {watched.name} before refusing it"

    class Counting:
        def __init__(self, file):
            self.file = file

        def read(self, *args):
            data = self.file.read(*args)
            spend(len(data))
            return data

        def __getattr__(self, name):
            return getattr(self.file, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

    def open_(self, *args, **kwargs):
        file = real_open(self, *args, **kwargs)
        return Counting(file) if Path(self) == watched else file

    def read_bytes(self):
        if Path(self) == watched:
            spend(self.stat().st_size)
        return real_read_bytes(self)

    monkeypatch.setattr(Path, "open", open_)
    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    return counted


@pytest.mark.parametrize("role, content", list(JUNK))
def test_a_junk_file_is_refused_having_read_its_first_bytes_only(world, junk_files, tmp_path, capfd, monkeypatch,
                                                                  role, content):
    """64 MiB of zeros or random bytes handed as the model or the bundle: refused by the library with the code of its
    framing check and by noisenerf-reveal in one line, each having read at most READ_AT_MOST bytes of it."""
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.errors import UserError
    from noisenerf.runtime.model import load_model

    junk = junk_files[content]
    code, message = JUNK[role, content]
    counted = count_reads(monkeypatch, junk)
    with pytest.raises(UserError) as refused:
        (load_model if role == "model" else load_bundle)(junk)
    assert refused.value.code == code, refused.value
    assert 0 < counted[0] <= READ_AT_MOST
    model, bundle = (junk, world.bundle) if role == "model" else (world.model, junk)
    out = tmp_path / "out.png"
    assert_refused(run_main(reveal_main, [model, bundle, "-o", out], capfd), out, message)
    assert counted[0] <= 2 * READ_AT_MOST


def counted_varints(monkeypatch, most: int) -> list[int]:
    """Count runtime/onnx_file's varint reads into the returned one-item list; more than `most` fails at once."""
    from noisenerf.runtime import onnx_file

    counted, real = [0], onnx_file.read_varint

    def read_varint(data, position):
        counted[0] += 1
        assert counted[0] <= most, f"more than {most} varints read"
        return real(data, position)

    monkeypatch.setattr(onnx_file, "read_varint", read_varint)
    return counted


@pytest.mark.parametrize("content", ["zeros", "empty fields", "empty fields in the graph"])
def test_a_model_of_junk_bytes_is_refused_after_a_bounded_walk(monkeypatch, content):
    """A model's bytes (as the page holds them) are refused for their framing at once (zeros: field number 0), or
    after MAX_MODEL_FIELDS fields of a file made of tiny well-formed ones, wherever they lie: never walked to their
    end. (Random bytes were refused within a few fields already; what they cost was reading them: the test above.)"""
    from noisenerf.runtime.errors import UserError
    from noisenerf.runtime.limits import MAX_MODEL_FIELDS
    from noisenerf.runtime.onnx_file import parse_model, varint

    names = b"\x12\x00" * (JUNK_BYTES // 2)  # empty names, again and again: well formed, and skipped
    data = {"zeros": bytes(JUNK_BYTES), "empty fields": b"\x08\x00" * (JUNK_BYTES // 2),  # ir_version 0, again and again
            "empty fields in the graph": varint(7 << 3 | 2) + varint(len(names)) + names}[content]
    most = 100 if content == "zeros" else 2 * MAX_MODEL_FIELDS + 100  # a key and a value a field
    counted = counted_varints(monkeypatch, most)
    with pytest.raises(UserError) as refused:
        parse_model(data, "junk.onnx")
    assert refused.value.code == "onnx.malformed", refused.value
    assert counted[0] <= most


# ---- allocation: a small file must not dictate a large allocation ---------------------------------

PEAK_WRAPPER = """
import atexit, re, runpy, sys
report, module = sys.argv[1], sys.argv[2]
def write_peak():
    with open('/proc/self/status') as status, open(report, 'w') as out:
        out.write(re.search(r'VmHWM:\\s+(\\d+)', status.read()).group(1))
atexit.register(write_peak)
sys.argv = [module, *sys.argv[3:]]
runpy.run_module(module, run_name='__main__', alter_sys=True)
"""


def peak_run(args: list, cwd: Path) -> tuple[Result, float]:
    """A CLI module in a subprocess: its result and its peak resident memory in MB. The child reports its
    own VmHWM at exit (ru_maxrss would include the forking test process's memory, kept across exec)."""
    if not Path("/proc/self/status").is_file():
        pytest.skip("peak memory is read from /proc/self/status (Linux)")
    result = subprocess.run([sys.executable, "-c", PEAK_WRAPPER, cwd / "peak", *map(str, args)],
                            capture_output=True, text=True, cwd=cwd, timeout=120)
    return Result(result.returncode, result.stdout, result.stderr), int((cwd / "peak").read_text()) / 1024


def big_header_png(path: Path, width: int, height: int) -> None:
    """A PNG whose header claims width x height; its data is one tiny deflate stream."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))


def bundle_case(edit):
    """A reveal of the valid bundle after `edit`."""
    return lambda world, d: ["noisenerf.cli.reveal", world.model,
                             rewrite_bundle(world.bundle, d / "b.bundle", edit, world.model), "-o", d / "out.png"]


def compact_case(edit):
    """A reveal of the session's compact bundle (`noisenerf hide`'s) after `edit`."""
    def command(world, d):
        (d / "hidden.bundle").write_bytes(world.hidden)
        return ["noisenerf.cli.reveal", world.model,
                rewrite_bundle(d / "hidden.bundle", d / "b.bundle", edit, world.model), "-o", d / "out.png"]
    return command


def view_case(edit):
    """An ordinary --view render of the model after `edit` to its metadata."""
    return lambda world, d: ["noisenerf.cli.reveal", write_model(d / "m.onnx", world.model, edit), "--view", 0,
                             "-o", d / "out.png"]


def header_case(world, d):
    """A hide of a secret whose PNG header claims far more pixels than the file holds."""
    big_header_png(d / "huge.png", 20_000, 20_000)  # OpenImageIO itself refuses 100000² at open
    return ["noisenerf.cli.main", "hide", world.scene, d / "huge.png", "-o", d / "out.png", "--quiet"]


def area_claim(meta, tensors):
    """A secret size within the caps that the tiles do not cover: refused before any mask is built."""
    meta["secret"].update(width=4096, height=4096)


ALLOCATIONS = {  # case: (command(world, folder), message)
    "bundle claims 100000x100000": (bundle_case(setter(("secret", "width"), 100_000)), "between 1 and"),
    "bundle claims 4096x4096": (bundle_case(area_claim), "do not add up"),
    "ray n_samples 20000": (bundle_case(setter((*SAMPLING, "n_samples"), 20_000)), "between 1 and"),
    "ray n_samples 1000": (bundle_case(setter((*SAMPLING, "n_samples"), 1000)), "at most 256"),
    "bundle JSON 100000 deep": (lambda world, d: ["noisenerf.cli.reveal", world.model, (
        raw_metadata_bundle("[" * 100_000 + "]" * 100_000)(d / "b.bundle", None), d / "b.bundle")[1],
        "-o", d / "out.png"], "nested deeper"),
    "model n_samples 10**6": (view_case(meta_set("render", "sampling", "n_samples", 10 ** 6)), "between 1 and"),
    "model camera 100000 square": (view_case(MODELS["camera 100000 square"][0]), "between 1 and"),
    "model grid 10**6 cells a side": (view_case(meta_set("grid", "resolution", 10 ** 6)), "between 1 and"),
    "secret PNG claims 20000x20000": (header_case, "header claims"),  # OpenImageIO checks PNG headers
    # decompression bombs (compact, the one layout with compressed streams): stated far beyond what the streams
    # can hold, refused before decoding; a stream expanding past what is stated, refused once it does
    "compact claims 8192x8192": (compact_case(stated(8192, 8192)), "at most 64 times their size"),
    "compact claims 4096x2048": (compact_case(stated(4096, 2048)), "at most 64 times their size"),
    "stream of 256 MiB of zeros": (compact_case(streamed(256 << 20)), "do not hold exactly (8, 16, "),
    "stream of 1 MiB of zeros": (compact_case(streamed(1 << 20)), "do not hold exactly (8, 16, "),
    "2048x2048 of zeros, as stated": (compact_case(zeros_as_stated(2048, 2048)), "at most 64 times their size"),
}


@pytest.mark.parametrize("case", list(ALLOCATIONS))
def test_small_file_cannot_dictate_a_large_allocation(world, tmp_path, case):
    command, message = ALLOCATIONS[case]
    result, peak_mb = peak_run(command(world, tmp_path), tmp_path)
    assert_refused(result, tmp_path / "out.png", message)
    assert peak_mb < PEAK_MB, f"{case}: peak {peak_mb:.0f} MB"
    print(f"{case}: peak {peak_mb:.0f} MB")


def test_a_large_ray_count_reveals_in_bounded_chunks(world, tmp_path):
    """The cap itself costs time, not memory: a ray-layout tile at 256 samples per ray still reveals
    (inexactly) with the reveal's buffers bounded by render.CHUNK_SAMPLES."""
    bad = rewrite_bundle(world.bundle, tmp_path / "b.bundle", setter((*SAMPLING, "n_samples"), 256), world.model)
    result, peak_mb = peak_run(["noisenerf.cli.reveal", world.model, bad, "-o", tmp_path / "out.png"], tmp_path)
    assert result.code == 0 and result.err == "", result
    assert peak_mb < PEAK_MB
    print(f"256 samples per ray: peak {peak_mb:.0f} MB")


# ---- output paths ---------------------------------------------------------------------------------

def symlink_to_file(path: Path) -> None:
    """`path` as a symlink to a file that must survive the refusal untouched."""
    (path.parent / "target.png").write_bytes(b"keep")
    path.symlink_to(path.parent / "target.png")


OUTPUTS = {  # case: (prepare(path), output name, message); every case passes --force
    "a symlink": (symlink_to_file, "out.png", "is a symlink"),
    "a dangling symlink": (lambda p: p.symlink_to(p.parent / "nowhere.png"), "out.png", "is a symlink"),
    "a FIFO": (os.mkfifo, "out.png", "is a FIFO"),
    "a directory": (lambda p: p.mkdir(), "out.png", "is a directory"),
    "a missing folder": (lambda p: None, "missing/out.png", "output folder does not exist"),
    "a 300-byte name": (lambda p: None, "x" * 296 + ".png", "longer than 255"),
    "a lossy .jpg": (lambda p: None, "out.jpg", "lossy"),
    "a lossy .JPEG": (lambda p: None, "out.JPEG", "lossy"),
    "an unknown .webp": (lambda p: None, "out.webp", "unknown image extension"),
}


@pytest.mark.parametrize("case", list(OUTPUTS))
def test_reveal_output_path_is_refused(world, tmp_path, capfd, case):
    prepare, name, message = OUTPUTS[case]
    out = tmp_path / name
    prepare(out)
    before = sorted(os.listdir(tmp_path))
    result = run_main(reveal_main, [world.model, world.bundle, "-o", out, "--force"], capfd)
    assert_refused(result, None, message)
    assert sorted(os.listdir(tmp_path)) == before  # nothing replaced, no temporary left
    if case == "a symlink":
        assert (tmp_path / "target.png").read_bytes() == b"keep"


def test_reveal_into_proc_is_one_line(world, capfd):
    assert_refused(run_main(reveal_main, [world.model, world.bundle, "-o", "/proc/noisenerf.png"], capfd), None,
                   "cannot write to folder /proc")


def test_existing_output_needs_force(world, tmp_path, capfd):
    (tmp_path / "out.png").write_bytes(b"keep")
    assert_refused(run_main(reveal_main, [world.model, world.bundle, "-o", tmp_path / "out.png"], capfd), None,
                   "--force")
    assert (tmp_path / "out.png").read_bytes() == b"keep"


def test_a_245_character_name_is_written(world, tmp_path, capfd):
    out = tmp_path / ("n" * 241 + ".png")
    result = run_main(reveal_main, [world.model, world.bundle, "-o", out], capfd)
    assert result.code == 0 and result.err == "" and out.is_file()
    assert sorted(os.listdir(tmp_path)) == [out.name]


HIDE_OUTPUTS = {  # case: (prepare(path), output name, message); every case passes --force
    "a symlink": (symlink_to_file, "s.bundle", "is a symlink"),
    "a FIFO": (os.mkfifo, "s.bundle", "is a FIFO"),
    "a directory": (lambda p: p.mkdir(), "s.bundle", "is a directory"),
    "a missing folder": (lambda p: None, "missing/s.bundle", "output folder does not exist"),
    "no room for .partial": (lambda p: None, "b" * 250, ".partial: file name too long"),
    "a 300-byte name": (lambda p: None, "b" * 300, "longer than 255"),
    ".partial is a file": (lambda p: p.with_name("s.bundle.partial").write_bytes(b"x"), "s.bundle", "is a file"),
    ".partial is a symlink": (lambda p: p.with_name("s.bundle.partial").symlink_to(p.parent), "s.bundle",
                              "is a symlink"),
}


@pytest.mark.parametrize("case", list(HIDE_OUTPUTS))
def test_hide_output_path_is_refused_before_the_solve(world, tmp_path, capfd, monkeypatch, case):
    prepare, name, message = HIDE_OUTPUTS[case]
    out = tmp_path / name
    prepare(out)
    before = sorted(os.listdir(tmp_path))
    monkeypatch.setattr(exact_solver, "solve_exact", lambda *a, **k: pytest.fail("solved before refusing"))
    assert_refused(run_main(noisenerf_main, hide_args(world, out, "--force", "--workers", 1), capfd), None,
                   message, any_case=True)  # "file name too long" is the system's own wording
    assert sorted(os.listdir(tmp_path)) == before


def test_hide_into_proc_is_refused_before_the_solve(world, capfd, monkeypatch):
    monkeypatch.setattr(exact_solver, "solve_exact", lambda *a, **k: pytest.fail("solved before refusing"))
    assert_refused(run_main(noisenerf_main, hide_args(world, "/proc/s.bundle", "--workers", 1), capfd), None,
                   "/proc")


# ---- secret images and datasets -------------------------------------------------------------------

def truncated_png(path: Path) -> None:
    """A PNG cut after 100 bytes (libpng would print its own complaint)."""
    write_image(path, np.zeros((40, 40, 3), np.uint8) + np.arange(40, dtype=np.uint8)[:, None, None])
    path.write_bytes(path.read_bytes()[:100])


def corrupt_png(path: Path) -> None:
    """A PNG with zeroed bytes where its first data chunk's header is."""
    write_image(path, np.zeros((40, 40, 3), np.uint8))
    data = bytearray(path.read_bytes())
    data[40:60] = bytes(20)
    path.write_bytes(bytes(data))


def float_image(value: float, channels: int = 3):
    """A writer of an 8x8 float image (EXR or TIFF by the path's suffix) with one value set to `value`."""
    def write(path: Path) -> None:
        import OpenImageIO as oiio

        pixels = np.full((8, 8, channels), 0.5, np.float32)
        pixels[2, 3, 0] = value
        output = oiio.ImageOutput.create(str(path))
        output.open(str(path), oiio.ImageSpec(8, 8, channels, "float"))
        output.write_image(pixels)
        output.close()
    return write


SECRETS = {  # case: (file name, write(path), message)
    "truncated PNG": ("s.png", truncated_png, "cannot read image"),
    "corrupt PNG": ("s.png", corrupt_png, "cannot read image"),
    "not an image": ("s.png", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"x" * 100), "cannot read image"),
    "empty file": ("s.png", lambda p: p.write_bytes(b""), "image file is empty"),
    "a directory": ("s.png", lambda p: p.mkdir(), "image not found"),
    "NaN EXR": ("s.exr", float_image(NAN), "NaN"),
    "20-channel TIFF": ("s.tif", float_image(0.5, channels=20), "channels"),
    "5-channel TIFF": ("s.tif", float_image(0.5, channels=5), "5 channels"),
    "20000 px wide": ("s.png", lambda p: write_image(p, np.zeros((1, 20000, 3), np.uint8)), "between 1 and"),
}


@pytest.mark.parametrize("case", list(SECRETS))
def test_hostile_secret_image_is_refused(world, tmp_path, capfd, case):
    name, write, message = SECRETS[case]
    write(tmp_path / name)
    out = tmp_path / "s.bundle"
    args = ["hide", world.scene, tmp_path / name, "-o", out, "--quiet"]
    assert_refused(run_main(noisenerf_main, args, capfd), out, message)
    assert not out.with_name("s.bundle.partial").exists()


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    return write_procedural_dataset(tmp_path_factory.mktemp("fitdata") / "d", size=8, n_train=2, n_val=1, n_test=1)


def nan_frame(dataset: Path, folder: Path) -> Path:
    """The dataset with its first training image replaced by an EXR holding a NaN."""
    copy = folder / "nan"
    shutil.copytree(dataset, copy)
    float_image(NAN, channels=4)(copy / "train" / "nan.exr")
    meta = json.loads((copy / "transforms_train.json").read_text())
    meta["frames"][0]["file_path"] = "./train/nan.exr"
    (copy / "transforms_train.json").write_text(json.dumps(meta))
    return copy


def degenerate_llff(folder: Path) -> Path:
    """An LLFF dataset whose poses have no rotation at all."""
    (folder / "llff").mkdir()
    poses = turning_llff(folder / "llff")
    poses[:, [0, 1, 2, 5, 6, 7, 10, 11, 12]] = 0.0  # every rotation zero
    np.save(folder / "llff" / "poses_bounds.npy", poses)
    return folder / "llff"


FITS = {  # case: (args(dataset, folder), message)
    "NaN image": (lambda d, f: [nan_frame(d, f), "-o", f / "scene"], "NaN"),
    "output is a file": (lambda d, f: [d, "-o", (f / "scene").write_bytes(b"x") and f / "scene"], "is a file"),
    "degenerate LLFF poses": (lambda d, f: [degenerate_llff(f), "-o", f / "scene"], "degenerate poses"),
    "device bogus": (lambda d, f: [d, "-o", f / "scene", "--device", "bogus"], "unknown --device"),
    "zero iterations": (lambda d, f: [d, "-o", f / "scene", "--iters", "0"], "must be positive"),
}


@pytest.mark.parametrize("case", list(FITS))
def test_hostile_fit_input_is_refused_and_leaves_no_folder(tiny_dataset, tmp_path, capfd, case):
    make_args, message = FITS[case]
    args = ["fit", *make_args(tiny_dataset, tmp_path), "--quiet"]
    if "--iters" not in args:
        args += ["--iters", "1"]
    assert_refused(run_main(noisenerf_main, args, capfd), None, message)
    assert not (tmp_path / "scene").is_dir()


def test_scene_with_nan_weights_is_refused_before_the_solve(world, tmp_path, capfd):
    """A fit that diverged: hiding in it used to spend minutes before failing."""
    shutil.copytree(world.scene, tmp_path / "scene")
    weights = load_torch_file(str(tmp_path / "scene" / "weights.safetensors"))
    next(iter(weights.values())).view(-1)[0] = float("nan")
    save_torch_file(weights, str(tmp_path / "scene" / "weights.safetensors"))
    args = ["hide", tmp_path / "scene", world.secret, "-o", tmp_path / "s.bundle", "--quiet"]
    assert_refused(run_main(noisenerf_main, args, capfd), tmp_path / "s.bundle", "NaN or infinite weights")


# ---- arguments ------------------------------------------------------------------------------------

ARGUMENTS = {  # case: (which main, args(world, folder), message)
    "reveal: nothing": (reveal_main, lambda w, d: [], "required"),
    "reveal: threads abc": (reveal_main, lambda w, d: [w.model, w.bundle, "-o", d / "o.png", "--threads", "abc"],
                            "invalid int"),
    "reveal: threads 0": (reveal_main, lambda w, d: [w.model, w.bundle, "-o", d / "o.png", "--threads", 0],
                          "at least 1"),
    "reveal: device bogus": (reveal_main, lambda w, d: [w.model, w.bundle, "-o", d / "o.png", "--device", "tpu"],
                             "invalid choice"),
    "reveal: bundle and view": (reveal_main, lambda w, d: [w.model, w.bundle, "--view", 0, "-o", d / "o.png"],
                                "either"),
    "reveal: no-skip with a bundle": (reveal_main, lambda w, d: [w.model, w.bundle, "--no-skip", "-o", d / "o.png"],
                                      "--view renders only"),
    "reveal: view 99": (reveal_main, lambda w, d: [w.model, "--view", 99, "-o", d / "o.png"], "out of range"),
    "noisenerf: nothing": (noisenerf_main, lambda w, d: [], "required"),
    "noisenerf: unknown command": (noisenerf_main, lambda w, d: ["unhide"], "invalid choice"),
    "hide: tile size abc": (noisenerf_main, lambda w, d: hide_args(w, d / "s.bundle", "--tile-size", "abc"),
                            "invalid int"),
    "hide: device bogus": (noisenerf_main, lambda w, d: hide_args(w, d / "s.bundle", "--device", "bogus"),
                           "unknown --device"),
    "hide: paper iters 0": (noisenerf_main, lambda w, d: hide_args(w, d / "s.bundle", "--method", "paper",
                                                                   "--iters", 0), "must be positive"),
    "hide: samples 10**6": (noisenerf_main, lambda w, d: hide_args(w, d / "s.bundle", "--method", "paper",
                                                                   "--samples", 10 ** 6), "1 to 1024 samples"),
    "hide: ray layout 300 samples": (noisenerf_main, lambda w, d: hide_args(
        w, d / "s.bundle", "--method", "paper", "--layout", "ray", "--samples", 300), "at most 256"),
    "export: output a symlink": (noisenerf_main, lambda w, d: ["export", w.scene, "-o", (d / "m.onnx").symlink_to(
        d / "elsewhere.onnx") or d / "m.onnx"], "is a symlink"),
    "export: unknown flag": (noisenerf_main, lambda w, d: ["export", w.scene, "-o", d / "m.onnx", "--forse"],
                             "unrecognized arguments"),
}


@pytest.mark.parametrize("case", list(ARGUMENTS))
def test_bad_arguments_are_one_line(world, tmp_path, capfd, case):
    main, make_args, message = ARGUMENTS[case]
    assert_refused(run_main(main, make_args(world, tmp_path), capfd), tmp_path / "o.png", message)


def test_numpy_warnings_add_no_line(world, tmp_path, capfd, monkeypatch):
    """Arithmetic on a hostile file may warn on its way to a refusal: only the refusal is printed."""
    import warnings

    from noisenerf.cli import reveal as reveal_module
    from noisenerf.runtime.errors import UserError

    def warn_then_refuse(args):
        np.divide(np.ones(2, np.float32), np.zeros(2, np.float32))
        warnings.warn("overflow somewhere", RuntimeWarning)
        raise UserError("refused")

    monkeypatch.setattr(reveal_module, "run", warn_then_refuse)
    assert_refused(run_main(reveal_main, [world.model, world.bundle, "-o", tmp_path / "o.png"], capfd), None,
                   "refused")
    assert np.geterr()["divide"] == "warn"  # the command's silence did not outlive it


def test_threads_beyond_the_cores_are_capped(world, tmp_path, capfd):
    result = run_main(reveal_main, [world.model, world.bundle, "-o", tmp_path / "o.png", "--threads", 100_000], capfd)
    assert result.code == 0 and result.err == "", result


# ---- resume folders: a bad part is recomputed, never trusted -------------------------------------

def part_files(partial: Path) -> list[Path]:
    """The saved parts of a partial folder, in tile order."""
    return sorted(partial.glob("*.safetensors"))


def restamped(path: Path, key: str, tensors: dict) -> None:
    """Write `tensors` as part `path` with a valid stamp for run `key` (what a careless or hostile writer
    that knows the key could do): only the shape and value checks stand between it and the bundle."""
    tile, part = (int(piece[-4:] if i == 0 else piece[-5:]) for i, piece in enumerate(path.stem.split("_")))
    stamp = resume_module.ResumeStore.stamp(SimpleNamespace(key=key), tile, part, tensors)
    save_torch_file(tensors, str(path), metadata=stamp)


def with_tensors(edit):
    """A corruption that edits the first part's tensors and restamps it with the run's own key."""
    def corrupt(partial: Path) -> None:
        path = part_files(partial)[0]
        tensors = load_torch_file(str(path))
        edit(tensors)
        restamped(path, (partial / "key").read_text(), tensors)
    return corrupt


def first_part(write):
    """A corruption applying write(path, partial) to the first part file."""
    return lambda partial: write(part_files(partial)[0], partial)


def other_runs_part(partial: Path, delete_key: bool = False) -> None:
    """The first part replaced by one another run (another key) stamped properly, as two runs sharing the
    folder used to leave; optionally with the key file gone too."""
    path = part_files(partial)[0]
    tensors = load_torch_file(str(path))
    tensors["noise"] = torch.randn_like(tensors["noise"])
    restamped(path, "0" * 64, tensors)
    if delete_key:
        (partial / "key").unlink()


PARTIALS = {  # case: corrupt(partial folder); the rerun must recompute and write the exact bundle
    "part zeroed, no stamp": first_part(lambda p, _: save_torch_file(
        {k: torch.zeros_like(v) for k, v in load_torch_file(str(p)).items()}, str(p))),
    "part of another run": other_runs_part,
    "part of another run, key deleted": lambda partial: other_runs_part(partial, delete_key=True),
    "part moved to another tile": lambda partial: shutil.copy(part_files(partial)[1], part_files(partial)[0]),
    "part truncated": first_part(lambda p, _: p.write_bytes(p.read_bytes()[:200])),
    "part random bytes": first_part(lambda p, _: p.write_bytes(np.random.default_rng(2).bytes(3000))),
    "part empty": first_part(lambda p, _: p.write_bytes(b"")),
    "part a folder": first_part(lambda p, _: p.unlink() or p.mkdir()),
    "part wrong shape": with_tensors(lambda t: t.update(noise=t["noise"][:-1].clone())),
    "part float64, no stamp": first_part(lambda p, _: save_torch_file(
        {k: v.double() for k, v in load_torch_file(str(p)).items()}, str(p))),
    "part float64, stamped": with_tensors(lambda t: t.update(noise=t["noise"].double())),
    "part counts float32, stamped": with_tensors(lambda t: t.update(counts=t["counts"].float())),
    "part params off the lattice, stamped": with_tensors(lambda t: t["noise"].view(-1).__setitem__(0, 1e-3)),
    "part escaped 7, stamped": with_tensors(lambda t: t["escaped"].view(-1).__setitem__(0, 7)),
    # sound by every check a part can make alone, wrong for its tile: found when the tile renders, solved again
    "part moved along the lattice, stamped": with_tensors(lambda t: t.update(noise=t["noise"] + 37)),
    "part of zeros, stamped": with_tensors(lambda t: t.update(noise=torch.zeros_like(t["noise"]))),
    "part NaN": with_tensors(lambda t: t["noise"].view(-1).__setitem__(5, float("nan"))),
    "part without counts": with_tensors(lambda t: t.pop("counts")),
    "part with an extra field": with_tensors(lambda t: t.update(extra=torch.zeros(3))),
    "key a folder": lambda partial: (partial / "key").unlink() or (partial / "key").mkdir(),
    "key a symlink": lambda partial: (partial / "key").unlink() or (partial / "key").symlink_to("/etc/hostname"),
}


@pytest.mark.parametrize("case", list(PARTIALS))
def test_bad_resume_part_is_recomputed(world, tmp_path, capfd, case):
    out = tmp_path / "s.bundle"
    partial = tmp_path / "s.bundle.partial"
    shutil.copytree(world.partial, partial, symlinks=True)
    PARTIALS[case](partial)
    result = run_main(noisenerf_main, hide_args(world, out, "--json"), capfd)
    assert result.code == 0 and result.err == "", result
    assert json.loads(result.out)["exact"] is True
    assert out.read_bytes() == world.hidden
    assert not partial.exists()


def test_sound_parts_are_reused(world, tmp_path, capfd, monkeypatch):
    shutil.copytree(world.partial, tmp_path / "s.bundle.partial")
    monkeypatch.setattr(exact_solver, "solve_exact", lambda *a, **k: pytest.fail("a sound part was solved again"))
    # patched in this process only: --workers 1
    assert run_main(noisenerf_main, hide_args(world, tmp_path / "s.bundle", "--workers", 1), capfd).code == 0
    assert (tmp_path / "s.bundle").read_bytes() == world.hidden


# ---- one run per output ---------------------------------------------------------------------------

def test_a_held_lock_refuses_a_second_hide_at_once(world, tmp_path, capfd):
    (tmp_path / "s.bundle.partial").mkdir()
    holder = os.open(tmp_path / "s.bundle.partial" / "lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(holder, fcntl.LOCK_EX)
    try:
        assert_refused(run_main(noisenerf_main, hide_args(world, tmp_path / "s.bundle"), capfd),
                       tmp_path / "s.bundle", "another hide is writing to")
    finally:
        os.close(holder)


def test_two_concurrent_hides_one_wins_exactly_the_other_refuses_at_once(world, tmp_path, capfd):
    """Different secrets, same -o: the first holds the lock and writes an exact bundle of its own secret;
    the second is refused within a second, and touches nothing of the first's."""
    first = tmp_path / "first.png"
    write_image(first, np.random.default_rng(11).integers(0, 256, (48, 48, 3), dtype=np.uint8))
    out = tmp_path / "s.bundle"
    command = [sys.executable, "-m", "noisenerf.cli.main", *map(str, hide_args(world, out, "--json"))]
    command[command.index(str(world.secret))] = str(first)
    runner = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (tmp_path / "s.bundle.partial" / "key").exists():
        assert runner.poll() is None and time.monotonic() < deadline, runner.communicate()
        time.sleep(0.05)
    started = time.monotonic()
    second = run_main(noisenerf_main, hide_args(world, out), capfd)
    waited = time.monotonic() - started
    stdout, stderr = runner.communicate(timeout=120)
    assert runner.returncode == 0 and stderr == "", stderr
    assert_refused(second, None, "another hide is writing to")
    assert waited < 5.0
    assert json.loads(stdout)["exact"] is True
    from noisenerf.runtime.bundle import secret_digest
    from noisenerf.runtime.images import load_secret
    assert hidden_bundle(out, world.model).secret_sha256 == secret_digest(load_secret(first)[0])
