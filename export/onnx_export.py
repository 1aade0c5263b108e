"""Scene directory -> one self-contained ONNX model file for recipients.

The graph holds the scene's frozen fields: inputs `points` (n, 3), `viewdirs` (n, 3), `noise`
(n, noise_dims), outputs `rgb` (n, 3) and `sigma` (n,) of the render network (the fine one if there is
one, as before the coarse network was exported) and, for a scene with a fine network, `rgb_coarse` and
`sigma_coarse` of the coarse one on the same inputs: the runtime needs it for nerf-pytorch's hierarchical
render and for bundles hidden through it (the paper's method). n is dynamic. Positional encoding is
inside the graph and the noise is added to [γ(x) ‖ γ(d)] exactly as NeRFField.forward does; rays,
sampling, skipping and compositing stay in numpy on the host (noisenerf.runtime), so a torch render
and an onnxruntime render differ only by field evaluation.

The initializers are the scene's weights under the scene's names (coarse.pts_linears.0.weight, ...) in
nn.Linear's (out, in) layout, which Gemm(transB=1) reads as is: the runtime recomputes the scene
fingerprint from them. They are traced as graph inputs (keep_initializers_as_inputs), which turns off the
exporter's merging of equal-valued initializers (it would drop one of two equal tensors, and its name),
and are then removed from the inputs again. The export refuses to write a graph whose initializers do
not reproduce the scene fingerprint.

Exporter: torch's TorchScript exporter (`dynamo=False`). In torch 2.13 it is deprecated but present; it
exports this MLP in under a second, deterministically (same weights -> same bytes), and its graph runs
as fast in onnxruntime as the dynamo exporter's, which takes ~10 s per export here. The output is
checked with onnx.checker (full_check) and against torch on probe batches before anything is written.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
import io
import os
import time
import warnings
from dataclasses import dataclass

import numpy as np
import onnx
import torch
from torch import nn

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import atomic_output, check_output_path
from noisenerf.runtime.fingerprint import weights_fingerprint
from noisenerf.runtime.model import ModelMetadata
from noisenerf.runtime.onnx_file import parse_model
from noisenerf.runtime.session import COARSE_OUTPUT_NAMES, INPUT_NAMES, OUTPUT_NAMES, OnnxField
from noisenerf.train.scene.field import NeRFField
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.scene import Scene, load_scene

OPSET = 17
PROBE_TOLERANCE = 1e-5  # see probe_parity
FLOAT32_SLACK = 2.0  # onnxruntime may be this many times less exact than torch float32, plus the tolerance
PROBE_POINTS = 1024
PROBE_NOISE_SCALES = {"zero": 0.0, "normal": 1.0, "huge": 1e3}


class SceneFields(nn.Module):
    """The scene's networks as one module to trace: (points, viewdirs, noise) -> rgb, sigma of the render
    network, then rgb_coarse, sigma_coarse where there is a fine network. Its submodules are named
    `coarse` and `fine`, so parameter names are the scene's weight names."""

    def __init__(self, coarse: NeRFField, fine: NeRFField | None):
        super().__init__()
        self.coarse, self.fine = coarse, fine

    @property
    def output_names(self) -> tuple[str, ...]:
        return OUTPUT_NAMES + (COARSE_OUTPUT_NAMES if self.fine is not None else ())

    def forward(self, points: torch.Tensor, viewdirs: torch.Tensor, noise: torch.Tensor):
        if self.fine is None:
            return self.coarse(points, viewdirs, noise)
        return (*self.fine(points, viewdirs, noise), *self.coarse(points, viewdirs, noise))


def fields_to_onnx(fields: SceneFields, opset: int = OPSET) -> onnx.ModelProto:
    """Trace the fields (on the CPU, as load_scene leaves them) with their noise port into an in-memory
    ONNX model with a dynamic batch axis, weights as named initializers."""
    example = (torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2, fields.coarse.config.noise_dims))
    # torch < 2.5 has no `dynamo` switch and only the TorchScript exporter
    exporter = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
    names = INPUT_NAMES + fields.output_names
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # the TorchScript exporter's deprecation notice is ours to track, not the user's to read
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(fields.eval(), example, buffer, input_names=list(INPUT_NAMES),
                          output_names=list(fields.output_names), opset_version=opset,
                          dynamic_axes={name: {0: "n"} for name in names}, keep_initializers_as_inputs=True,
                          **exporter)
    model = onnx.load_from_string(buffer.getvalue())
    weights = {tensor.name for tensor in model.graph.initializer}
    inputs = [value for value in model.graph.input if value.name not in weights]
    del model.graph.input[:]
    model.graph.input.extend(inputs)
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


def probe_parity(field: NeRFField, onnx_field: OnnxField, aabb, seed: int, network: str = "render"
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


def check_initializers(data: bytes, metadata: ModelMetadata) -> None:
    """Refuse a graph whose initializers, read back as the runtime reads them, miss the scene fingerprint."""
    source = "the exported graph"
    if weights_fingerprint(parse_model(data, source).weights(source), metadata.architecture) != metadata.fingerprint:
        raise UserError("export refused: the graph's initializers do not reproduce the scene's weights")


def export_scene(scene_dir: str | os.PathLike, out_path: str | os.PathLike, probe_seed: int = 0,
                 force: bool = True) -> dict:
    """Export a scene directory's fields to `out_path`; nothing is written unless onnx.checker, the
    torch-vs-onnxruntime probe of every network and the fingerprint check all pass. Returns a report
    (bytes, seconds, parity, opset)."""
    start = time.perf_counter()
    check_output_path(out_path, force=force)
    scene = load_scene(scene_dir)
    model = fields_to_onnx(SceneFields(scene.coarse, scene.fine))
    metadata = scene_metadata(scene)
    attach_metadata(model, metadata)
    onnx.checker.check_model(model, full_check=True)
    data = model.SerializeToString()
    onnx_field = OnnxField(data, threads=1)
    probe = [case for name, field in scene.fields().items()
             for case in probe_parity(field, onnx_field.network(name), scene.config.aabb, probe_seed, name)]
    for case in probe:
        if not case.passed:
            raise UserError(f"export refused: on the '{case.name}' noise probe of the {case.network} network "
                            f"onnxruntime is off by {case.onnx_error:.3g}, torch float32 by "
                            f"{case.torch_error:.3g} (allowed: {PROBE_TOLERANCE:g} + {FLOAT32_SLACK:g}x torch's)")
    check_initializers(data, metadata)
    with atomic_output(out_path) as tmp:
        tmp.write_bytes(data)
    return {"model": str(out_path), "fingerprint": scene.fingerprint(), "bytes": len(data),
            "seconds": round(time.perf_counter() - start, 3), "opset": OPSET, "networks": list(scene.fields()),
            "max_abs_diff": max(case.max_abs_diff for case in probe), "probe": [case.to_dict() for case in probe]}
