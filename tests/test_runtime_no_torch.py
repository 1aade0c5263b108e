"""The recipient's side never needs torch or onnx: proven in a fresh interpreter where importing them fails."""

import json
import subprocess
import sys

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
