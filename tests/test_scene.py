"""Scene directories round-trip, fingerprint their weights, and refuse malformed content."""

import json

import pytest
import torch

from helpers import make_tiny_scene
from noisenerf.runtime.errors import UserError
from noisenerf.train.scene.scene import load_scene


def test_save_load_roundtrip_keeps_weights_and_fingerprint(tmp_path):
    scene = make_tiny_scene(seed=3, fine=True)
    scene.save(tmp_path / "s")
    loaded = load_scene(tmp_path / "s")
    assert loaded.fingerprint() == scene.fingerprint()
    assert loaded.config == scene.config
    for name, value in scene.fine.state_dict().items():
        assert torch.equal(value, loaded.fine.state_dict()[name])
    assert json.loads((tmp_path / "s" / "scene.json").read_text())["fingerprint"] == scene.fingerprint()


def test_fingerprint_changes_with_any_weight():
    scene = make_tiny_scene(seed=3)
    before = scene.fingerprint()
    with torch.no_grad():
        scene.coarse.rgb_linear.bias[0] += 1e-6
    assert scene.fingerprint() != before


def test_fingerprint_changes_with_architecture():
    a = make_tiny_scene(seed=3, width=32)
    b = make_tiny_scene(seed=3, width=16)
    assert a.fingerprint() != b.fingerprint()


def test_not_a_scene_directory(tmp_path):
    with pytest.raises(UserError, match="not a scene directory"):
        load_scene(tmp_path)


def test_weights_of_wrong_shape_are_refused(tmp_path):
    make_tiny_scene(width=32).save(tmp_path / "s")
    config = json.loads((tmp_path / "s" / "scene.json").read_text())
    config["coarse"]["width"] = 16
    (tmp_path / "s" / "scene.json").write_text(json.dumps(config))
    with pytest.raises(UserError, match="has shape"):
        load_scene(tmp_path / "s")


def test_truncated_weights_are_refused(tmp_path):
    make_tiny_scene().save(tmp_path / "s")
    path = tmp_path / "s" / "weights.safetensors"
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(UserError, match="not a readable safetensors"):
        load_scene(tmp_path / "s")


def test_malformed_json_is_refused(tmp_path):
    make_tiny_scene().save(tmp_path / "s")
    (tmp_path / "s" / "scene.json").write_text("{nope")
    with pytest.raises(UserError, match="not valid JSON"):
        load_scene(tmp_path / "s")


@pytest.mark.parametrize("config", [
    {"depth": 6, "width": 128},
    {"depth": 3, "width": 32, "skips": (1,)},
    {"depth": 4, "width": 32, "use_viewdirs": False},
])
def test_hand_written_jacobian_equals_autograd(config):
    from noisenerf.train.scene.field import MlpConfig, MlpField

    torch.manual_seed(0)
    field = MlpField(MlpConfig(**config)).double().requires_grad_(False)
    encoded = 2.0 * torch.randn(64, field.config.noise_dims, dtype=torch.float64)
    raw, jacobian = field.outputs_and_jacobian(encoded)

    def outputs(x):
        rgb, density = field.raw_outputs(x)
        return torch.cat([rgb, density[..., None]], dim=-1)

    expected = torch.func.vmap(torch.func.jacrev(outputs))(encoded)
    assert jacobian.shape == (64, 4, field.config.noise_dims)
    torch.testing.assert_close(raw, outputs(encoded), rtol=0, atol=1e-12)
    torch.testing.assert_close(jacobian, expected, rtol=0, atol=1e-12)
    assert (jacobian != 0).any(dim=-1).all()  # every row is reached by the noise
