"""What a new host kind costs: a kind that lives in this file alone (`affine`: no encoding, one ReLU layer to
density and a feature, one linear colour head), registered for the test in the two lists a kind joins
(runtime.fields.field_kinds and train.scene.field_kinds.CLASSES), goes through the scene folder, export, an
ordinary render, an exact hide and an onnxruntime reveal with nothing else written. Its torch module writes
only what FieldModule cannot derive; the derived Jacobians are checked against the built-in kinds' hand-written
ones."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
import torch
from torch import nn

import noisenerf
from noisenerf.runtime import fields
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import FieldKind, Segment
from noisenerf.runtime.graph import GraphBuilder
from noisenerf.runtime.limits import checked_int
from noisenerf.runtime.model import load_model
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.render import render_view
from noisenerf.train.scene import field_kinds
from noisenerf.train.scene.field_module import FieldModule
from noisenerf.train.scene.random_scene import random_scene, ring_scene_config
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.scene import Scene, build_fields, load_scene


@dataclass(frozen=True)
class AffineConfig:
    kind: ClassVar[str] = "affine"
    hidden: int = 32
    geo_features: int = 6
    position_dims: ClassVar[int] = 3
    direction_dims: ClassVar[int] = 3
    noise_dims: ClassVar[int] = 6
    has_view_branch: ClassVar[bool] = True

    def to_dict(self) -> dict:
        return {"kind": self.kind, **dataclasses.asdict(self)}

    def in_box(self, aabb) -> "AffineConfig":
        return self

    @staticmethod
    def from_dict(data: dict) -> "AffineConfig":
        return AffineConfig(hidden=data["hidden"], geo_features=data["geo_features"])


class AffineField(FieldModule):
    def __init__(self, config: AffineConfig):
        super().__init__()
        self.config = config
        self.trunk0 = nn.Linear(3, config.hidden)
        self.trunk1 = nn.Linear(config.hidden, 1 + config.geo_features)
        self.head = nn.Linear(config.geo_features + 3, 3)

    def encode(self, points, viewdirs):
        return torch.cat([points, viewdirs], -1)

    def trunk_outputs(self, encoded_position):
        out = self.trunk1(torch.relu(self.trunk0(encoded_position)))
        return out[:, 0], out[:, 1:]

    def colour_head(self, feature, encoded_dirs):
        return self.head(torch.cat([feature, encoded_dirs], -1))

    @staticmethod
    def density_of(raw):
        return torch.relu(raw)

    @staticmethod
    def raw_density_at(density: float) -> float:
        return density

    @staticmethod
    def zero_slope(raw):
        return raw <= 0

    def density_layers(self):
        return [self.trunk0, self.trunk1]


class AffineKind(FieldKind):
    name = "affine"
    opset = 17

    def checked(self, config, what: str) -> dict:
        if not isinstance(config, dict) or set(config) != {"kind", "hidden", "geo_features"}:
            raise UserError(f"the {what} network's architecture must have exactly kind, hidden and geo_features",
                            code="field.keys", network=what, kind=self.name)
        return {key: checked_int(config[key], f"{what} {key}", 1, 256, code="field.width")
                for key in ("hidden", "geo_features")}

    def segments(self, config: dict) -> tuple[Segment, ...]:
        return Segment("position", 3), Segment("direction", 3)

    def build(self, builder: GraphBuilder, prefix: str, config: dict, rgb: str, sigma: str) -> None:
        hidden, geo = config["hidden"], config["geo_features"]
        position, dirs = builder.noisy_pair("points", "viewdirs",
                                            lambda: builder.constant("split.3.3", np.array([3, 3], np.int64)))
        h = builder.add("Relu", (builder.linear(prefix, "trunk0", position, 3, hidden),), f"{prefix}.h")
        out = builder.linear(prefix, "trunk1", h, hidden, 1 + geo)
        density, feature = builder.split(out, builder.constant(f"split.1.{geo}", np.array([1, geo], np.int64)),
                                         (f"{prefix}.raw_density", f"{prefix}.feature"))
        branch = builder.add("Concat", (feature, dirs), f"{prefix}.branch", axis=1)
        builder.add("Sigmoid", (builder.linear(prefix, "head", branch, geo + 3, 3),), rgb)
        builder.add("Squeeze", (builder.add("Relu", (density,), f"{prefix}.sigma"),
                                builder.constant("axes.1", np.array([1], np.int64))), sigma)


@pytest.fixture
def affine_registered(monkeypatch):
    registered = fields.field_kinds()
    monkeypatch.setattr(fields, "field_kinds", lambda: {**registered, "affine": AffineKind()})
    monkeypatch.setitem(field_kinds.CLASSES, "affine", (AffineConfig, AffineField))


def affine_scene() -> Scene:
    config = dataclasses.replace(ring_scene_config(), coarse=AffineConfig())
    torch.manual_seed(3)
    coarse, _ = build_fields(config)
    coarse.eval().requires_grad_(False)
    return Scene(config, coarse, None, OccupancyGrid(config.aabb, np.ones((config.grid_resolution,) * 3, bool)))


def test_a_kind_written_in_one_file_exports_renders_and_hides_exactly(affine_registered, tmp_path):
    affine_scene().save(tmp_path / "scene")
    scene = load_scene(tmp_path / "scene")
    assert isinstance(scene.coarse, AffineField) and scene.config.coarse == AffineConfig()
    noisenerf.export_model(tmp_path / "scene", tmp_path / "model.onnx")
    model = load_model(tmp_path / "model.onnx")
    camera = scene.config.cameras[1]
    ours, _ = render_view(camera, scene.config.render, numpy_field(scene.render_field), scene.sampler())
    theirs, _ = render_view(camera, model.render_config, model.field, model.sampler())
    assert np.abs(ours - theirs).max() <= 1e-5

    rng = np.random.default_rng(7)
    secret = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    secret[:4] = [255, 0, 0]  # saturated rows: the sigmoid's far ends
    secret[4:6] = [0, 0, 0]
    report = noisenerf.hide(tmp_path / "scene", secret, tmp_path / "s.bundle", view=4, workers=1)
    assert report["exact"]
    revealed = noisenerf.reveal(tmp_path / "model.onnx", tmp_path / "s.bundle")
    assert revealed.exact and np.array_equal(revealed.pixels, secret)


def test_the_kind_is_unknown_without_its_registration(tmp_path, affine_registered, monkeypatch):
    """The lists are the only way in: unregistered, the same folder and model are refused by name."""
    affine_scene().save(tmp_path / "scene")
    noisenerf.export_model(tmp_path / "scene", tmp_path / "model.onnx")
    monkeypatch.undo()
    with pytest.raises(UserError, match="of kind 'affine'"):
        load_model(tmp_path / "model.onnx")
    with pytest.raises(UserError, match="unknown field kind 'affine'"):
        load_scene(tmp_path / "scene")


@pytest.mark.parametrize("kind", ["mlp", "hashgrid"])
def test_derived_jacobians_equal_the_hand_written_ones(kind):
    """FieldModule's torch.func Jacobian of a built-in kind equals its hand-written reverse pass."""
    field = random_scene(seed=2, kind=kind).coarse.double()
    encoded = field.encode(*torch.randn(2, 64, 3, dtype=torch.float64).unbind(0))
    encoded = encoded + 0.1 * torch.randn_like(encoded)
    raw, jacobian = type(field).outputs_and_jacobian(field, encoded)
    derived_raw, derived = FieldModule.outputs_and_jacobian(field, encoded)
    assert torch.allclose(raw, derived_raw, rtol=0, atol=1e-12)
    assert torch.allclose(jacobian, derived, rtol=1e-9, atol=1e-12)
