"""Numerical stress: every output finite and torch and onnxruntime agreeing at the extremes, on a small
random-weight scene: noise up to ±1e4, densities near float32 overflow, near/far at 1e-4 and 1e4, grazing
and axis-aligned rays, denormal noise, float16 bundles, and 1-pixel to many-tile secrets.

Each check is a plain function of the stressed scene and one case that raises StressFailure where a bound is
missed (an error, not an `assert`, which `python -O` would drop). `noisenerf bench --stress` runs every case
(`run_stress`); tests/test_stress.py runs the same checks as tests, the fast subset of their cases unless
NOISENERF_STRESS=full.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from noisenerf.export.onnx_export import FLOAT32_SLACK, PROBE_TOLERANCE, export_scene, scaled_error
from noisenerf.runtime import compositing
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.camera import normalize_directions
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.field_callbacks import plain
from noisenerf.runtime.model import Model, load_model
from noisenerf.runtime.rays import RayBatch
from noisenerf.runtime.render import render_rays
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.runtime.sampling import LAST_DELTA, SamplingConfig
from noisenerf.train.hide.settings import PaperSettings
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene import render as rendering
from noisenerf.train.scene.field_kinds import Field
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.random_scene import random_scene
from noisenerf.train.scene.scene import Scene

CPU = torch.device("cpu")
GRAZING = [[1, 0, 0], [0, 1, 0], [0, 0, -1], [-1, 0, 0], [1, 1e-7, 0], [1, 0, 1e-30], [1, 1, 1], [3e-8, 1, 0]]


class StressFailure(Exception):
    """A stress case that missed its bound."""


def require(holds, what: str) -> None:
    """Raise StressFailure(what) unless `holds`."""
    if not holds:
        raise StressFailure(what)


def all_finite(*arrays) -> None:
    for i, array in enumerate(arrays):
        require(np.isfinite(array).all(), f"output {i} holds NaN or Inf")


def at_most(value: float, bound: float, what: str) -> None:
    require(value <= bound, f"{what} {value:.3g} > {bound:.3g}")


@dataclass(frozen=True)
class Stressed:
    """The scene under stress, its render field in float64 (the reference), and its onnxruntime model."""

    scene: Scene
    reference: Field
    model: Model
    folder: Path  # its scene directory and model.onnx; the hides' bundles go in folders below


def stress_scene(folder: Path, seed: int = 7) -> Stressed:
    """The default ring scene of train/scene/random_scene.py, saved and exported into `folder`."""
    scene = random_scene(seed)
    scene.save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    return Stressed(scene, copy.deepcopy(scene.render_field).double(), load_model(folder / "model.onnx", threads=1),
                    folder)


def field_inputs(n: int, seed: int, noise_scale: float, dims: int):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32)
    viewdirs = normalize_directions(rng.normal(size=(n, 3)))
    noise = (noise_scale * rng.choice([-1.0, 1.0], (n, dims)) * rng.random((n, dims))).astype(np.float32)
    return points, viewdirs, noise


def noisy_field_is_finite_and_onnxruntime_is_as_exact_as_torch(stressed: Stressed, noise_scale: float) -> None:
    scene, model = stressed.scene, stressed.model
    points, viewdirs, noise = field_inputs(512, 1, noise_scale, model.noise_dims)
    exact = numpy_field(stressed.reference)(points, viewdirs, noise)
    ours, theirs = numpy_field(scene.render_field)(points, viewdirs, noise), model.field(points, viewdirs, noise)
    for exact_part, torch_part, onnx_part in zip(exact, ours, theirs):
        all_finite(torch_part, onnx_part)
        at_most(scaled_error(exact_part, onnx_part), PROBE_TOLERANCE + FLOAT32_SLACK * scaled_error(exact_part, torch_part),
                "onnxruntime's scaled error")


def compositing_near_float32_overflow_is_finite_in_both_backends(stressed: Stressed, sigma: float) -> None:
    rng = np.random.default_rng(2)
    sigmas = (rng.random((64, 16)) * sigma).astype(np.float32)
    deltas = np.concatenate([rng.random((64, 15)) * 10, np.full((64, 1), LAST_DELTA)], axis=1).astype(np.float32)
    rgbs = rng.random((64, 16, 3)).astype(np.float32)
    background = np.ones(3, np.float32)
    expected = compositing.composite(compositing.render_weights(sigmas, deltas), rgbs, background)
    weights = rendering.render_weights(torch.from_numpy(sigmas), torch.from_numpy(deltas))
    got = rendering.composite(weights, torch.from_numpy(rgbs), torch.from_numpy(background)).numpy()
    all_finite(expected, got)
    at_most(float(weights.sum(1).max()), 1.0 + 1e-6, "a ray's weight sum")
    at_most(float(np.abs(expected - got).max()), 1e-6, "numpy against torch")


def rays_through_box(directions: np.ndarray, origin_distance: float) -> RayBatch:
    directions = np.asarray(directions, dtype=np.float32)
    unit = normalize_directions(directions)
    return RayBatch((-origin_distance * unit).astype(np.float32), directions, unit)


def extreme_near_far_grazing_and_axis_aligned_rays_render_alike(stressed: Stressed, near: float, far: float) -> None:
    scene, model = stressed.scene, stressed.model
    config = dataclasses.replace(scene.config.render, sampling=SamplingConfig(near, far, 64))
    rays = rays_through_box(GRAZING, origin_distance=3.0)
    ours, _ = render_rays(config, rays, plain(numpy_field(scene.render_field)), scene.grid)
    theirs, _ = render_rays(config, rays, plain(model.field), model.grid)
    all_finite(ours, theirs)
    at_most(float(np.abs(ours - theirs).max()), 1e-5, "torch against onnxruntime")


def zero_length_direction_is_refused_clearly(stressed: Stressed) -> None:
    try:
        normalize_directions(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], dtype=np.float32))
    except UserError as error:
        require("zero-length direction" in str(error), f"refused otherwise: {error}")
        return
    raise StressFailure("a zero-length direction was not refused")


def denormal_noise_renders_like_no_noise(stressed: Stressed, tiny: float) -> None:
    scene, model = stressed.scene, stressed.model
    points, viewdirs, _ = field_inputs(256, 3, 0.0, model.noise_dims)
    noise = np.full((256, model.noise_dims), tiny, dtype=np.float32)
    for field_fn in (numpy_field(scene.render_field), model.field):
        clean, noisy = field_fn(points, viewdirs, None), field_fn(points, viewdirs, noise)
        for a, b in zip(clean, noisy):
            all_finite(b)
            at_most(float(np.abs(a - b).max()), 1e-6, "denormal noise against none")


def tiny_and_many_tile_secrets_hide_and_reveal_exactly(stressed: Stressed, height: int, width: int, tile: int,
                                                       layout: str, dtype: str) -> None:
    scene, model = stressed.scene, stressed.model
    secret = np.random.default_rng(height * width).integers(0, 256, (height, width, 3), dtype=np.uint8)
    with tempfile.TemporaryDirectory(dir=stressed.folder) as tmp:
        path = Path(tmp) / "s.bundle"
        report = hide(scene, secret, path, HideConfig(tile_size=tile, layout=layout, dtype=dtype), CPU)
        require(report["exact"], "the hide is not exact")
        bundle = load_bundle(path, model.mask_secret)
        all_finite(*(t.noise.loaded().rows(0, t.rect[2] * t.rect[3]) for t in bundle.tiles))
        revealed = reveal_tiles(bundle, model.render_config, model.fields())
        require(revealed.exact and np.array_equal(revealed.pixels, secret), "the reveal is not the secret")


def same_seed_same_bundle_bytes(stressed: Stressed, method: str, layout: str) -> None:
    secret = np.random.default_rng(5).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    config = HideConfig(method=method, tile_size=16, seed=3, n_samples=None if method == "exact" else 4,
                        layout=layout, settings=(PaperSettings(iters=5, record_at=()),))
    with tempfile.TemporaryDirectory(dir=stressed.folder) as tmp:
        for name in ("a", "b"):
            hide(stressed.scene, secret, Path(tmp) / f"{name}.bundle", config, CPU)
        require((Path(tmp) / "a.bundle").read_bytes() == (Path(tmp) / "b.bundle").read_bytes(),
                "the same seed wrote different bundles")


@dataclass(frozen=True)
class StressCheck:
    """A check and its cases: each case is the arguments after the stressed scene (which every check takes,
    used or not, so that one loop runs them all)."""

    run: Callable[..., None]
    full: tuple[tuple, ...]  # every case: `noisenerf bench --stress`, NOISENERF_STRESS=full
    fast: tuple[tuple, ...]  # the subset the test suite runs by default

    @property
    def name(self) -> str:
        return self.run.__name__


def each(*values) -> tuple[tuple, ...]:
    """One-argument cases."""
    return tuple((value,) for value in values)


SECRET_LAYOUTS = (("compact", "int16"), ("ray", "float16"), ("ray", "float32"))
SAME_SEED_CASES = (("exact", "compact"), ("exact", "ray"), ("paper", "sample"))
STRESS_CHECKS = (
    StressCheck(noisy_field_is_finite_and_onnxruntime_is_as_exact_as_torch,
                full=each(0.0, 1e-3, 1.0, 1e1, 1e2, 1e3, 3e3, 1e4), fast=each(0.0, 1e2, 1e4)),
    StressCheck(compositing_near_float32_overflow_is_finite_in_both_backends,
                full=each(1e10, 1e20, 1e30, 1e37, np.finfo(np.float32).max), fast=each(1e30, np.finfo(np.float32).max)),
    StressCheck(extreme_near_far_grazing_and_axis_aligned_rays_render_alike,
                full=((1e-4, 1e4), (1e-4, 4.0), (2.0, 1e4), (0.0, 1e-4)), fast=((1e-4, 1e4),)),
    StressCheck(zero_length_direction_is_refused_clearly, full=((),), fast=((),)),
    StressCheck(denormal_noise_renders_like_no_noise, full=each(1e-45, 1e-40, 1e-38, 6e-8), fast=each(1e-40)),
    StressCheck(tiny_and_many_tile_secrets_hide_and_reveal_exactly,
                full=tuple(size + layout for size, layout in itertools.product(
                    ((1, 1, 16), (1, 700, 16), (700, 1, 16), (20, 300, 16), (64, 64, 64)), SECRET_LAYOUTS)),
                fast=tuple(size + layout for size, layout in itertools.product(((1, 1, 16), (20, 300, 16)),
                                                                               SECRET_LAYOUTS))),
    StressCheck(same_seed_same_bundle_bytes, full=SAME_SEED_CASES, fast=SAME_SEED_CASES),
)


def stress_cases(full: bool) -> list[tuple[StressCheck, tuple]]:
    """Every (check, case), or the fast subset."""
    return [(check, case) for check in STRESS_CHECKS for case in (check.full if full else check.fast)]


def case_name(check: StressCheck, case: tuple) -> str:
    return f"{check.name}({', '.join(map(str, case))})"


def run_stress(full: bool = True) -> list[dict]:
    """Every case (or the fast subset) on a stress scene in a temporary folder: one row per case, with the
    error of a case that failed. Any exception fails its case, as under pytest, and the others still run."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        stressed = stress_scene(Path(tmp))
        for check, case in stress_cases(full):
            started, error = time.perf_counter(), ""
            try:
                check.run(stressed, *case)
            except Exception as failure:
                error = f"{type(failure).__name__}: {failure}".strip()
            rows.append({"case": case_name(check, case), "passed": not error, "error": error,
                         "seconds": time.perf_counter() - started})
    return rows
