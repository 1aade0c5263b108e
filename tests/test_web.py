"""The browser reveal (web/, JavaScript on onnxruntime-web) against golden files the Python runtime writes.

`write_fixtures` builds tiny scenes from seeds, hides secrets in them (every layout: compact with an
escaped pixel, ray, sample; a fine network and the coarse one of a hierarchical scene; an NDC scene; a
multi-tile bundle; a hash-grid field; nerfacto fields of both implementations, imported from synthetic
nerfstudio runs), exports the models, and writes beside each model.onnx and
secret.bundle what the Python runtime computes on them: per tile the rays (runtime.rays.camera_ray_batch),
the expanded noise (the tile noise's `rows`), the rendered colours (runtime.reveal.render_tile), and the
revealed 8-bit pixels, digest and exactness (runtime.reveal.reveal_tiles). Tampered copies carry the refusal's code and
params (`noisenerf.reveal` raises them; `noisenerf-reveal` exits 2 with its message). The manifest also holds the
graphs runtime.fields derives for hash-grid and nerfacto architectures, and the refusals of those out of the caps,
and the models of a fine
network's and nerfacto scenes pruned to each set of outputs a session fetches (runtime.onnx_file.pruned_model,
under pruned/). Then `node --test` runs web/test/ with NOISENERF_WEB_FIXTURES pointing there: the JavaScript
port must give the same pixels byte for byte, the same graphs, the same pruned models and the same refusals (code
and params; the messages are each language's own).

Run by hand: `python tests/test_web.py DIR` writes the fixtures into DIR (then `npm test` in web/ with
NOISENERF_WEB_FIXTURES=DIR).
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import hashlib
import io
import json
import lzma
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import (NGP_GOLDENS, as_older_compact_format, flip_first_float32, lens_scene, make_tiny_scene,
                     nerfstudio_run_from_goldens, rewrite_bundle, write_nerfstudio_run, xor_masked_bytes)

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "web"


def write_array(folder: Path, name: str, array: np.ndarray) -> dict:
    """A float32 or uint8 array as raw little-endian bytes, described in the manifest."""
    array = np.ascontiguousarray(array)
    (folder / f"{name}.bin").write_bytes(array.astype(array.dtype.newbyteorder("<")).tobytes())
    return {"file": f"{name}.bin", "dtype": array.dtype.name, "shape": list(array.shape)}


def run_cli(folder: Path, passphrase: str | None = None, output: str = "revealed.png") -> tuple[int, str]:
    """`noisenerf-reveal model.onnx secret.bundle -o OUTPUT` in `folder` (the passphrase from a file, never from
    the environment) -> exit code, stderr."""
    from noisenerf.cli.reveal import main

    stderr, cwd = io.StringIO(), os.getcwd()
    args = ["model.onnx", "secret.bundle", "-o", output]
    if passphrase is not None:
        (folder / "passphrase.txt").write_text(passphrase)
        args += ["--passphrase-file", "passphrase.txt"]
    saved = os.environ.pop("NOISENERF_PASSPHRASE", None)
    try:
        os.chdir(folder)
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            code = main(args)
    finally:
        os.chdir(cwd)
        if saved is not None:
            os.environ["NOISENERF_PASSPHRASE"] = saved
    return code, stderr.getvalue()


def refusal(error) -> dict:
    """A UserError as the manifest holds it: the stable code and params the JavaScript must raise too."""
    assert error.code is not None, f"a refusal of runtime/ without a code: {error}"
    return {"code": error.code, "params": error.params, "message": str(error)}


def cli_refusal(folder: Path, passphrase: str | None = None) -> dict:
    """How the library refuses folder's model.onnx and secret.bundle (`noisenerf.reveal`: code, params, message),
    checked to be the refusal `noisenerf-reveal` exits 2 with (its line starts with the library's message)."""
    from noisenerf import reveal
    from noisenerf.runtime.errors import UserError

    code, stderr = run_cli(folder, passphrase)
    assert code == 2, f"expected a refusal in {folder}, got exit code {code}: {stderr}"
    line = stderr.strip().splitlines()[-1]
    prefix = "noisenerf-reveal: error: "
    assert line.startswith(prefix), line
    cwd = os.getcwd()
    try:
        os.chdir(folder)  # the files named as the CLI names them
        with pytest.raises(UserError) as caught:
            reveal("model.onnx", "secret.bundle", passphrase, threads=1)
    finally:
        os.chdir(cwd)
    assert line[len(prefix):].startswith(str(caught.value)), (line, str(caught.value))
    return refusal(caught.value)


def golden(folder: Path) -> dict:
    """What the Python runtime computes on folder's model.onnx and secret.bundle, written beside them."""
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.model import check_bundle, load_model
    from noisenerf.runtime.rays import camera_ray_batch
    from noisenerf.runtime.reveal import render_tile, reveal_tiles, tile_field

    model = load_model(folder / "model.onnx", threads=1)
    bundle = load_bundle(folder / "secret.bundle", model.mask_secret)
    check_bundle(model, bundle)
    fields = model.fields()
    tiles = []
    for i, tile in enumerate(bundle.tiles):
        rays = camera_ray_batch(tile.camera, model.render_config)
        n = tile.rect[2] * tile.rect[3]
        escapes = getattr(tile.noise, "basis", None)
        tiles.append({
            "rect": list(tile.rect), "network": tile.network,
            "escapes": [] if escapes is None else escapes.escapes.tolist(),
            "origins": write_array(folder, f"tile{i}_origins", rays.origins),
            "directions": write_array(folder, f"tile{i}_directions", rays.directions),
            "viewdirs": write_array(folder, f"tile{i}_viewdirs", rays.viewdirs),
            "noise": write_array(folder, f"tile{i}_noise", tile.noise.loaded().rows(0, n)),
            "colors": write_array(folder, f"tile{i}_colors",
                                  render_tile(tile, model.render_config, tile_field(tile, fields))),
        })
    revealed = reveal_tiles(bundle, model.render_config, fields, keep_float=True)
    return {"width": bundle.width, "height": bundle.height, "layout": bundle.layout, "exact": revealed.exact,
            "sha256": bundle.secret_sha256, "fingerprint": model.fingerprint, "tiles": tiles,
            "image": write_array(folder, "image", revealed.image),
            "pixels": write_array(folder, "pixels", revealed.pixels)}


def with_escape(path: Path, mask_secret: bytes) -> None:
    """Rewrite a compact bundle so that tile 0's pixels 5 and 9 escape, and 12 and 14 are branch escapes: their
    coefficients 0, their noise the float16 of what they expanded to (a branch escape's values after the
    basis's leading zero rows, where the offset stands) (the reveal's golden is what Python then reveals, exact
    or not)."""
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.layouts import CompactBasis, CompactNoise

    bundle = load_bundle(path, mask_secret)
    tile = bundle.tiles[0]
    n = tile.rect[2] * tile.rect[3]
    noise = tile.noise.loaded().rows(0, n)[:, 0]
    coefficients = tile.noise.coefficients()
    coefficients.reshape(n, -1)[[5, 9, 12, 14]] = 0
    lead = int(np.argmax(tile.noise.basis.basis.any(axis=1)))
    assert lead > 0  # the tiny scene's tile has its basis in the direction segment
    basis = dataclasses.replace(tile.noise.basis, escapes=np.array([5, 9], np.int32),
                                escape_noise=noise[[5, 9]].astype(np.float16),
                                branch_escapes=np.array([12, 14], np.int32),
                                branch_escape_noise=noise[[12, 14], lead:].astype(np.float16))
    assert isinstance(basis, CompactBasis)
    tiles = (dataclasses.replace(tile, noise=CompactNoise.of(coefficients, basis, tile.noise.band_rows)),) + bundle.tiles[1:]
    path.unlink()
    dataclasses.replace(bundle, tiles=tiles).save(path, mask_secret=mask_secret)


def tamper(fixtures: Path, source: str, case: str, edit_bundle=None, edit_model=None,
           passphrase: str | None = None) -> dict:
    """A copy of fixture `source` with its bundle or model edited, and how it is refused (revealed with
    `passphrase`, if any). A masked bundle is edited unmasked (its fixture's model unmasks it) and masked again as its
    edited metadata states, so that an edit of its noise means what it says."""
    folder = fixtures / "tampered" / case
    folder.mkdir(parents=True)
    model = fixtures / source / "model.onnx"
    data = model.read_bytes()
    (folder / "model.onnx").write_bytes(edit_model(data) if edit_model else data)
    data = (fixtures / source / "secret.bundle").read_bytes()
    if edit_bundle is not None:
        data = xor_masked_bytes(edit_bundle(xor_masked_bytes(data, model)), model)
    (folder / "secret.bundle").write_bytes(data)
    return {"case": case, "source": source, "folder": f"tampered/{case}", "passphrase": passphrase,
            **cli_refusal(folder, passphrase)}


def payload_golden(folder: Path, passphrase: str | None) -> dict:
    """What `noisenerf-reveal` writes for a payload bundle: its bytes (payload.out) and report."""
    code, stderr = run_cli(folder, passphrase, output="payload.out")
    assert code == 0, stderr
    from noisenerf.runtime.bundle import load_bundle
    from noisenerf.runtime.model import load_model

    bundle = load_bundle(folder / "secret.bundle", load_model(folder / "model.onnx").mask_secret)
    data = (folder / "payload.out").read_bytes()
    return {"file": "payload.out", "passphrase": passphrase, "sealed": passphrase is not None,
            "width": bundle.width, "height": bundle.height, "sha256": hashlib.sha256(data).hexdigest()}


def reformatted(data: bytes) -> bytes:
    """A bundle whose safetensors header is written with other spacing (same JSON value: the tag still holds)."""
    size = int.from_bytes(data[:8], "little")
    text = json.dumps(json.loads(data[8:8 + size]), indent=1).encode()
    text += b" " * (-len(text) % 8)
    return len(text).to_bytes(8, "little") + text + data[8 + size:]


PAYLOAD = b"the eagle lands at noon\n\x00\xff binary tail"
PASSPHRASE = "r\u00e9f\u00e9rence"  # not ASCII: the page sends UTF-8, as the CLI's prompt does


def changed_initializer(pick):
    """The model with the first byte of the raw data of its first initializer whose name `pick` accepts changed (a
    float's low mantissa bit, an integer's lowest bit)."""
    def apply(data: bytes) -> bytes:
        from noisenerf.runtime.onnx_file import parse_model

        record = next(r for r in parse_model(data, "model").initializers if pick(r.name))
        at = data.index(record.raw_data)
        return data[:at] + bytes([data[at] ^ 1]) + data[at + 1:]
    return apply


changed_weight = changed_initializer(lambda name: name.endswith(".weight"))


def model_edit(edit):
    """Edit a model through onnx's ModelProto (edit(model) -> the model to write), e.g. test_model_graph's
    tamperings."""
    def apply(data: bytes) -> bytes:
        import onnx

        return edit(onnx.load_from_string(data)).SerializeToString()
    return apply


def swapped_xor(model):
    """A model whose hash's second XOR is an OR: the same weights looked up at other rows."""
    next(node for node in model.graph.node if node.output[0].endswith(".hxyz")).op_type = "BitwiseOr"
    return model


def dropped_output(name: str):
    """A model whose graph no longer declares the output `name` (its nodes kept)."""
    def edit(model):
        kept = [port for port in model.graph.output if port.name != name]
        del model.graph.output[:]
        model.graph.output.extend(kept)
        return model
    return edit


def renamed_output(name: str, new: str):
    """A model whose output `name`, and the node computing it, are called `new`."""
    def edit(model):
        next(node for node in model.graph.node if name in node.output).output[0] = new
        next(port for port in model.graph.output if port.name == name).name = new
        return model
    return edit


def one_proposal(meta: dict) -> None:
    """A nerfacto model's metadata stating its first proposal network alone."""
    coarse = meta["architecture"]["coarse"]
    coarse.update(proposals=coarse["proposals"][:1], sampler={**coarse["sampler"], "proposal_samples": [256]})


def model_metadata_edit(edit):
    """Edit a model's noisenerf metadata (JSON), its graph and weights kept."""
    def apply(model):
        entry = next(entry for entry in model.metadata_props if entry.key == "noisenerf")
        meta = json.loads(entry.value)
        edit(meta)
        entry.value = json.dumps(meta)
        return model
    return model_edit(apply)


def model_architecture(path: Path) -> dict:
    """The architecture in a model file's noisenerf metadata."""
    import onnx

    entry = next(entry for entry in onnx.load(str(path)).metadata_props if entry.key == "noisenerf")
    return json.loads(entry.value)["architecture"]


def graph_golden(architecture: dict, noise_dims: int) -> dict:
    """runtime.fields.field_graph(architecture, noise_dims) as JSON: nodes, constants (name, dtype, shape, values:
    float32 values exactly, as the doubles they are), weights, ports and opset, or the refusal. The
    architecture goes as its JSON text, which the JavaScript parses as Python does (16.0 a float, 16 an int)."""
    from noisenerf.runtime.errors import UserError
    from noisenerf.runtime.fields import field_graph

    text = json.dumps(architecture)
    try:
        graph = field_graph(json.loads(text), noise_dims)
    except UserError as error:
        return {"architecture": text, "noise_dims": noise_dims, **refusal(error)}
    ports = lambda ports: [[port.name, list(port.shape), port.elem_type] for port in ports]  # noqa: E731
    return {"architecture": text, "noise_dims": noise_dims, "opset": graph.opset,
            "nodes": [[node.op, list(node.inputs), list(node.outputs), [list(a) for a in node.attributes]]
                      for node in graph.nodes],
            "constants": [[name, values.dtype.name, list(values.shape), values.ravel().tolist()]
                          for name, values in graph.constants.items()],
            "weights": [[name, list(shape)] for name, shape in graph.weights.items()],
            "inputs": ports(graph.inputs), "outputs": ports(graph.outputs)}


# per_level_scale of 16 levels from 16 to 1024 and to 2048 vertices a side (64 and 128 to the 1/15), and others
PER_LEVEL_SCALES = (1.3195079107728942, 1.381912879967776, 2.0, 1.5, 1.26, 1.0)


def hashgrid_architectures() -> tuple[list, list]:
    """(architectures whose graphs the JavaScript must derive exactly, architectures it must refuse with Python's
    message): the random scene's hash grid and variants of it (fine, beside an MLP, without a geometric feature,
    other SH degrees and widths, every level hashed, every level dense), then every cap, key and kind."""
    from noisenerf.train.scene.random_scene import SMALL_HASHGRID

    grid = SMALL_HASHGRID.to_dict()
    mlp = {"depth": 2, "width": 8, "skips": [1], "xyz_freqs": 2, "dir_freqs": 1, "use_viewdirs": True}
    without_aabb = {key: value for key, value in grid.items() if key != "aabb"}

    def coarse(**change) -> dict:
        return {"coarse": {**grid, **change}, "fine": None}

    graphs = [coarse(), {"coarse": grid, "fine": grid}, {"coarse": mlp, "fine": grid}, {"coarse": grid, "fine": mlp},
              coarse(geo_features=0, sh_degree=3, colour_layers=1), coarse(sh_degree=1, colour_hidden=3),
              coarse(log2_table=3), coarse(log2_table=24, per_level_scale=1.0, levels=2),
              coarse(levels=8, base_resolution=3, per_level_scale=4.0, log2_table=12, features=1,
                     aabb=[-2, 0, 1, 3, 1.25, 7])]
    refused = [coarse(levels=33), coarse(log2_table=25), coarse(levels=16, per_level_scale=4.0), coarse(features=0),
               coarse(levels=32, features=8, log2_table=24, per_level_scale=1.0, base_resolution=4096),
               coarse(aabb=[0, 0, 0, 1, -1, 1]), coarse(aabb=[0, 0, 0, 1, 1]), coarse(aabb=[0, 0, 0, 1, 1, 2e9]),
               coarse(aabb={"lo": 0}), coarse(sh_degree=5), coarse(geo_features=-1), coarse(colour_layers=0),
               coarse(per_level_scale=9.0), coarse(per_level_scale=0.5), coarse(per_level_scale="2"),
               coarse(per_level_scale=True), coarse(levels=2.0), coarse(kind="triplane"), coarse(kind=3),
               coarse(kind=None), coarse(kind="mlp"), {"coarse": without_aabb, "fine": None},
               {"coarse": grid, "fine": {**grid, "kind": "triplane"}},
               {"coarse": {**grid, "kind": "nerf"}, "fine": {**grid, "levels": 0}},
               {"coarse": {**mlp, "kind": "hashgrid"}, "fine": None},
               {"coarse": {**mlp, "depth": 10 ** 9}, "fine": None}]
    return graphs, refused


def scales_golden() -> list:
    """runtime.fields.hashgrid.grid_levels' float32 scales (16 levels from N_min 16) for PER_LEVEL_SCALES."""
    from noisenerf.runtime.fields.hashgrid import grid_levels

    return [{"per_level_scale": scale, "scale": grid_levels(16, 19, 16, scale).scale.tolist()}
            for scale in PER_LEVEL_SCALES]


def nerfacto_architectures(imported: dict) -> tuple[list, list]:
    """(nerfacto architectures whose graphs the JavaScript must derive exactly, architectures it must refuse with
    Python's message): the imported runs' fields of both implementations (`imported`: implementation -> coarse
    architecture) and variants (one proposal network, other SH degrees and widths, every level hashed or
    dense, integer scales), then every check of runtime.fields.nerfacto, and proposal networks beside a fine one."""
    tcnn, torch_field, ngp = imported["tcnn"], imported["torch"], imported["ngp"]
    mlp = {"depth": 2, "width": 8, "skips": [1], "xyz_freqs": 2, "dir_freqs": 1, "use_viewdirs": True}

    def coarse(field=tcnn, **change) -> dict:
        return {"coarse": {**field, **change}, "fine": None}

    def sampler(field=tcnn, **change) -> dict:
        return {**field["sampler"], **change}

    def proposal(field=tcnn, i=0, **change) -> list:
        return [*field["proposals"][:i], {**field["proposals"][i], **change}, *field["proposals"][i + 1:]]

    one = {"proposals": tcnn["proposals"][:1], "sampler": sampler(proposal_samples=[64])}
    graphs = [coarse(), coarse(torch_field),
              coarse(torch_field, sh_degree=3, geo_features=0, colour_layers=1, colour_hidden=5),
              coarse(**one, log2_table=3, sh_degree=1),
              coarse(scales=[0.0, 1.0, 2.5, 7.25], log2_table=12, features=1, density_scale=0.3),
              coarse(torch_field, scales=[16, 23, 35], density_scale=1, proposals=torch_field["proposals"][::-1]),
              coarse(ngp), coarse(ngp, implementation="tcnn", sampler=sampler(
                  ngp, levels=1, resolution=64, occupancy=base64.b64encode(bytes(64 ** 3 // 8)).decode()))]
    without = {key: value for key, value in tcnn.items() if key != "sampler"}
    refused = [coarse(implementation="cuda"), coarse(implementation=3), {"coarse": without, "fine": None},
               coarse(proposals=[], sampler=sampler(proposal_samples=[])), coarse(scales=[255.0, 15.0], log2_table=12),
               coarse(extra=1), coarse(scales="16"), coarse(scales=[]), coarse(scales=[15.0] * 33),
               coarse(torch_field, scales=[0.5, 16.0]), coarse(scales=[-1.0]), coarse(scales=[2e6]),
               coarse(scales=["1"]), coarse(features=9), coarse(log2_table=2), coarse(sh_degree=5),
               coarse(density_scale=0), coarse(density_scale="0.01"), coarse(geo_features=-1),
               coarse(proposals=tcnn["proposals"] * 3), coarse(proposals={"0": 1}),
               coarse(proposals=[{key: v for key, v in tcnn["proposals"][0].items() if key != "hidden"}]),
               coarse(proposals=proposal(hidden=0)), coarse(proposals=proposal(scales=[])),
               coarse(torch_field, proposals=proposal(torch_field, scales=[16.0, 0.5])),
               coarse(proposals=proposal(i=1, log2_table=25)),
               coarse(sampler={key: v for key, v in tcnn["sampler"].items() if key != "near"}),
               coarse(sampler=sampler(proposal_samples=[256])), coarse(sampler=sampler(near=5.0, far=1)),
               coarse(sampler=sampler(far=2e9)), coarse(sampler=sampler(samples=0)),
               coarse(sampler=sampler(proposal_samples=[0, 96])), coarse(sampler=sampler(histogram_padding=2.0)),
               coarse(sampler=[1]),
               coarse(torch_field, scales=[1000.0] * 32, log2_table=24, features=8),
               {"coarse": tcnn, "fine": tcnn}, {"coarse": mlp, "fine": torch_field},
               {"coarse": {**tcnn, "proposals": [], "sampler": sampler(proposal_samples=[])}, "fine": mlp},
               {"coarse": {**mlp, "kind": "nerfacto"}, "fine": None},
               # nerfstudio's instant-ngp: nerfacc's grid sampler where there are no proposal networks
               coarse(ngp, sampler=sampler(tcnn)), coarse(tcnn, sampler=sampler(ngp)),
               coarse(ngp, sampler={key: v for key, v in ngp["sampler"].items() if key != "cone_angle"}),
               coarse(ngp, sampler=sampler(ngp, levels=9)), coarse(ngp, sampler=sampler(ngp, resolution=0)),
               coarse(ngp, sampler=sampler(ngp, resolution=513)), coarse(ngp, sampler=sampler(ngp, levels=8, resolution=300)),
               coarse(ngp, sampler=sampler(ngp, occupancy=ngp["sampler"]["occupancy"][:-4])),
               coarse(ngp, sampler=sampler(ngp, occupancy="*" + ngp["sampler"]["occupancy"][1:])),
               coarse(ngp, sampler=sampler(ngp, occupancy=3)), coarse(ngp, sampler=sampler(ngp, aabb=[1, 1, 1, 0, 2, 2])),
               coarse(ngp, sampler=sampler(ngp, aabb=[1, 1])), coarse(ngp, sampler=sampler(ngp, cone_angle=2.0)),
               coarse(ngp, sampler=sampler(ngp, step=0.0)), coarse(ngp, sampler=sampler(ngp, near=3.0, far=2.0))]
    return graphs, refused


PRUNED = {  # scene -> the sets of outputs a session fetches from its model (runtime.session.OnnxField.session_for)
    "nerfacto_tcnn": (("rgb", "sigma"), ("sigma_proposal0",), ("sigma_proposal1",)),
    "nerfacto_torch": (("rgb", "sigma"),),
    "fine": (("rgb", "sigma"), ("rgb_coarse", "sigma_coarse")),
    "plain": (("rgb", "sigma"),),  # every output: the model's own bytes
}


def pruned_goldens(root: Path) -> list:
    """runtime.onnx_file.pruned_model of the scenes' models (root/scenes) to each set of outputs in PRUNED, written
    under root/pruned: the bytes the JavaScript's prunedModel must give, with their node counts."""
    from noisenerf.runtime.onnx_file import parse_model, pruned_model

    (root / "pruned").mkdir()
    goldens = []
    for scene, output_sets in PRUNED.items():
        whole = parse_model((root / "scenes" / f"{scene}.onnx").read_bytes(), scene)
        for outputs in output_sets:
            name = f"pruned/{scene}.{'.'.join(outputs)}.onnx"
            (root / name).write_bytes(pruned_model(whole, outputs))
            goldens.append({"model": f"scenes/{scene}.onnx", "outputs": list(outputs), "file": name,
                            "nodes": len(parse_model((root / name).read_bytes(), name).nodes),
                            "whole_nodes": len(whole.nodes)})
    return goldens


def bundle_metadata_edit(edit):
    """Edit a bundle's JSON metadata (safetensors header), keeping its tensors."""
    def apply(data: bytes) -> bytes:
        size = int.from_bytes(data[:8], "little")
        header = json.loads(data[8:8 + size])
        meta = json.loads(header["__metadata__"]["noisenerf_bundle"])
        edit(meta)
        header["__metadata__"]["noisenerf_bundle"] = json.dumps(meta, sort_keys=True)
        text = json.dumps(header).encode()
        text += b" " * (-len(text) % 8)
        return len(text).to_bytes(8, "little") + text + data[8 + size:]
    return apply


def corrupt_tensor(name: str, position: int):
    """Flip one byte of a bundle tensor's data."""
    def apply(data: bytes) -> bytes:
        size = int.from_bytes(data[:8], "little")
        begin = json.loads(data[8:8 + size])[name]["data_offsets"][0]
        at = 8 + size + begin + position
        return data[:at] + bytes([data[at] ^ 0x55]) + data[at + 1:]
    return apply


def replaced_tensor(name: str, replace):
    """Replace a 1-D uint8 bundle tensor's bytes by replace(its bytes), the others kept (their offsets moved)."""
    def apply(data: bytes) -> bytes:
        size = int.from_bytes(data[:8], "little")
        header = json.loads(data[8:8 + size])
        body = data[8 + size:]
        tensors = {key: body[slice(*info["data_offsets"])] for key, info in header.items() if key != "__metadata__"}
        tensors[name] = replace(tensors[name])
        header[name]["shape"] = [len(tensors[name])]
        offset = 0
        for key, value in tensors.items():
            header[key]["data_offsets"] = [offset, offset + len(value)]
            offset += len(value)
        text = json.dumps(header).encode()
        text += b" " * (-len(text) % 8)
        return len(text).to_bytes(8, "little") + text + b"".join(tensors.values())
    return apply


def edited_tensors(edit):
    """Edit a bundle's tensors as arrays, edit(tensors dict), keeping its metadata."""
    def apply(data: bytes) -> bytes:
        from safetensors.numpy import load, save

        size = int.from_bytes(data[:8], "little")
        tensors = load(data)
        edit(tensors)
        return save(tensors, metadata=json.loads(data[8:8 + size])["__metadata__"])
    return apply


def stated_4096(meta: dict) -> None:
    """A compact bundle's metadata claiming a 4096² secret in one tile, its streams unchanged."""
    meta["secret"].update(width=4096, height=4096)
    meta["tiles"][0]["rect"] = [0, 0, 4096, 4096]
    del meta["tiles"][1:]


def recompressed(stream: bytes, dict_size: int) -> bytes:
    """The xz stream's data compressed again with a dictionary of dict_size bytes (the header states it)."""
    return lzma.compress(lzma.decompress(stream), format=lzma.FORMAT_XZ,
                         filters=[{"id": lzma.FILTER_LZMA2, "dict_size": dict_size, "mf": lzma.MF_HC3}])


def imported_nerfacto(root: Path, implementation: str):
    """A synthetic nerfstudio run of this implementation (tests/helpers.write_nerfstudio_run, as
    tests/test_import_nerfstudio.py writes it), imported as `noisenerf import-nerfstudio` imports it -> the scene."""
    from noisenerf.train.scene.import_nerfstudio import import_nerfstudio

    folder = root / "nerfstudio" / implementation
    folder.mkdir(parents=True)
    run, data = write_nerfstudio_run(folder, implementation, seed=3,
                                     prefix="_model.module." if implementation == "tcnn" else "_model.")
    return import_nerfstudio(run, folder / "scene", data=data)


def imported_ngp(root: Path):
    """nerfstudio's instant-ngp run of tests/goldens/ngp_torch, imported -> the scene (no proposal networks: its
    architecture's sampler is nerfacc's grid, which the page must check as Python does)."""
    from noisenerf.train.scene.import_nerfstudio import import_nerfstudio

    folder = root / "nerfstudio" / "ngp"
    folder.mkdir(parents=True)
    run, data = nerfstudio_run_from_goldens(folder, NGP_GOLDENS)
    return import_nerfstudio(run, folder / "scene", data=data)


def write_fixtures(root: Path) -> dict:
    """Every fixture under root, and root/manifest.json describing them."""
    import torch

    from noisenerf.export.onnx_export import export_scene
    from noisenerf.train.hide.settings import PaperSettings
    from noisenerf.train.hide.plan import HideConfig
    from noisenerf.train.hide.run import hide
    from test_model_graph import appended_node, changed_opset, removed_node

    cpu = torch.device("cpu")
    rng = np.random.default_rng(7)
    secret = rng.integers(0, 256, (20, 24, 3), dtype=np.uint8)
    scenes = {"plain": make_tiny_scene(seed=0), "fine": make_tiny_scene(seed=3, fine=True),
              "ndc": make_tiny_scene(seed=1, ndc=True),
              "wide": make_tiny_scene(seed=0, width=64, depth=4),  # tests/test_reference.py's payload scene
              "hashgrid": make_tiny_scene(seed=2, kind="hashgrid"),
              "lens_opencv": lens_scene("opencv", seed=5), "lens_fisheye": lens_scene("fisheye", seed=6),
              **{f"nerfacto_{implementation}": imported_nerfacto(root, implementation)
                 for implementation in ("tcnn", "torch")}, "ngp": imported_ngp(root)}
    paper = (PaperSettings(iters=4, record_at=(4,)),)
    cases = {  # name -> scene, secret, hide config
        "compact_tiles": ("plain", secret, HideConfig(tile_size=16, part_pixels=96)),  # bands of 6 rows
        "ray": ("plain", secret[:6, :8], HideConfig(layout="ray", tile_size=16, view=2, seed=5)),
        "ray_float32": ("plain", secret[:5, :7], HideConfig(layout="ray", dtype="float32", tile_size=16, view=1)),
        "sample": ("plain", secret[:6, :8], HideConfig(method="paper", tile_size=16, n_samples=8, settings=paper)),
        "fine_compact": ("fine", secret[:8, :8], HideConfig(tile_size=16)),
        "fine_coarse_sample": ("fine", secret[:6, :8], HideConfig(method="paper", tile_size=16, n_samples=8,
                                                                  settings=paper)),
        "ndc_compact": ("ndc", secret[:8, :12], HideConfig(tile_size=16)),
        "hashgrid_compact": ("hashgrid", secret[:8, :12], HideConfig(tile_size=16)),
        "hashgrid_ray": ("hashgrid", secret[:6, :8], HideConfig(layout="ray", tile_size=16, view=2, seed=5)),
        # cameras with lenses (runtime.lens): rays undistorted in float64 by both languages
        "lens_opencv_compact": ("lens_opencv", secret[:12, :16], HideConfig(tile_size=16, view=1)),
        "lens_fisheye_ray": ("lens_fisheye", secret[:6, :8], HideConfig(layout="ray", tile_size=16, view=3)),
        # the defaults, as `noisenerf hide SCENE secret.png -o b.nnrf --view 4` hides in an imported run
        "nerfacto_tcnn": ("nerfacto_tcnn", secret[:6, :7], HideConfig(view=4)),
        "nerfacto_torch": ("nerfacto_torch", secret[:6, :7], HideConfig(view=4)),
        "ngp": ("ngp", secret[:6, :7], HideConfig(view=5)),
    }
    manifest = {"fixtures": {}, "tampered": []}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    (root / "scenes").mkdir()
    try:
        for scene_name, scene in scenes.items():
            scene.save(root / "scenes" / scene_name)
            export_scene(root / "scenes" / scene_name, root / "scenes" / f"{scene_name}.onnx")
        for name, (scene_name, part, config) in cases.items():
            folder = root / name
            folder.mkdir(parents=True)
            shutil.copyfile(root / "scenes" / f"{scene_name}.onnx", folder / "model.onnx")
            hide(scenes[scene_name], part, folder / "secret.bundle", config, cpu, workers=1,
                 allow_inexact=True)
            if name == "compact_tiles":
                with_escape(folder / "secret.bundle", scenes[scene_name].digests().mask_secret)
            manifest["fixtures"][name] = golden(folder)
        older = root / "compact_tiles_format_3"  # the same coefficients as format 3 stored them: plain planes
        older.mkdir()
        shutil.copyfile(root / "compact_tiles" / "model.onnx", older / "model.onnx")
        rewrite_bundle(root / "compact_tiles" / "secret.bundle", older / "secret.bundle", as_older_compact_format(3),
                       scenes["plain"])
        manifest["fixtures"]["compact_tiles_format_3"] = golden(older)
        unmasked = root / "compact_tiles_format_4"  # the same bundle as format 4 wrote it: unmasked, no mask object
        unmasked.mkdir()
        shutil.copyfile(root / "compact_tiles" / "model.onnx", unmasked / "model.onnx")
        rewrite_bundle(root / "compact_tiles" / "secret.bundle", unmasked / "secret.bundle",
                       lambda meta, tensors: meta.update(format_version=4) or meta.pop("mask"), scenes["plain"])
        manifest["fixtures"]["compact_tiles_format_4"] = golden(unmasked)
        from noisenerf.runtime.payload import Record
        from noisenerf.runtime.sealing import ScryptParams, new_seal
        from noisenerf.train.hide.payload import hide_payload

        record = Record("file", PAYLOAD, "n\u00f6te.txt".encode())
        manifest["payloads"] = {}
        for name, passphrase in (("payload", None), ("payload_sealed", PASSPHRASE)):
            folder = root / name
            folder.mkdir(parents=True)
            shutil.copyfile(root / "scenes" / "wide.onnx", folder / "model.onnx")
            seal = new_seal(ScryptParams(log2_n=10, r=8, p=1), salt=bytes(range(16)), nonce=bytes(range(12)))
            hide_payload(scenes["wide"], record, folder / "secret.bundle", HideConfig(tile_size=16), cpu,
                         passphrase=None if passphrase is None else passphrase.encode(), seal=seal, workers=1)
            manifest["payloads"][name] = {**payload_golden(folder, passphrase), "name": "n\u00f6te.txt"}
            assert (folder / "payload.out").read_bytes() == PAYLOAD
        shutil.copytree(root / "payload_sealed", root / "payload_sealed_reformatted",
                        ignore=shutil.ignore_patterns("payload.out", "passphrase.txt"))
        path = root / "payload_sealed_reformatted" / "secret.bundle"
        path.write_bytes(reformatted(path.read_bytes()))
        manifest["payloads"]["payload_sealed_reformatted"] = {
            **payload_golden(root / "payload_sealed_reformatted", PASSPHRASE), "name": "n\u00f6te.txt"}
    finally:
        torch.set_num_threads(threads)
    manifest["tampered"] = [
        tamper(root, "payload_sealed", "sealed_wrong_passphrase", passphrase="reference"),
        tamper(root, "payload_sealed", "sealed_no_passphrase"),
        tamper(root, "payload_sealed", "sealed_empty_passphrase", passphrase=""),
        tamper(root, "payload_sealed", "sealed_noise_byte", edit_bundle=flip_first_float32, passphrase=PASSPHRASE),
        tamper(root, "payload_sealed", "sealed_metadata", passphrase=PASSPHRASE,
               edit_bundle=bundle_metadata_edit(lambda meta: meta.setdefault("extra", {}).update(note="x"))),
        tamper(root, "payload_sealed", "sealed_other_model", passphrase=PASSPHRASE,
               edit_model=lambda data: (root / "scenes" / "ndc.onnx").read_bytes()),
        tamper(root, "payload_sealed", "sealed_kdf_cap", passphrase=PASSPHRASE, edit_bundle=bundle_metadata_edit(
            lambda meta: meta["payload"]["sealed"]["kdf"].update(log2_n=24))),
        tamper(root, "payload_sealed", "sealed_extra_field", passphrase=PASSPHRASE, edit_bundle=bundle_metadata_edit(
            lambda meta: meta["payload"]["sealed"].update(more=1))),
        tamper(root, "payload", "payload_version", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["payload"].update(version=2))),

        tamper(root, "ray", "changed_weight", edit_model=changed_weight),
        tamper(root, "ray", "other_model", edit_bundle=bundle_metadata_edit(
            lambda meta: meta.update(model_fingerprint="0" * 64))),
        tamper(root, "ray", "tile_outside", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["tiles"][0]["rect"].__setitem__(0, 3))),
        tamper(root, "ray", "format_6", edit_bundle=bundle_metadata_edit(lambda meta: meta.update(format_version=6))),
        # the mask (runtime.masking): stripped (its tensors left unmasked), malformed, stated by a format 4 bundle
        tamper(root, "ray", "mask_stripped", edit_bundle=bundle_metadata_edit(lambda meta: meta.pop("mask"))),
        tamper(root, "ray", "mask_salt_short", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["mask"].update(salt="AAAA"))),
        tamper(root, "ray", "mask_other_cipher", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["mask"].update(cipher="aes"))),
        # a tile camera's lens (runtime.lens): folding over inside the image, a model neither reads
        tamper(root, "lens_opencv_compact", "lens_folds", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["tiles"][0]["camera"]["lens"].update(k1=-5.0))),
        tamper(root, "lens_opencv_compact", "lens_model", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["tiles"][0]["camera"]["lens"].update(model="equirectangular"))),
        tamper(root, "compact_tiles", "mask_on_format_4", edit_bundle=bundle_metadata_edit(
            lambda meta: meta.update(format_version=4))),
        # quoted as repr() quotes it: a no-break space, a line separator and a zero-width space escaped
        tamper(root, "ray", "odd_tensor_name", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["tiles"][0].update(tensor="n\u00a0o\u2028pe\u200b"))),
        tamper(root, "compact_tiles", "branch_escape_also_escape", edit_bundle=edited_tensors(
            lambda t: t.update(tile_0000_branch_escapes=np.array([9, 14], np.int32)))),
        tamper(root, "compact_tiles", "branch_escape_too_wide", edit_bundle=edited_tensors(
            lambda t: t.update(tile_0000_branch_escape_noise=np.zeros((2, 200), np.float16)))),
        tamper(root, "compact_tiles", "branch_escape_nan", edit_bundle=edited_tensors(
            lambda t: t["tile_0000_branch_escape_noise"].__setitem__((1, 0), np.nan))),
        tamper(root, "compact_tiles", "branch_escapes_unsorted", edit_bundle=edited_tensors(
            lambda t: t.update(tile_0000_branch_escapes=np.array([14, 12], np.int32)))),
        tamper(root, "compact_tiles", "xz_corrupt", edit_bundle=corrupt_tensor("tile_0001", 40)),
        tamper(root, "compact_tiles", "xz_truncated", edit_bundle=replaced_tensor("tile_0001", lambda s: s[:len(s) // 2])),
        tamper(root, "compact_tiles", "xz_trailing", edit_bundle=replaced_tensor("tile_0001", lambda s: s + b"junk")),
        tamper(root, "compact_tiles", "xz_footer_cut", edit_bundle=replaced_tensor("tile_0001", lambda s: s[:-12])),
        # 96 MiB: the first dictionary size over a preset-9 stream's 64 MiB, past both sides' decoder memory
        tamper(root, "compact_tiles", "xz_dictionary", edit_bundle=replaced_tensor(
            "tile_0001", lambda s: recompressed(s, 96 << 20))),
        # bombs: a stream of 64 MiB of zeros where 5.8 KB are stated (refused once the stated size is passed),
        # and a secret stated 4096² on the same few KB of streams (refused before any decoding)
        tamper(root, "compact_tiles", "xz_bomb_expands", edit_bundle=replaced_tensor(
            "tile_0001", lambda s: lzma.compress(bytes(64 << 20), format=lzma.FORMAT_XZ))),
        tamper(root, "compact_tiles", "xz_bomb_stated", edit_bundle=bundle_metadata_edit(stated_4096)),
        # a sealed bundle stripped of its seal, revealed with the passphrase its recipient holds
        tamper(root, "payload_sealed", "sealed_stripped", passphrase=PASSPHRASE,
               edit_bundle=bundle_metadata_edit(lambda meta: meta.pop("payload"))),
        tamper(root, "compact_tiles", "band_rows", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["tiles"][1].update(band_rows=0))),
        tamper(root, "compact_tiles", "codec", edit_bundle=bundle_metadata_edit(
            lambda meta: meta["noise"].update(codec="zstd"))),
        # one stream and nothing after it, as Python's decoder reads it (the browser's reads on through zero padding
        # and further streams, and past a range coder's first byte that is not 0)
        tamper(root, "compact_tiles", "xz_padded", edit_bundle=replaced_tensor("tile_0001", lambda s: s + bytes(4))),
        tamper(root, "compact_tiles", "xz_two_streams", edit_bundle=replaced_tensor("tile_0001", lambda s: (
            raw := lzma.decompress(s), lzma.compress(raw[:len(raw) // 2]) + lzma.compress(raw[len(raw) // 2:]))[-1])),
        tamper(root, "compact_tiles", "xz_trailing_16", edit_bundle=replaced_tensor("tile_0001", lambda s: s + b"junk" * 4)),
        tamper(root, "compact_tiles", "xz_range_coder_byte", edit_bundle=replaced_tensor("tile_0001", lambda s: (
            at := 12 + (s[12] + 1) * 4 + 6, s[:at] + b"\x01" + s[at + 1:])[-1])),
        # the order of checks (runtime/bundle.py's docstring, web/src/bundle.js): wrong in two ways, refused for the
        # one checked first; the safetensors header itself edited (its JSON rewritten, the tensor data kept)
        tamper(root, "ray", "no_metadata_and_offsets", edit_bundle=lambda data: (
            n := int.from_bytes(data[:8], "little"), header := json.loads(data[8:8 + n]), header.pop("__metadata__"),
            header["tile_0000"]["data_offsets"].__setitem__(1, header["tile_0000"]["data_offsets"][1] + 2),
            text := json.dumps(header).encode(), len(text).to_bytes(8, "little") + text + data[8 + n:])[-1]),
        tamper(root, "ray", "dtype_and_offsets", edit_bundle=lambda data: (
            n := int.from_bytes(data[:8], "little"), header := json.loads(data[8:8 + n]),
            header["tile_0000"].update(dtype="F64"),
            text := json.dumps(header).encode(), len(text).to_bytes(8, "little") + text + data[8 + n:])[-1]),
        tamper(root, "ray", "metadata_null", edit_bundle=lambda data: (
            n := int.from_bytes(data[:8], "little"), header := json.loads(data[8:8 + n]), header.update(__metadata__=None),
            text := json.dumps(header).encode(), len(text).to_bytes(8, "little") + text + data[8 + n:])[-1]),
        tamper(root, "ray", "metadata_value_number", edit_bundle=lambda data: (
            n := int.from_bytes(data[:8], "little"), header := json.loads(data[8:8 + n]),
            header["__metadata__"].update(note=1),
            text := json.dumps(header).encode(), len(text).to_bytes(8, "little") + text + data[8 + n:])[-1]),
        tamper(root, "ray", "shape_not_whole", edit_bundle=lambda data: (
            n := int.from_bytes(data[:8], "little"), header := json.loads(data[8:8 + n]),
            header["tile_0000"]["shape"].__setitem__(0, float(header["tile_0000"]["shape"][0])),
            text := json.dumps(header).encode(), len(text).to_bytes(8, "little") + text + data[8 + n:])[-1]),
        tamper(root, "compact_tiles", "band_rows_and_stream_shape", edit_bundle=lambda data: (
            data := bundle_metadata_edit(lambda meta: meta["tiles"][1].update(band_rows=0))(data),
            n := int.from_bytes(data[:8], "little"), header := json.loads(data[8:8 + n]),
            header["tile_0001"].update(shape=[1, *header["tile_0001"]["shape"]]),
            text := json.dumps(header).encode(), len(text).to_bytes(8, "little") + text + data[8 + n:])[-1]),
        tamper(root, "ray", "header_past_end_and_format", edit_bundle=lambda data: (
            data := bundle_metadata_edit(lambda meta: meta.update(format_version=99))(data),
            len(data).to_bytes(8, "little") + data[8:])[-1]),
        tamper(root, "ray", "tile_dtype_and_shape", edit_bundle=edited_tensors(
            lambda t: t.update(tile_0000=np.zeros((3, *t["tile_0000"].shape[1:]), np.float32)))),
        tamper(root, "fine_compact", "wrong_model", edit_model=lambda data: (root / "scenes" / "plain.onnx").read_bytes()),
        # a float constant (the first level's scale), an integer one (the hash's primes), the table (the fingerprint)
        *(tamper(root, "hashgrid_ray", f"hashgrid_{name}", edit_model=changed_initializer(pick)) for name, pick in (
            ("scale", lambda name: name.endswith(".scale")), ("primes", lambda name: name == "grid.primes"),
            ("table", lambda name: name.endswith(".table")))),
        tamper(root, "hashgrid_compact", "hashgrid_appended_node", edit_model=model_edit(appended_node)),
        tamper(root, "hashgrid_compact", "hashgrid_xor", edit_model=model_edit(swapped_xor)),
        tamper(root, "hashgrid_compact", "hashgrid_opset", edit_model=model_edit(changed_opset)),
        tamper(root, "hashgrid_compact", "hashgrid_per_level_scale", edit_model=model_metadata_edit(
            lambda meta: meta["architecture"]["coarse"].update(per_level_scale=9.0))),
        tamper(root, "hashgrid_compact", "hashgrid_kind", edit_model=model_metadata_edit(
            lambda meta: meta["architecture"]["coarse"].update(kind="triplane"))),
        # nerfacto: float constants (a proposal grid's scales, σ's density scale, the torch SH's negated rows), the
        # tables (the fingerprint), a node more or fewer, a proposal output dropped or renamed, and metadata that
        # derives another graph or none
        *(tamper(root, f"nerfacto_{implementation}", f"nerfacto_{implementation}_{name}",
                 edit_model=changed_initializer(lambda initializer, pick=pick: initializer == pick))
          for implementation, name, pick in (
              ("tcnn", "scale", "coarse.proposals.1.grid.scale"), ("tcnn", "density_scale", "density.scale"),
              ("torch", "sh_signs", "viewdirs.halved.sh.matrix.4"), ("torch", "table", "coarse.proposals.0.table"))),
        tamper(root, "nerfacto_tcnn", "nerfacto_appended_node", edit_model=model_edit(appended_node)),
        tamper(root, "nerfacto_torch", "nerfacto_removed_node", edit_model=model_edit(removed_node)),
        tamper(root, "nerfacto_tcnn", "nerfacto_dropped_proposal",
               edit_model=model_edit(dropped_output("sigma_proposal1"))),
        tamper(root, "nerfacto_torch", "nerfacto_renamed_proposal",
               edit_model=model_edit(renamed_output("sigma_proposal0", "sigma_proposal2"))),
        tamper(root, "nerfacto_torch", "nerfacto_implementation", edit_model=model_metadata_edit(
            lambda meta: meta["architecture"]["coarse"].update(implementation="tcnn"))),
        tamper(root, "nerfacto_tcnn", "nerfacto_meta_density_scale", edit_model=model_metadata_edit(
            lambda meta: meta["architecture"]["coarse"].update(density_scale=0.02))),
        tamper(root, "nerfacto_tcnn", "nerfacto_one_proposal", edit_model=model_metadata_edit(one_proposal)),
        tamper(root, "nerfacto_torch", "nerfacto_near_far", edit_model=model_metadata_edit(
            lambda meta: meta["architecture"]["coarse"]["sampler"].update(near=2000.0))),
        tamper(root, "nerfacto_tcnn", "nerfacto_beside_fine", edit_model=model_metadata_edit(
            lambda meta: meta.update(architecture={**meta["architecture"], "fine": meta["architecture"]["coarse"]},
                                     hierarchy={"n_coarse": 64, "n_importance": 64}))),
    ]
    graphs, refused = hashgrid_architectures()
    noise_dims = scenes["hashgrid"].render_field.config.noise_dims
    manifest["graphs"] = [graph_golden(architecture, noise_dims) for architecture in graphs + refused]
    assert ["code" in graph for graph in manifest["graphs"]] == [False] * len(graphs) + [True] * len(refused)
    graphs, refused = nerfacto_architectures({name: model_architecture(root / "scenes" / f"{scene}.onnx")["coarse"]
                                              for name, scene in (("tcnn", "nerfacto_tcnn"), ("torch", "nerfacto_torch"),
                                                                  ("ngp", "ngp"))})
    nerfacto = [graph_golden(architecture, scenes["nerfacto_tcnn"].render_field.config.noise_dims)
                for architecture in graphs + refused]
    assert ["code" in graph for graph in nerfacto] == [False] * len(graphs) + [True] * len(refused)
    manifest["graphs"] += nerfacto
    manifest["scales"] = scales_golden()
    manifest["pruned"] = pruned_goldens(root)
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> Path:
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the browser reveal's Node tests need Node 20 (CI installs it)")
    if not (WEB / "node_modules").is_dir():
        pytest.skip("web/node_modules is missing: run `npm ci` in web/ first (CI does)")
    root = tmp_path_factory.mktemp("web_fixtures")
    write_fixtures(root)
    return root


def expected_javascript_cases(manifest: dict) -> dict[str, set[str]]:
    """Every top-level test web/test/ must run on these fixtures, by file: the names its loops make of the
    manifest (a loop over a key the manifest lacks would run no test and still exit 0)."""
    fixtures, payloads, tampered = manifest["fixtures"], manifest["payloads"], manifest["tampered"]
    graphs = [f"field graph {i}: {'refused (' + g['code'] + ')' if 'code' in g else 'derived'} as Python does: "
              f"{g['architecture'][:100]}" for i, g in enumerate(manifest["graphs"])]
    pruned = [f"{g['model']} pruned to {', '.join(g['outputs'])}" for g in manifest["pruned"]]
    return {
        "fields.test.js": {*graphs, "grid level scales are Python's to the bit for Instant-NGP's per-level scales"},
        "pool.test.js": {*(f"{name}: two workers reveal Python's pixels byte for byte" for name in fixtures),
                         "tiles cut into many small chunks, out of order in two workers, render the same colours as whole",
                         "a worker that dies is left out: the others render on and release does not wait for it",
                         "a worker's refusal is the caller's UserError, and the pool renders on after it"},
        "pruning.test.js": {*(f"{label}: {what}" for label in pruned for what in (
                                "Python's bytes, the fetched outputs alone, fewer nodes",
                                "onnxruntime-web computes the whole graph's values")),
                            "a renderer's sessions are each of the graph pruned to one network's outputs",
                            "a reveal opens sessions for the networks its tiles name only, and reveals Python's pixels",
                            "a pool's workers are sent each network's pruned model alone, and reveal Python's pixels"},
        "reveal.test.js": {*(f"{name}: {what}" for name in fixtures for what in (
                               "rays, noise and colours against Python",
                               "the revealed 8-bit pixels are Python's byte for byte")),
                           *(f"{name}: the payload's bytes are noisenerf-reveal's" for name in payloads),
                           *(f"refused as noisenerf-reveal refuses it: {t['case']} ({t['code']})" for t in tampered),
                           "summary of the measured differences"},
    }


def test_the_javascript_reveal_matches_the_python_runtime(fixtures, tmp_path):
    """`node --test` exits 0 and ran exactly the cases the manifest makes, every one passed and none skipped."""
    events = tmp_path / "events.jsonl"
    result = subprocess.run(["node", "--test", "--test-reporter=spec", "--test-reporter-destination=stdout",
                             f"--test-reporter={REPO / 'tests' / 'node' / 'events_reporter.mjs'}",
                             f"--test-reporter-destination={events}", "test/"], cwd=WEB, capture_output=True,
                            text=True, env={**os.environ, "NOISENERF_WEB_FIXTURES": str(fixtures)}, timeout=900)
    print(result.stdout[-20000:])
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-3000:]
    ran: dict[str, set[str]] = {}
    for line in events.read_text().splitlines():
        case = json.loads(line)
        if case["nesting"] == 0:
            assert case["passed"] and case["skip"] is False and case["todo"] is False, case
            if case["name"] != case["file"]:  # a file is its own case only when it holds none (refusals.js)
                ran.setdefault(Path(case["file"]).name, set()).add(case["name"])
    expected = expected_javascript_cases(json.loads((fixtures / "manifest.json").read_text()))
    assert ran == expected
    # the manifest's own loops are not empty: every layout's fixture, tampered copies, graphs, payloads
    assert min(len(names) for names in expected.values()) >= 4 and len(expected["reveal.test.js"]) > 60


if __name__ == "__main__":
    target = Path(sys.argv[1])
    target.mkdir(parents=True, exist_ok=True)
    print(json.dumps(write_fixtures(target)["tampered"], indent=1))
