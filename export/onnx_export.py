"""Scene directory -> one self-contained ONNX model file for recipients.

The graph holds the scene's frozen fields: inputs `points` (n, 3), `viewdirs` (n, 3), `noise`
(n, noise_dims), outputs `rgb` (n, 3) and `sigma` (n,) of the render network (the fine one if there is
one) and, for a scene with a fine network, `rgb_coarse` and `sigma_coarse` of the coarse one on the same
inputs: the runtime needs it for nerf-pytorch's hierarchical render and for bundles hidden through it
(the paper's method). n is dynamic. The encodings (γ, or the hash grid and SH) are inside the graph and
the noise is added to them exactly as the field kind's torch module does; rays, sampling, skipping and
compositing stay in numpy on the host (noisenerf.runtime), so a torch render and an onnxruntime render
differ only by field evaluation.

The graph is written node for node from runtime.fields.field_graph, a pure function of the architecture
that the reveal rebuilds to check a model's graph (so it is not traced: a tracer's output may change with
the torch version, and the runtime could not predict it). The initializers are the scene's weights under
the scene's names (coarse.pts_linears.0.weight, ...) in nn.Linear's (out, in) layout, which
Gemm(transB=1) reads as is, plus the graph's few constants; the runtime recomputes the scene fingerprint
from the weights. The output is checked with onnx.checker (full_check), against torch on probe batches
and by the runtime's own graph and fingerprint checks before anything is written.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import time
from dataclasses import dataclass

import numpy as np
import onnx

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import check_output_path, write_bytes
from noisenerf.runtime.fingerprint import weights_fingerprint
from noisenerf.runtime.model import ModelMetadata
from noisenerf.runtime.onnx_file import ModelFile, parse_model
from noisenerf.runtime.fields import field_graph
from noisenerf.runtime.graph import IR_VERSION, Port, check_graph
from noisenerf.runtime.session import OnnxField
from noisenerf.train.scene.field_kinds import Field
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.scene import Scene, load_scene

PROBE_TOLERANCE = 1e-5  # see probe_parity
FLOAT32_SLACK = 2.0  # onnxruntime may be this many times less exact than torch float32, plus the tolerance
PROBE_POINTS = 1024
PROBE_NOISE_SCALES = {"zero": 0.0, "normal": 1.0, "huge": 1e3}


def fields_to_onnx(scene: Scene, metadata: ModelMetadata) -> onnx.ModelProto:
    """The ONNX model of the scene's fields, node for node runtime.fields.field_graph of its architecture
    (the graph the reveal checks), with the scene's weights as named initializers."""
    graph = field_graph(metadata.architecture, metadata.noise_dims)
    weights = scene.weight_arrays()
    if set(weights) != set(graph.weights):
        raise UserError(f"export refused: the scene's weights {sorted(set(weights) ^ set(graph.weights))[:3]} "
                        "disagree with its architecture")

    def port(value: Port) -> onnx.ValueInfoProto:
        return onnx.helper.make_tensor_value_info(value.name, value.elem_type, list(value.shape))

    nodes = [onnx.helper.make_node(node.op, list(node.inputs), list(node.outputs), name=f"node{i}",
                                   **dict(node.attributes)) for i, node in enumerate(graph.nodes)]
    initializers = [onnx.numpy_helper.from_array(np.ascontiguousarray(values), name)
                    for name, values in {**weights, **graph.constants}.items()]
    model = onnx.helper.make_model(
        onnx.helper.make_graph(nodes, "noisenerf", [port(p) for p in graph.inputs], [port(p) for p in graph.outputs],
                               initializers),
        opset_imports=[onnx.helper.make_opsetid("", graph.opset)], producer_name="noisenerf")
    model.ir_version = IR_VERSION
    return model


def scene_metadata(scene: Scene) -> ModelMetadata:
    widths = {field.config.noise_dims for field in scene.fields().values()}
    if len(widths) != 1:
        raise UserError(f"export refused: the coarse and fine networks take noise of different widths {sorted(widths)}")
    return ModelMetadata(fingerprint=scene.fingerprint(), architecture=scene.config.architecture(),
                         noise_dims=widths.pop(), render_config=scene.config.render, hierarchy=scene.hierarchy,
                         cameras=tuple(scene.config.cameras), grid=scene.grid)


def attach_metadata(model: onnx.ModelProto, metadata: ModelMetadata) -> None:
    """Replace the model's metadata_props with ours."""
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, metadata.metadata_props())


def probe_inputs(aabb, noise_dims: int, seed: int) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, points (n, 3), viewdirs (n, 3), noise (n, noise_dims)) per noise case: random points in the
    box, random unit directions; noise 0, N(0, 1), and ±1e3 (random signs, far beyond any trained noise)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(aabb, np.float32)[:3], np.asarray(aabb, np.float32)[3:]
    cases = []
    for name, scale in PROBE_NOISE_SCALES.items():
        points = (lo + rng.random((PROBE_POINTS, 3), dtype=np.float32) * (hi - lo)).astype(np.float32)
        viewdirs = rng.normal(size=(PROBE_POINTS, 3)).astype(np.float32)
        viewdirs /= np.linalg.norm(viewdirs, axis=1, keepdims=True)
        shape = (PROBE_POINTS, noise_dims)
        noise = rng.normal(size=shape) if name == "normal" else rng.choice([-1.0, 1.0], size=shape)
        cases.append((name, points, viewdirs, (scale * noise).astype(np.float32)))
    return cases


def scaled_error(reference: np.ndarray, candidate: np.ndarray) -> float:
    """max |Δ| / max(1, |reference|): absolute for rgb and ordinary densities, relative for densities
    above 1, where float32 cannot even represent a 1e-5 step (huge noise gives σ in the hundreds)."""
    return float(np.max(np.abs(candidate - reference) / np.maximum(1.0, np.abs(reference)), initial=0.0))


@dataclass(frozen=True)
class CaseParity:
    """One probe case: both float32 backends measured against a float64 evaluation of the same field."""

    name: str
    network: str
    max_abs_diff: float  # |onnxruntime − torch| over rgb and sigma
    torch_error: float  # scaled error of torch float32 vs float64
    onnx_error: float  # scaled error of onnxruntime vs float64

    @property
    def passed(self) -> bool:
        """False for NaN too."""
        return self.onnx_error <= PROBE_TOLERANCE + FLOAT32_SLACK * self.torch_error

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "passed": self.passed}


def probe_parity(field: Field, onnx_field: OnnxField, aabb, seed: int, network: str = "render"
                 ) -> tuple[CaseParity, ...]:
    """Compare one network of the exported graph with torch on the probe batches.

    The check is against float64, not against torch float32 alone: with ±1e3 noise the encoded inputs
    are ~1e3 and float32 GEMMs summed in another order (MKL vs MLAS) legitimately differ by 1e-5 to 4e-5;
    torch float32 itself is that far from the exact value. So onnxruntime passes when its error is within
    PROBE_TOLERANCE + FLOAT32_SLACK × torch's own; for noise 0 and N(0, 1), where torch's error is ~1e-7,
    that is an error below ~1e-5. A real export fault (weights, encoding, noise port) errs by ~1e-1.
    """
    float32_fn = numpy_field(field)
    float64_fn = numpy_field(copy.deepcopy(field).double())
    cases = []
    for name, points, viewdirs, noise in probe_inputs(aabb, field.config.noise_dims, seed):
        exact, torch32, onnx32 = (fn(points, viewdirs, noise) for fn in (float64_fn, float32_fn, onnx_field))
        cases.append(CaseParity(
            name=name, network=network,
            max_abs_diff=max(float(np.max(np.abs(a - b), initial=0.0)) for a, b in zip(torch32, onnx32)),
            torch_error=max(scaled_error(e, t) for e, t in zip(exact, torch32)),
            onnx_error=max(scaled_error(e, o) for e, o in zip(exact, onnx32)),
        ))
    return tuple(cases)


def check_as_runtime(file: ModelFile, metadata: ModelMetadata) -> None:
    """Refuse a model that the runtime would refuse: its graph, read back, is not field_graph's, or its
    weights miss the scene fingerprint."""
    weights = check_graph(file, field_graph(metadata.architecture, metadata.noise_dims), file.source)
    if weights_fingerprint(weights, metadata.architecture) != metadata.fingerprint:
        raise UserError("export refused: the graph's initializers do not reproduce the scene's weights")


def export_scene(scene_dir: str | os.PathLike, out_path: str | os.PathLike, probe_seed: int = 0,
                 force: bool = True) -> dict:
    """Export a scene directory's fields to `out_path`; nothing is written unless onnx.checker, the
    torch-vs-onnxruntime probe of every network and the fingerprint check all pass. Returns a report
    (bytes, seconds, parity, opset)."""
    start = time.perf_counter()
    check_output_path(out_path, force=force)
    scene = load_scene(scene_dir)
    metadata = scene_metadata(scene)
    model = fields_to_onnx(scene, metadata)
    attach_metadata(model, metadata)
    onnx.checker.check_model(model, full_check=True)
    data = model.SerializeToString()
    file = parse_model(data, "the exported graph")
    onnx_field = OnnxField(file, threads=1)
    probe = [case for name, field in scene.fields().items()
             for case in probe_parity(field, onnx_field.network(name), scene.config.aabb, probe_seed, name)]
    for case in probe:
        if not case.passed:
            raise UserError(f"export refused: on the '{case.name}' noise probe of the {case.network} network "
                            f"onnxruntime is off by {case.onnx_error:.3g}, torch float32 by "
                            f"{case.torch_error:.3g} (allowed: {PROBE_TOLERANCE:g} + {FLOAT32_SLACK:g}x torch's)")
    check_as_runtime(file, metadata)
    write_bytes(out_path, data, replace=force)
    return {"model": str(out_path), "fingerprint": scene.fingerprint(), "bytes": len(data),
            "seconds": round(time.perf_counter() - start, 3), "opset": model.opset_import[0].version, "networks": list(scene.fields()),
            "max_abs_diff": max(case.max_abs_diff for case in probe), "probe": [case.to_dict() for case in probe]}
