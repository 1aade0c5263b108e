"""The frozen fields behind onnxruntime: the numpy field callbacks every render and reveal runs on.

The model is read into memory, checked for tensors stored outside the file (runtime.onnx_file refuses
them: onnxruntime would resolve them against the current directory even for a model given as bytes),
and only then handed to onnxruntime as bytes.

A model holds one network (outputs `rgb`, `sigma`) or, for a scene with a fine network, both: `rgb`,
`sigma` are then the fine network (the render network, so models and bundles made before the coarse
network was exported keep their meaning) and `rgb_coarse`, `sigma_coarse` the coarse one, on the same
inputs; a nerfacto model adds its proposal networks' `sigma_proposal0`, …. Each run computes only the
outputs asked for: onnxruntime's inference builds run every node of a graph whatever is fetched (its
RunOptions.only_execute_path_to_fetches works in training builds only, microsoft/onnxruntime#16013), so
each set of outputs gets a session of the graph pruned to it (runtime.onnx_file.pruned_model), checked
as the whole was.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import onnxruntime as ort

from noisenerf.runtime.cores import available_cores
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.graph import COARSE_OUTPUT_NAMES, INPUT_NAMES, OUTPUT_NAMES, proposal_output
from noisenerf.runtime.networks import NETWORKS, network_names, render_network
from noisenerf.runtime.onnx_file import ModelFile, parse_model, pruned_model

DEVICES = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider"}
# TF32 off: onnxruntime's CUDA provider takes TF32 matmuls by default, which moved a reveal's colours by up to 0.55
# levels (an H100, docs/bench/gpu); in float32 CUDA differs from the CPU by ~1e-4 levels, within the exact method's margin
PROVIDER_OPTIONS = {"CUDAExecutionProvider": {"use_tf32": "0"}}
DEFAULT_BATCH = 16384  # points per onnxruntime run: as fast as larger batches on CPU, ~16 MB per 256-wide activation
# onnxruntime's log levels: FATAL keeps its own lines, errors included (they raise and are reported once, as
# our one line), off stderr; --verbose shows its warnings and errors. The level is onnxruntime's process-wide
# logger's (sessions log through it): quiet from this import on, until onnxruntime_logging says otherwise.
LOG_SEVERITY = {"quiet": 4, "verbose": 2}
ort.set_default_logger_severity(LOG_SEVERITY["quiet"])


def onnxruntime_logging(verbose: bool) -> None:
    """Whether onnxruntime's own log lines reach stderr (the process-wide logger every session logs through)."""
    ort.set_default_logger_severity(LOG_SEVERITY["verbose" if verbose else "quiet"])


def providers_for(device: str) -> list[tuple[str, dict]]:
    """onnxruntime execution providers, with their options, for a device name, refusing one this installation
    lacks."""
    if device not in DEVICES:
        raise UserError(f"unknown device {device!r} (expected one of {', '.join(DEVICES)})",
                        code="session.unknown_device", device=device[:60])
    provider = DEVICES[device]
    available = ort.get_available_providers()
    if provider not in available:
        raise UserError(f"device {device!r} needs onnxruntime's {provider}, which this installation lacks "
                        f"(available: {', '.join(available)}); install onnxruntime-gpu for cuda",
                        code="session.no_provider", device=device, provider=provider)
    chosen = [provider] if device == "cpu" else [provider, DEVICES["cpu"]]
    return [(name, PROVIDER_OPTIONS.get(name, {})) for name in chosen]


def session_options(threads: int | None) -> ort.SessionOptions:
    """Intra-op threads (default, and at most: the cores there are; more only oversubscribes and, in
    the thousands, hangs onnxruntime); one inter-op thread, the graph being a single chain. Idle pool
    threads sleep instead of spinning, so a reveal on a shared machine leaves its cores to whoever needs
    them (the exact hide's cause of slowness there, see train/hide/exact_solver.ExactSolver.threads).
    Sessions log through onnxruntime's default logger (silenced: a failure is our one line on stderr)."""
    cores = available_cores()
    threads = cores if threads is None else threads
    if threads < 1:
        raise UserError(f"threads must be at least 1, got {threads}", code="session.threads", threads=threads)
    options = ort.SessionOptions()
    options.intra_op_num_threads = min(threads, cores)
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return options


def load_failure(source: str, error: Exception) -> UserError:
    """One readable line for a model onnxruntime could not load."""
    detail = str(error).replace("\n", " ").strip()
    return UserError(f"{source} is not a loadable ONNX model (not ONNX, or truncated): {detail[:200]}",
                     code="session.load_failed")


def read_model_file(model: str | os.PathLike | bytes) -> ModelFile:
    """A model file's bytes, parsed once (runtime.onnx_file refuses external data and malformed bytes)."""
    if isinstance(model, bytes):
        return parse_model(model, "model")
    path = Path(model)
    if not path.is_file():
        raise UserError(f"model not found: {path}", code="model.not_found")
    return parse_model(path.read_bytes(), str(path))


def declared_noise_dims(file: ModelFile) -> int:
    """The noise port's width as the file declares it. Every model a user gives has had each port checked by
    runtime.graph.check_graph (load_model) before it gets here; the export's own are built by runtime.graph."""
    port = next((port for port in file.inputs if port is not None and port.name == "noise"), None)
    if port is None or not isinstance(port.shape[-1], int):
        raise UserError(f"{file.source} is not a noisenerf field: it has no noise input of fixed width",
                        code="session.no_noise_input")
    return port.shape[-1]


class OnnxField:
    """field(points (n, 3), viewdirs (n, 3), noise (n, noise_dims) | None) -> rgb (n, 3), sigma (n,).

    The render network; `network(name)` gives either network of the same session. Satisfies both
    runtime.field_callbacks.FieldFn (no noise) and NoisyFieldFn; inputs are run in batches of at most `batch`
    points so that memory stays bounded whatever the caller passes. Made from a parsed ModelFile, so
    onnxruntime never sees bytes with external data (read_model_file reads and parses a path).
    """

    def __init__(self, file: ModelFile, device: str = "cpu", threads: int | None = None,
                 batch: int = DEFAULT_BATCH):
        if batch < 1:
            raise UserError(f"batch must be at least 1 point, got {batch}", code="session.batch", batch=batch)
        self.file, self.source = file, file.source
        self.options, self.providers = session_options(threads), providers_for(device)
        self.noise_dims = declared_noise_dims(file)
        has_fine = set(COARSE_OUTPUT_NAMES) <= {port.name for port in file.outputs if port is not None}
        self.networks = network_names(has_fine)
        self.outputs = OUTPUT_NAMES
        self.sessions: dict[tuple[str, ...], ort.InferenceSession] = {}  # shared by network()'s copies
        self.session_for(self.outputs)  # a model onnxruntime cannot load fails here, at load
        self.run_options = ort.RunOptions()
        self.batch = batch

    def session_for(self, outputs: tuple[str, ...]) -> ort.InferenceSession:
        """A session of the graph pruned to `outputs` (onnxruntime evaluates every node of a graph whatever
        is fetched: a fine network's model would run its coarse network too, a nerfacto model its proposal
        networks), made once per set of outputs."""
        if outputs not in self.sessions:
            try:
                self.sessions[outputs] = ort.InferenceSession(pruned_model(self.file, outputs), self.options,
                                                              providers=self.providers)
            except Exception as error:  # onnxruntime's pybind errors share no base class but Exception
                raise load_failure(self.source, error) from None
        return self.sessions[outputs]

    def network(self, name: str) -> "OnnxField":
        """The same session answering for the `coarse` or `fine` network: the render network is on the
        outputs rgb, sigma (runtime.graph), the other one on rgb_coarse, sigma_coarse."""
        if name not in NETWORKS:
            raise UserError(f"unknown network {name!r} (expected one of {', '.join(NETWORKS)})",
                            code="session.unknown_network", network=name[:60])
        if name not in self.networks:
            raise UserError(f"{self.source} has no {name} network", code="session.no_network", network=name)
        network = copy.copy(self)
        network.outputs = OUTPUT_NAMES if name == render_network(self.networks) else COARSE_OUTPUT_NAMES
        return network

    def __call__(self, points: np.ndarray, viewdirs: np.ndarray, noise: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        n = points.shape[0]
        if noise is None:
            noise = np.zeros((n, self.noise_dims), dtype=np.float32)
        if points.shape != (n, 3) or viewdirs.shape != (n, 3) or noise.shape != (n, self.noise_dims):
            raise ValueError(f"field inputs must be (n, 3), (n, 3), (n, {self.noise_dims}); got "
                             f"{points.shape}, {viewdirs.shape}, {noise.shape}")
        rgb = np.empty((n, 3), dtype=np.float32)
        sigma = np.empty(n, dtype=np.float32)
        for start in range(0, n, self.batch):
            window = slice(start, start + self.batch)
            feed = {name: np.ascontiguousarray(array[window], dtype=np.float32)
                    for name, array in zip(INPUT_NAMES, (points, viewdirs, noise))}
            rgb[window], sigma[window] = self.evaluate(feed)
        return rgb, sigma

    def proposal_density(self, index: int):
        """σ (n,) of proposal network `index` at points (n, 3) (output sigma_proposal<index>; the graph check
        has made it exist), run in batches as the field is."""
        output = proposal_output(index)

        def density(points: np.ndarray) -> np.ndarray:
            sigma = np.empty(points.shape[0], dtype=np.float32)
            for start in range(0, points.shape[0], self.batch):
                batch = np.ascontiguousarray(points[start:start + self.batch], dtype=np.float32)
                m = batch.shape[0]
                feed = {"points": batch, "viewdirs": np.zeros((m, 3), np.float32),
                        "noise": np.zeros((m, self.noise_dims), np.float32)}
                sigma[start:start + m] = self.run([output], feed, (m,))[0]
            return sigma

        return density

    def run(self, outputs: list[str], feed: dict[str, np.ndarray], *shapes: tuple[int, ...]) -> list[np.ndarray]:
        """One onnxruntime run; a failing graph, or outputs of other shapes than `shapes`, is one UserError."""
        try:
            results = self.session_for(tuple(outputs)).run(outputs, feed, self.run_options)
        except Exception as error:  # onnxruntime's pybind errors share no base class but Exception
            raise UserError(f"{self.source} failed to evaluate: {' '.join(str(error).split())[:200]}",
                            code="session.evaluate_failed") from None
        if [result.shape for result in results] != list(shapes):
            raise UserError(f"{self.source} returned {' and '.join(f'{n} {r.shape}' for n, r in zip(outputs, results))} "
                            f"for {feed['points'].shape[0]} points, expected {' and '.join(map(str, shapes))}",
                            code="session.output_shape", points=feed["points"].shape[0],
                            shapes=[result.shape for result in results], expected=list(shapes))
        return results

    def evaluate(self, feed: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """One batch through onnxruntime; a failing graph, or outputs of another shape than the declared
        (m, 3) and (m,), is one UserError."""
        m = feed["points"].shape[0]
        rgb, sigma = self.run(list(self.outputs), feed, (m, 3), (m,))
        return rgb, sigma
