"""The `mlp` field kind: the standard NeRF MLP (nerf-pytorch's, layer for layer), the paper's host.

Graph, per distinct encoding (shared by coarse and fine networks when their frequencies agree):
γ(v) = [v, sin(2⁰v), cos(2⁰v), …] by Unsqueeze → Mul → Sin, Cos → Unsqueeze → Concat → Reshape → Concat
(paper eq. 4, nerf-pytorch's order); noise is added to [γ(x) ‖ γ(d)] and split again (eq. 4–5); the
network is nn.Linear's layers as Gemm(transB=1) with ReLU and its skip Concat, then sigmoid colour and
ReLU density (σ squeezed to (n,)). Noise segments: position γ(x) (3 + 6·xyz_freqs), direction γ(d)
(3 + 6·dir_freqs, absent without view directions). Torch twin: train.scene.field.MlpField.
"""

from __future__ import annotations

import numpy as np

from noisenerf.runtime.encoding import encoding_dims
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import FieldKind, Segment
from noisenerf.runtime.graph import GraphBuilder
from noisenerf.runtime.limits import MAX_FIELD_DEPTH, MAX_FIELD_WIDTH, MAX_FREQUENCIES, checked_int, checked_list

KEYS = {"depth", "width", "skips", "xyz_freqs", "dir_freqs", "use_viewdirs"}


def encoding(builder: GraphBuilder, x: str, n_freqs: int) -> str:
    """γ(x) of an (n, 3) value -> (n, 3 + 6·n_freqs), computed once per (input, frequencies)."""
    name = f"gamma.{x}.{n_freqs}"
    if builder.computed(name):
        return name
    axis1 = builder.constant("axes.1", np.array([1], np.int64))
    axis2 = builder.constant("axes.2", np.array([2], np.int64))
    freqs = builder.constant(f"freqs.{n_freqs}", (2.0 ** np.arange(n_freqs, dtype=np.float32))[:, None])
    scaled = builder.add("Mul", (builder.add("Unsqueeze", (x, axis1), f"{name}.x"), freqs), f"{name}.scaled")
    sin = builder.add("Unsqueeze", (builder.add("Sin", (scaled,), f"{name}.sin"), axis2), f"{name}.sin4")
    cos = builder.add("Unsqueeze", (builder.add("Cos", (scaled,), f"{name}.cos"), axis2), f"{name}.cos4")
    bands = builder.add("Concat", (sin, cos), f"{name}.bands4", axis=2)
    flat = builder.add("Reshape", (bands, builder.constant("shape.flat", np.array([0, -1], np.int64))),
                       f"{name}.bands")
    return builder.add("Concat", (x, flat), name, axis=1)


def noisy_inputs(builder: GraphBuilder, config: dict) -> tuple[str, str | None]:
    """γ(x) + noise, or [γ(x) ‖ γ(d)] + noise split back into its γ(x) and γ(d) parts (the latter None
    without view directions), computed once per frequencies."""
    xyz = encoding(builder, "points", config["xyz_freqs"])
    if not config["use_viewdirs"]:
        name = f"{xyz}+noise"
        return (name if builder.computed(name) else builder.add("Add", (xyz, "noise"), name)), None
    dirs = encoding(builder, "viewdirs", config["dir_freqs"])
    return builder.noisy_pair(xyz, dirs, lambda: builder.constant(f"split.{config['xyz_freqs']}.{config['dir_freqs']}", np.array(
        [encoding_dims(config["xyz_freqs"]), encoding_dims(config["dir_freqs"])], np.int64)))


class MlpKind(FieldKind):
    name = "mlp"
    opset = 17

    def checked(self, config, what: str) -> dict:
        """train.scene.field.MlpConfig's fields, exactly, within the caps."""
        if not isinstance(config, dict) or set(config) != KEYS:
            raise UserError(f"the {what} network's architecture must have exactly depth, width, skips, xyz_freqs, "
                            "dir_freqs and use_viewdirs", code="field.keys", network=what, kind=self.name)
        depth = checked_int(config["depth"], f"{what} depth", 1, MAX_FIELD_DEPTH, code="field.depth")
        skips = [checked_int(skip, f"{what} skip", 0, depth - 1, code="field.skips") for skip in checked_list(
            list(config["skips"]) if isinstance(config["skips"], tuple) else config["skips"], "skips", most=depth,
            code="field.skips")]
        if not isinstance(config["use_viewdirs"], bool):
            raise UserError(f"the {what} network's use_viewdirs must be true or false", code="field.use_viewdirs",
                            network=what)
        return {"depth": depth, "width": checked_int(config["width"], f"{what} width", 2, MAX_FIELD_WIDTH,
                                                     code="field.width"),
                "skips": sorted(set(skips)), "use_viewdirs": config["use_viewdirs"],
                **{key: checked_int(config[key], f"{what} {key}", 0, MAX_FREQUENCIES, code="field.frequencies")
                   for key in ("xyz_freqs", "dir_freqs")}}

    def segments(self, config: dict) -> tuple[Segment, ...]:
        position = Segment("position", encoding_dims(config["xyz_freqs"]))
        return (position, Segment("direction", encoding_dims(config["dir_freqs"]))) if config["use_viewdirs"] \
            else (position,)

    def build(self, builder: GraphBuilder, prefix: str, config: dict, rgb: str, sigma: str) -> None:
        """One NeRF MLP (train.scene.field.MlpField, layer for layer)."""
        xyz, dirs = noisy_inputs(builder, config)
        xyz_dims, width = encoding_dims(config["xyz_freqs"]), config["width"]
        h, fan_in = xyz, xyz_dims
        for i in range(config["depth"]):
            h = builder.add("Relu", (builder.linear(prefix, f"pts_linears.{i}", h, fan_in, width),), f"{prefix}.h{i}")
            fan_in = width
            if i in config["skips"]:
                h, fan_in = builder.add("Concat", (xyz, h), f"{prefix}.skip{i}", axis=1), width + xyz_dims
        if config["use_viewdirs"]:
            density = builder.linear(prefix, "alpha_linear", h, width, 1)
            feature = builder.linear(prefix, "feature_linear", h, width, width)
            branch = builder.add("Concat", (feature, dirs), f"{prefix}.branch", axis=1)
            hidden = builder.linear(prefix, "views_linears.0", branch, width + encoding_dims(config["dir_freqs"]),
                                    width // 2)
            raw_rgb = builder.linear(prefix, "rgb_linear", builder.add("Relu", (hidden,), f"{prefix}.views"),
                                     width // 2, 3)
        else:
            raw = builder.linear(prefix, "output_linear", h, width, 4)
            sizes = builder.constant("split.rgb_density", np.array([3, 1], np.int64))
            raw_rgb, density = builder.split(raw, sizes, (f"{prefix}.raw_rgb", f"{prefix}.raw_density"))
        builder.add("Sigmoid", (raw_rgb,), rgb)
        builder.add("Squeeze", (builder.add("Relu", (density,), f"{prefix}.sigma"),
                                builder.constant("axes.1", np.array([1], np.int64))), sigma)


MLP = MlpKind()
