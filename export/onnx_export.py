"""Scene directory -> one self-contained ONNX model file for recipients.

The graph is the frozen render field alone (the fine network if there is one): inputs `points` (n, 3),
`viewdirs` (n, 3), `noise` (n, noise_dims), outputs `rgb` (n, 3) and `sigma` (n,), n dynamic. Positional
encoding is inside the graph and the noise is added to [γ(x) ‖ γ(d)] exactly as NeRFField.forward does;
rays, sampling, skipping and compositing stay in numpy on the host (noisenerf.runtime), so a torch render
and an onnxruntime render differ only by field evaluation.

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

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import atomic_output, check_output_path
from noisenerf.runtime.model import ModelMetadata
from noisenerf.runtime.session import INPUT_NAMES, OUTPUT_NAMES, OnnxField
from noisenerf.train.field import NeRFField
from noisenerf.train.renderer import numpy_field
from noisenerf.train.scene import Scene, load_scene

OPSET = 17
PROBE_TOLERANCE = 1e-5  # see probe_parity
FLOAT32_SLACK = 2.0  # onnxruntime may be this many times less exact than torch float32, plus the tolerance
PROBE_POINTS = 1024
PROBE_NOISE_SCALES = {"zero": 0.0, "normal": 1.0, "huge": 1e3}


def field_to_onnx(field: NeRFField, opset: int = OPSET) -> onnx.ModelProto:
    """Trace the field (on the CPU, as load_scene leaves it) with its noise port into an in-memory ONNX
    model with a dynamic batch axis."""
    example = (torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2, field.config.noise_dims))
    # torch < 2.5 has no `dynamo` switch and only the TorchScript exporter
    exporter = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # the TorchScript exporter's deprecation notice is ours to track, not the user's to read
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(field.eval(), example, buffer, input_names=list(INPUT_NAMES),
                          output_names=list(OUTPUT_NAMES), opset_version=opset,
                          dynamic_axes={name: {0: "n"} for name in INPUT_NAMES + OUTPUT_NAMES}, **exporter)
    return onnx.load_from_string(buffer.getvalue())


def scene_metadata(scene: Scene) -> ModelMetadata:
    field = scene.render_field.config
    return ModelMetadata(fingerprint=scene.fingerprint(), field=field.to_dict(), noise_dims=field.noise_dims,
                         render_config=scene.config.render, cameras=tuple(scene.config.cameras), grid=scene.grid)


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
    max_abs_diff: float  # |onnxruntime − torch| over rgb and sigma
    torch_error: float  # scaled error of torch float32 vs float64
    onnx_error: float  # scaled error of onnxruntime vs float64

    @property
    def passed(self) -> bool:
        """False for NaN too."""
        return self.onnx_error <= PROBE_TOLERANCE + FLOAT32_SLACK * self.torch_error

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "passed": self.passed}


def probe_parity(field: NeRFField, onnx_field: OnnxField, aabb, seed: int) -> tuple[CaseParity, ...]:
    """Compare the exported graph with torch on the probe batches.

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
            name=name,
            max_abs_diff=max(float(np.max(np.abs(a - b), initial=0.0)) for a, b in zip(torch32, onnx32)),
            torch_error=max(scaled_error(e, t) for e, t in zip(exact, torch32)),
            onnx_error=max(scaled_error(e, o) for e, o in zip(exact, onnx32)),
        ))
    return tuple(cases)


def export_scene(scene_dir: str | os.PathLike, out_path: str | os.PathLike, probe_seed: int = 0,
                 force: bool = True) -> dict:
    """Export a scene directory's render field to `out_path`; nothing is written unless onnx.checker
    and the torch-vs-onnxruntime probe both pass. Returns a report (bytes, seconds, parity, opset)."""
    start = time.perf_counter()
    check_output_path(out_path, force=force)
    scene = load_scene(scene_dir)
    model = field_to_onnx(scene.render_field)
    attach_metadata(model, scene_metadata(scene))
    onnx.checker.check_model(model, full_check=True)
    data = model.SerializeToString()
    probe = probe_parity(scene.render_field, OnnxField(data, threads=1), scene.config.aabb, probe_seed)
    for case in probe:
        if not case.passed:
            raise UserError(f"export refused: on the '{case.name}' noise probe onnxruntime is off by "
                            f"{case.onnx_error:.3g}, torch float32 by {case.torch_error:.3g} (allowed: "
                            f"{PROBE_TOLERANCE:g} + {FLOAT32_SLACK:g}x torch's)")
    with atomic_output(out_path) as tmp:
        tmp.write_bytes(data)
    return {"model": str(out_path), "fingerprint": scene.fingerprint(), "bytes": len(data),
            "seconds": round(time.perf_counter() - start, 3), "opset": OPSET,
            "max_abs_diff": max(case.max_abs_diff for case in probe), "probe": [case.to_dict() for case in probe]}
