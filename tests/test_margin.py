"""The exact method's rounding margin: every revealed value lies EXACT_MARGIN_LEVELS or more inside its 8-bit bin,
measured as the reveal computes it, so arithmetic that differs by less (another execution provider) reveals the same
pixels; a hide that cannot keep it writes no bundle."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers import hidden_bundle
from noisenerf.cli.bench.coverage import hard_secrets
from noisenerf.cli.bench.margins import perturbed
from noisenerf.cli.demo import DEMO_VIEW
from noisenerf.runtime.errors import InexactResult
from noisenerf.runtime.metrics import rounding_margins
from noisenerf.runtime.model import load_model
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide import run as hide_run
from noisenerf.train.hide.methods import EXACT_MARGIN_LEVELS
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import procedural_secret

CPU = torch.device("cpu")


def test_rounding_margins_are_distances_to_the_bins_edges_in_levels():
    colors = np.array([[0.0, 0.3 / 255, 1.0], [254.6 / 255, 100.2 / 255, 99.6 / 255]], np.float32)
    pixels = np.array([[0, 0, 255], [255, 100, 100]], np.uint8)
    margins = rounding_margins(colors, pixels)
    np.testing.assert_allclose(margins, [[0.5, 0.2, 0.5], [0.1, 0.3, 0.1]], atol=2e-5)
    assert rounding_margins(np.array([[0.7 / 255]]), np.array([[0]], np.uint8))[0, 0] == pytest.approx(-0.2)


@pytest.mark.parametrize("secret_name", ["photo-like", "saturated"])
def test_hidden_values_keep_their_margin_and_survive_relative_errors_of_1e_5(demo_scene, demo_model, tmp_path,
                                                                            secret_name):
    secret = procedural_secret(24, 24) if secret_name == "photo-like" else \
        hard_secrets(24, tuple(demo_scene.config.render.background))["near saturated"]
    report = hide(demo_scene, secret, tmp_path / "s.bundle", HideConfig(view=DEMO_VIEW), CPU, workers=1)
    assert EXACT_MARGIN_LEVELS == 0.05  # the promise docs/methods.md states
    assert report["exact"] and report["margin_levels"] >= EXACT_MARGIN_LEVELS
    model = load_model(demo_model, threads=1)
    bundle = hidden_bundle(tmp_path / "s.bundle", model)
    revealed = reveal_tiles(bundle, model.render_config, model.fields(), keep_float=True)
    assert revealed.exact
    assert rounding_margins(revealed.image, secret).min() >= EXACT_MARGIN_LEVELS - 1e-3  # onnxruntime's, not torch's
    for relative in (1e-6, 1e-5):
        fields = {name: perturbed(field, relative, seed=3) for name, field in model.fields().items()}
        assert np.array_equal(reveal_tiles(bundle, model.render_config, fields).pixels, secret), relative


def test_a_hide_that_cannot_keep_the_margin_writes_nothing(demo_scene, tmp_path, monkeypatch):
    """Asked for more than the solver keeps (its margin_bins, 0.1), the hide refuses in one line naming it."""
    monkeypatch.setattr(hide_run, "EXACT_MARGIN_LEVELS", 0.2)
    with pytest.raises(InexactResult, match=r"levels from its rounding boundary \(an exact hide keeps 0.2\)"):
        hide(demo_scene, procedural_secret(12, 12), tmp_path / "s.bundle", HideConfig(view=DEMO_VIEW), CPU, workers=1)
    assert not (tmp_path / "s.bundle").exists()
