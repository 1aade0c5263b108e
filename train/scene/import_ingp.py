"""`noisenerf import-ingp`: an Instant-NGP NeRF snapshot (`.ingp`, `.msgpack`) -> a `hashgrid` scene directory.

What the file is (NVlabs/instant-ngp @ abe236e, tiny-cuda-nn as it vendors it; docs/field-kinds.md keeps the
list with line numbers):

- The testbed's network config (configs/nerf/base.json merged with its parents) plus a `snapshot` object,
  serialised by nlohmann's `to_msgpack`; `.ingp` through zstr, which deflates as **gzip** (window bits 15 + 16)
  and inflates gzip, zlib or raw alike; `.msgpack` raw (src/testbed.cu:5288–5355 save, 271–300 load).
- `snapshot`: `version` ≥ 1 and `mode` (`nerf`, `sdf`, `image`, `volume`; 5292–5293, 5359–5371), tiny-cuda-nn's
  `Trainer::serialize` (`n_params`, `params_type` "__half" or "float", `params_binary`: the inference
  parameters, flat), `aabb` ({min, max}), `background_color`, and `nerf`: `aabb_scale`, `dataset` (every
  training camera: `xforms[i].start` in Instant-NGP's frame, 3 rows of 4 (tiny-cuda-nn's vec_json.h), `metadata[i]` with `resolution`, `focal_length` in
  pixels, `principal_point` as a fraction of the image, `lens`; its `scale`, `offset`, `n_extra_learnable_dims`:
  include/neural-graphics-primitives/json_binding.h:100–175).
- The network (include/neural-graphics-primitives/nerf_network.h:80–105, 357–372): parameters in the order
  density MLP, colour MLP, position encoding (the hash grid), direction encoding (none). The density MLP reads
  the grid's L·F features (aligned to 16) and gives 16 outputs, raw density first; the colour MLP reads
  [those 16 outputs ‖ SH(d), 16 values at degree 4] and gives 3 (its output padded to 16 rows). tiny-cuda-nn's
  MLPs have no biases; each matrix is row-major (out, in). σ = exp(raw) (nerf_device.cuh:235–243), colour =
  logistic for LDR data (testbed_nerf.cu:2354). The grid reads (p − aabb.min)/(aabb.max − aabb.min)
  (nerf_device.cuh:266–271) and has tiny-cuda-nn's level layout, as the `hashgrid` kind; `per_level_scale`
  is in the config (testbed.cu:4245–4252 writes it there when the config left it out).
- Cameras: Instant-NGP's frame is the NeRF frame scaled by `scale`, offset by `offset`, its axes cycled
  xyz ← yzx and its camera y and z flipped (nerf_loader.h:95–119); rays go through pixel centres (+0.5).

The scene is a `hashgrid` scene in Instant-NGP's frame: the density MLP gains one output, a copy of the raw
density, so that the kind's geometric feature is Instant-NGP's 16 density outputs and the colour MLP's first
matrix is its own with the columns reordered to [SH ‖ density outputs]; all biases are zero. float16 weights
become float32 exactly. Renders march noisenerf's occupancy grid, built from the field as for a fit, not
Instant-NGP's cascades (its step 1/1024 and cone angle are not reproduced; the field is).

Refused in one line: other testbed modes, encodings, MLPs and activations than these, per-image latent
codes, HDR (linear) datasets, and any length, number or structure that disagrees with the config. The file is
read with bounded memory: at most MAX_SNAPSHOT_BYTES are inflated, and msgpack's own limits follow the bytes
actually present, so no number in the file sets an allocation.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import torch

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import field_kind
from noisenerf.runtime.fields.hashgrid import grid_levels
from noisenerf.runtime.lens import Lens
from noisenerf.runtime.limits import MAX_HASH_LEVELS, MAX_LOG2_TABLE, checked_float, checked_int, checked_list
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import SamplingConfig
from noisenerf.train.scene.captures import read_capture
from noisenerf.train.scene.hashgrid import HashGridConfig, HashGridField
from noisenerf.train.scene.occupancy import OccupancyConfig, build_occupancy_grid
from noisenerf.train.scene.scene import Scene, SceneConfig, check_scene_output

MAX_SNAPSHOT_BYTES = 512 * 2 ** 20  # inflated; Instant-NGP's largest configs write a few hundred MB
READ_CHUNK = 2 ** 20
MLP_TYPES = ("FullyFusedMLP", "CutlassMLP")
TCNN_ALIGNMENT = 16  # both MLP types align their inputs and outputs to 16 (tiny-cuda-nn's REQUIRED_ALIGNMENT)
DENSITY_OUTPUTS = 16  # nerf_network.h: the density network's n_output_dims when the config names none
SH_DEGREE = 4
RENDER_SAMPLES = 512  # uniform samples per ray over [near, far] (the grid skips the empty ones)
NEAR = 0.05
# NeRF frame → Instant-NGP frame: row i of the result is row CYCLE[i] of the scaled matrix (xyz ← yzx)
CYCLE = (1, 2, 0)


def inflate(raw: bytes, source: str) -> bytes:
    """A snapshot's msgpack bytes: gzip or zlib inflated as zstr reads them (a raw stream passes as it is),
    refusing more than MAX_SNAPSHOT_BYTES without inflating further."""
    if raw[:2] != b"\x1f\x8b" and not (len(raw) >= 2 and raw[0] & 0x0F == 8 and (raw[0] << 8 | raw[1]) % 31 == 0):
        return raw
    stream, parts, size = zlib.decompressobj(wbits=47), [], 0
    try:
        for start in range(0, len(raw), READ_CHUNK):
            data = raw[start:start + READ_CHUNK]
            while data:
                part = stream.decompress(data, MAX_SNAPSHOT_BYTES + 1 - size)
                size += len(part)
                parts.append(part)
                if size > MAX_SNAPSHOT_BYTES:
                    raise UserError(f"{source}: inflates to more than {MAX_SNAPSHOT_BYTES} bytes; not a snapshot "
                                    "this importer reads")
                data = stream.unconsumed_tail
        if not stream.eof:
            raise UserError(f"{source}: the compressed stream ends early (a truncated snapshot)")
    except zlib.error as error:
        raise UserError(f"{source}: not a readable compressed snapshot ({error})") from None
    return b"".join(parts)


def read_snapshot(path: Path) -> dict:
    """The file's network config and snapshot as plain data (module docstring)."""
    import msgpack

    source = str(path)
    if not path.is_file():
        raise UserError(f"{source} not found")
    if path.stat().st_size > MAX_SNAPSHOT_BYTES:
        raise UserError(f"{source}: {path.stat().st_size} bytes, more than a snapshot this importer reads "
                        f"({MAX_SNAPSHOT_BYTES})")
    data = inflate(path.read_bytes(), source)
    try:
        config = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except (msgpack.exceptions.ExtraData, msgpack.exceptions.FormatError, msgpack.exceptions.StackError,
            ValueError, TypeError) as error:
        raise UserError(f"{source}: not an Instant-NGP snapshot (msgpack: {type(error).__name__})") from None
    if not isinstance(config, dict) or not isinstance(config.get("snapshot"), dict):
        raise UserError(f"{source}: not an Instant-NGP snapshot (no 'snapshot' object)")
    return config


def entry(data: dict, key: str, kind, where: str):
    value = data.get(key) if isinstance(data, dict) else None
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise UserError(f"{where}: '{key}' is missing or not {getattr(kind, '__name__', kind)}")
    return value


def checked_mlp(config: dict, key: str, source: str) -> dict:
    """A tiny-cuda-nn MLP config: its type, ReLU hidden layers, no output activation. -> its width and depth."""
    network = entry(config, key, dict, source)
    where = f"{source}: {key}"
    if network.get("otype") not in MLP_TYPES:
        raise UserError(f"{where} is a {network.get('otype')!r}; only {' and '.join(MLP_TYPES)} import")
    if network.get("activation", "ReLU") != "ReLU" or network.get("output_activation", "None") != "None":
        raise UserError(f"{where}: activation {network.get('activation')!r} / output "
                        f"{network.get('output_activation')!r}; only ReLU with no output activation imports")
    return {"width": checked_int(network.get("n_neurons"), f"{where} n_neurons", 1, 1024),
            "hidden": checked_int(network.get("n_hidden_layers"), f"{where} n_hidden_layers", 1, 16)}


def checked_encoding(config: dict, source: str, aabb_scale: int) -> dict:
    """The position encoding: tiny-cuda-nn's HashGrid with linear interpolation and its default hash."""
    encoding = entry(config, "encoding", dict, source)
    where = f"{source}: encoding"
    if encoding.get("otype") != "HashGrid":
        raise UserError(f"{where} is {encoding.get('otype')!r}; only HashGrid imports")
    if encoding.get("interpolation", "Linear") != "Linear" or encoding.get("hash", "CoherentPrime") != "CoherentPrime":
        raise UserError(f"{where}: interpolation {encoding.get('interpolation')!r}, hash {encoding.get('hash')!r}; "
                        "only Linear and CoherentPrime import")
    levels = checked_int(encoding.get("n_levels", 16), f"{where} n_levels", 1, MAX_HASH_LEVELS)
    base = checked_int(encoding.get("base_resolution"), f"{where} base_resolution", 1, 4096)
    scale = encoding.get("per_level_scale")
    if scale is None:  # testbed.cu:4245–4252, float32 as there
        scale = float(np.exp(np.float32(np.log(np.float32(2048.0 * aabb_scale / base))) / np.float32(max(levels - 1, 1))))
    return {"levels": levels, "features": checked_int(encoding.get("n_features_per_level", 2), f"{where} features", 1, 8),
            "log2_table": checked_int(encoding.get("log2_hashmap_size", 15), f"{where} log2_hashmap_size", 1,
                                      MAX_LOG2_TABLE),
            "base_resolution": base, "per_level_scale": checked_float(scale, f"{where} per_level_scale", 1.0, 16.0)}


def checked_directions(config: dict, source: str) -> None:
    """The direction encoding: SH of degree 4 on the 3 direction dims (alone, or in a Composite with an
    Identity of the extra dims, of which there must be none)."""
    encoding = entry(config, "dir_encoding", dict, source)
    nested = encoding.get("nested") if encoding.get("otype") == "Composite" else [encoding]
    if not isinstance(nested, list) or not nested or not isinstance(nested[0], dict):
        raise UserError(f"{source}: dir_encoding is not a SphericalHarmonics encoding")
    sh, rest = nested[0], nested[1:]
    if (sh.get("otype") != "SphericalHarmonics" or sh.get("degree") != SH_DEGREE
            or sh.get("n_dims_to_encode", 3) != 3 or any(not isinstance(r, dict) or r.get("otype") != "Identity"
                                                         for r in rest)):
        raise UserError(f"{source}: dir_encoding must be SphericalHarmonics of degree {SH_DEGREE} (with an "
                        "Identity of extra dims); this one is not imported")


def ngp_config(config: dict, source: str) -> tuple[HashGridConfig, tuple[float, ...]]:
    """The scene's field config and its box from the snapshot's network config, all checked."""
    snapshot = config["snapshot"]
    if not isinstance(snapshot.get("version"), int) or snapshot["version"] < 1:
        raise UserError(f"{source}: snapshot version {snapshot.get('version')!r}; Instant-NGP reads version 1 on")
    mode = snapshot.get("mode", "nerf" if "nerf" in snapshot else None)
    if mode != "nerf":
        raise UserError(f"{source}: an Instant-NGP {mode!r} snapshot; only NeRF snapshots import (SDF, image and "
                        "volume testbeds hold no radiance field)")
    nerf = entry(snapshot, "nerf", dict, f"{source}: snapshot")
    aabb_scale = checked_int(nerf.get("aabb_scale", 1), f"{source}: aabb_scale", 1, 128)
    dataset = nerf.get("dataset") if isinstance(nerf.get("dataset"), dict) else {}
    if dataset.get("n_extra_learnable_dims", 0):
        raise UserError(f"{source}: per-image latent codes (n_extra_learnable_dims) are not reproduced")
    if dataset.get("is_hdr", False):
        raise UserError(f"{source}: an HDR dataset (exponential colour activation) is not reproduced")
    encoding = checked_encoding(config, source, aabb_scale)
    density, colour = checked_mlp(config, "network", source), checked_mlp(config, "rgb_network", source)
    if density["hidden"] != 1:
        raise UserError(f"{source}: a density network of {density['hidden']} hidden layers; the hashgrid kind's has 1")
    if config["network"].get("n_output_dims", DENSITY_OUTPUTS) != DENSITY_OUTPUTS:
        raise UserError(f"{source}: a density network of {config['network'].get('n_output_dims')} outputs "
                        f"(expected {DENSITY_OUTPUTS})")
    checked_directions(config, source)
    box = entry(snapshot, "aabb", dict, f"{source}: snapshot")
    corners = [checked_list(box.get(key), f"{source}: aabb {key}", length=3) for key in ("min", "max")]
    aabb = tuple(checked_float(v, f"{source}: aabb", -1e4, 1e4) for v in corners[0] + corners[1])
    if not all(aabb[i] < aabb[i + 3] for i in range(3)):
        raise UserError(f"{source}: an empty aabb {aabb}")
    field = HashGridConfig(**encoding, density_hidden=density["width"], geo_features=DENSITY_OUTPUTS,
                           sh_degree=SH_DEGREE, colour_hidden=colour["width"], colour_layers=colour["hidden"],
                           aabb=aabb)
    field_kind(field.to_dict(), source).checked(field.to_dict(), source)  # the kind's caps: resolutions, table sizes
    return field, aabb


def aligned(n: int) -> int:
    return -(-n // TCNN_ALIGNMENT) * TCNN_ALIGNMENT


def parameter_layout(field: HashGridConfig) -> list[tuple[str, tuple[int, int]]]:
    """Instant-NGP's flat parameters, in order (nerf_network.h:357–372): each matrix (rows, columns) as tiny-cuda-nn
    stores it, padded rows and columns included, then the grid's (rows, features)."""
    width, hidden = field.density_hidden, field.colour_hidden
    layout = [("density.0", (width, aligned(field.position_dims))), ("density.1", (aligned(DENSITY_OUTPUTS), width)),
              ("colour.0", (hidden, aligned(DENSITY_OUTPUTS + 16)))]
    layout += [(f"colour.{i}", (hidden, hidden)) for i in range(1, field.colour_layers)]
    layout += [(f"colour.{field.colour_layers}", (aligned(3), hidden))]
    levels = grid_levels(field.levels, field.log2_table, field.base_resolution, field.per_level_scale)
    return layout + [("grid", (levels.total_rows, field.features))]


def snapshot_parameters(snapshot: dict, field: HashGridConfig, source: str) -> dict[str, np.ndarray]:
    """The flat parameters as float32 arrays by name, their count and byte length checked against the config."""
    layout = parameter_layout(field)
    expected = sum(rows * columns for _, (rows, columns) in layout)
    dtype = {"__half": np.float16, "float": np.float32}.get(snapshot.get("params_type", "__half"))
    if dtype is None:
        raise UserError(f"{source}: params_type {snapshot.get('params_type')!r} (expected __half or float)")
    binary = snapshot.get("params_binary")
    if not isinstance(binary, (bytes, bytearray)):
        raise UserError(f"{source}: the snapshot holds no params_binary")
    if snapshot.get("n_params") != expected or len(binary) != expected * np.dtype(dtype).itemsize:
        raise UserError(f"{source}: {snapshot.get('n_params')!r} parameters in {len(binary)} bytes, but the network "
                        f"config lays out {expected} of {np.dtype(dtype).itemsize} bytes")
    flat = np.frombuffer(binary, dtype=np.dtype(dtype).newbyteorder("<")).astype(np.float32)
    arrays, start = {}, 0
    for name, (rows, columns) in layout:
        arrays[name] = flat[start:start + rows * columns].reshape(rows, columns)
        start += rows * columns
    return arrays


def field_state(arrays: dict[str, np.ndarray], field: HashGridConfig) -> dict[str, torch.Tensor]:
    """Instant-NGP's matrices as the hashgrid kind's layers (module docstring): padded rows and columns dropped,
    the raw density copied into the geometric feature, the colour input reordered, zero biases."""
    density0 = arrays["density.0"][:, :field.position_dims]
    outputs = arrays["density.1"][:DENSITY_OUTPUTS]
    density1 = np.concatenate([outputs[:1], outputs])
    colour0 = arrays["colour.0"][:, :DENSITY_OUTPUTS + 16]
    colours = [np.concatenate([colour0[:, DENSITY_OUTPUTS:], colour0[:, :DENSITY_OUTPUTS]], axis=1)]
    colours += [arrays[f"colour.{i}"] for i in range(1, field.colour_layers)]
    colours.append(arrays[f"colour.{field.colour_layers}"][:3])
    state = {"table": arrays["grid"]}
    for prefix, matrices in (("density_linears", (density0, density1)), ("colour_linears", colours)):
        for i, matrix in enumerate(matrices):
            state[f"{prefix}.{i}.weight"] = matrix
            state[f"{prefix}.{i}.bias"] = np.zeros(len(matrix), np.float32)
    return {name: torch.from_numpy(np.ascontiguousarray(value)) for name, value in state.items()}


def to_ngp_frame(c2w: np.ndarray, scale: float, offset: np.ndarray) -> np.ndarray:
    """A NeRF-frame camera-to-world (OpenGL axes) in Instant-NGP's frame, keeping OpenGL camera axes:
    rotation rows cycled, position scaled, offset and cycled (nerf_loader.h:95–119). (4, 4) -> (4, 4)."""
    moved = np.array(c2w, np.float64)
    moved[:3, 3] = moved[:3, 3] * scale + offset
    result = np.eye(4)
    result[:3] = moved[list(CYCLE), :]
    return result


def snapshot_cameras(dataset: dict, source: str) -> tuple[Camera, ...]:
    """The training cameras the snapshot carries (Instant-NGP's frame and camera axes: x right, y down,
    looking along +z), as noisenerf cameras (y and z flipped back)."""
    xforms, metadata = dataset.get("xforms"), dataset.get("metadata")
    if not isinstance(xforms, list) or not isinstance(metadata, list) or not xforms or len(xforms) != len(metadata):
        raise UserError(f"{source}: the snapshot's dataset lists no cameras; give the capture with --data")
    cameras = []
    for k, (xform, meta) in enumerate(zip(xforms, metadata)):
        where = f"{source}: camera {k}"
        start = checked_list(xform.get("start") if isinstance(xform, dict) else None, f"{where} xform", length=3)
        matrix = np.array([[checked_float(v, f"{where} xform", -1e6, 1e6)
                            for v in checked_list(row, f"{where} xform", length=4)] for row in start])
        c2w = np.eye(4)
        c2w[:3] = matrix * np.array([1.0, -1.0, -1.0, 1.0])
        width, height = (checked_int(v, f"{where} resolution", 1, 65536)
                         for v in checked_list(entry(meta, "resolution", list, where), f"{where} resolution", length=2))
        fx, fy = (checked_float(v, f"{where} focal_length", 1e-3, 1e7)
                  for v in checked_list(entry(meta, "focal_length", list, where), f"{where} focal_length", length=2))
        px, py = (checked_float(v, f"{where} principal_point", -100, 100) for v in checked_list(
            entry(meta, "principal_point", list, where), f"{where} principal_point", length=2))
        lens = ngp_lens(meta.get("lens"), where)
        cameras.append(Camera.from_dict({"c2w": c2w.tolist(), "width": width, "height": height, "fx": fx, "fy": fy,
                                         "cx": px * width, "cy": py * height,
                                         **({"lens": lens.to_dict()} if lens else {})}))
    return tuple(cameras)


def ngp_lens(lens, where: str) -> Lens | None:
    """Instant-NGP's lens object (json_binding.h:40–100) as a noisenerf lens: OpenCV (k1 k2 p1 p2), OpenCV fisheye
    (k1..k4); other models refused."""
    if not lens or not isinstance(lens, dict) or not any(key in lens for key in ("k1", "ftheta_p0", "latlong",
                                                                                 "equirectangular", "orthographic")):
        return None
    if "k1" not in lens:
        raise UserError(f"{where}: a {next(key for key in lens)} lens is not reproduced")
    values = {key: checked_float(lens.get(key, 0.0), f"{where} lens {key}", -1000, 1000)
              for key in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if lens.get("is_fisheye"):
        return Lens.from_dict({"model": "fisheye", **values, "p1": 0.0, "p2": 0.0})
    return Lens.from_dict({"model": "opencv", **values, "k3": 0.0, "k4": 0.0})


def capture_cameras(data: Path, dataset: dict, source: str) -> tuple[Camera, ...]:
    """The capture's cameras (its transforms.json, read as the fit reads it) moved into Instant-NGP's frame with
    the scale and offset the snapshot's dataset records."""
    scale = checked_float(dataset.get("scale"), f"{source}: dataset scale", 1e-6, 1e6)
    offset = np.array([checked_float(v, f"{source}: dataset offset", -1e6, 1e6)
                       for v in checked_list(dataset.get("offset"), f"{source}: dataset offset", length=3)])
    if dataset.get("from_mitsuba"):
        raise UserError(f"{source}: a Mitsuba-frame dataset is not reproduced")
    cameras = []
    for frame in read_capture(data).frames:
        stated = frame.camera()
        cameras.append(Camera.from_dict({**stated.to_dict(), "c2w": to_ngp_frame(frame.c2w, scale, offset).tolist()}))
    return tuple(cameras)


def render_config(snapshot: dict, cameras: tuple[Camera, ...], aabb: tuple[float, ...], source: str) -> RenderConfig:
    """Uniform samples from NEAR to the farthest box corner any camera sees, over the snapshot's background."""
    corners = np.array([[aabb[i + 3 * bit] for i, bit in enumerate(bits)]
                        for bits in np.ndindex(2, 2, 2)], np.float64)
    positions = np.array([np.asarray(c.c2w, np.float64)[:3, 3] for c in cameras])
    far = float(np.linalg.norm(positions[:, None] - corners[None], axis=-1).max())
    background = snapshot.get("background_color", [0.0, 0.0, 0.0, 0.0])
    rgb = tuple(min(max(checked_float(v, f"{source}: background_color", -1e3, 1e3), 0.0), 1.0)
                for v in checked_list(background, f"{source}: background_color", length=4)[:3])
    return RenderConfig(SamplingConfig(NEAR, max(far, 2 * NEAR), RENDER_SAMPLES), background=rgb, pixel_center=0.5)


def import_ingp(snapshot_path: Path, out_dir: Path, data: Path | None = None, force: bool = False) -> Scene:
    """Convert an Instant-NGP NeRF snapshot into a scene directory (module docstring): everything checked before
    out_dir is written; cameras from `data`'s transforms.json when given, else the snapshot's own."""
    snapshot_path, out_dir = Path(snapshot_path), Path(out_dir)
    check_scene_output(out_dir, force)
    source = str(snapshot_path)
    config = read_snapshot(snapshot_path)
    field_config, aabb = ngp_config(config, source)
    snapshot = config["snapshot"]
    arrays = snapshot_parameters(snapshot, field_config, source)
    field = HashGridField(field_config)
    field.load_state_dict(field_state(arrays, field_config))
    dataset = snapshot["nerf"].get("dataset") if isinstance(snapshot["nerf"].get("dataset"), dict) else {}
    cameras = capture_cameras(Path(data), dataset, source) if data is not None else snapshot_cameras(dataset, source)
    render = render_config(snapshot, cameras, aabb, source)
    step = (render.sampling.far - render.sampling.near) / render.sampling.n_samples
    resolution = OccupancyConfig().saved_resolution  # a fit's grid, not Instant-NGP's 128³ cascades
    scene_config = SceneConfig(coarse=field_config, fine=None, n_coarse=0, n_importance=0, render=render, aabb=aabb,
                               grid_resolution=resolution, cameras=cameras, source="instant-ngp")
    grid = build_occupancy_grid(field, aabb, resolution, step_size=step)
    scene = Scene(scene_config, field, None, grid)
    scene.publish(out_dir, source=snapshot_path, force=force)
    return scene

