"""The recipient's side never needs torch or onnx: proven in a fresh interpreter where importing them fails."""

import dataclasses
import json
import subprocess
import sys

from noisenerf.train.hide.settings import CompactSettings

# Runs in the fresh interpreter: block torch and onnx (not onnxruntime), import every runtime module and
# the reveal CLI, reveal a bundle end to end, then report what got imported.
SCRIPT = r"""
import importlib, json, pkgutil, sys

BLOCKED = ("torch", "onnx", "onnxscript")

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is blocked in this test")
        return None

sys.meta_path.insert(0, Block())
import noisenerf.runtime
modules = [f"noisenerf.runtime.{m.name}" for m in pkgutil.iter_modules(noisenerf.runtime.__path__)]
for name in modules + ["noisenerf.cli.reveal"]:
    importlib.import_module(name)
from noisenerf.cli.reveal import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "modules": modules,
                  "leaked": sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)}), file=sys.stderr)
"""


def test_runtime_imports_and_reveals_without_torch_or_onnx(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    result = subprocess.run([sys.executable, "-c", SCRIPT, str(model), str(bundle), "-o", str(tmp_path / "out.png"),
                             "--json"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    status = json.loads(result.stderr.splitlines()[-1])
    assert status["code"] == 0 and status["leaked"] == []
    assert {"noisenerf.runtime.model", "noisenerf.runtime.session", "noisenerf.runtime.reveal"} <= set(status["modules"])
    assert json.loads(result.stdout)["exact"] is True
    assert (tmp_path / "out.png").is_file()


# Runs in a fresh interpreter with torch blocked: a hide's settings are built as the CLI builds them, for
# every method, and pickled as they travel to workers with each job.
SETTINGS_SCRIPT = r"""
import json, pickle, sys

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "torch":
            raise ImportError(f"{name} is blocked in this test")
        return None

sys.meta_path.insert(0, Block())
from noisenerf.cli.main import build_parser
from noisenerf.train.hide.methods import METHODS
from noisenerf.train.hide.plan import HideConfig

configs = {}
for method in METHODS.values():
    args = build_parser().parse_args(["hide", "scene", "secret.png", "-o", "s.bundle", "--method", method.name,
                                      "--iters", "7", "--revival", "dead"])
    settings = tuple(s for each in METHODS.values() for s in each.from_arguments(args, "cpu"))
    config = pickle.loads(pickle.dumps(HideConfig(method=args.method, settings=settings)))
    configs[method.name] = config.to_dict()
print(json.dumps({"configs": configs, "torch": "torch" in sys.modules}))
"""


def test_hide_settings_are_built_and_pickled_without_torch():
    result = subprocess.run([sys.executable, "-c", SETTINGS_SCRIPT], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    status = json.loads(result.stdout)
    assert status["torch"] is False
    exact, paper = status["configs"]["exact"], status["configs"]["paper"]
    assert (exact["layout"], exact["n_samples"], exact["compact"]) == ("compact", 1,
                                                                       dataclasses.asdict(CompactSettings()))
    assert "paper" not in exact and "exact" not in paper
    assert (paper["layout"], paper["n_samples"], paper["network"]) == ("sample", 64, "coarse")
    assert (paper["paper"]["iters"], paper["paper"]["revival"], paper["paper"]["pass_samples"]) == (7, "dead", 1 << 16)
