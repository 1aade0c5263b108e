"""The layers of ARCHITECTURE.md, enforced by reading every import (lazy ones and TYPE_CHECKING ones too):
runtime ← train.scene ← train.hide ← export ← api ← cli, and runtime never imports torch or onnx."""

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("runtime", "train.scene", "train.hide", "export", "api", "cli")  # each may import only itself and those before it
FORBIDDEN = {"runtime": {"torch", "onnx", "onnxscript"}, "train.scene": {"onnx"}, "train.hide": {"onnx"}}


def layer_of(module: str) -> str | None:
    """The layer of a module name relative to noisenerf (train.hide.run -> train.hide); None for others."""
    return next((layer for layer in sorted(LAYERS, key=len, reverse=True)
                 if module == layer or module.startswith(layer + ".")), None)


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(source: str, filename: str) -> list[tuple[int, str]]:
    """Every module a file imports, with its line; `from noisenerf.a import b` counts as noisenerf.a.b
    (b may be a module). Relative imports are reported as such (the project writes absolute ones)."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level:
            found.append((node.lineno, "." * node.level + (node.module or "")))
        elif isinstance(node, ast.ImportFrom):
            found += [(node.lineno, f"{node.module}.{alias.name}" if node.module.startswith("noisenerf") else node.module)
                      for alias in node.names]
    return found


def violations(files: dict[Path, str]) -> list[str]:
    """Imports that point up the layers, or at a package the layer must not use. files: path -> source."""
    problems = []
    for path, source in files.items():
        mine = layer_of(module_name(path))
        if mine is None:  # noisenerf/__init__.py and train/__init__.py: no code
            continue
        allowed = LAYERS[:LAYERS.index(mine) + 1]
        for line, imported in imports(source, str(path)):
            where = f"{path.relative_to(REPO)}:{line} imports {imported}"
            top = imported.split(".")[0]
            if imported.startswith("."):
                problems.append(f"{where} (a relative import)")
            elif top in FORBIDDEN.get(mine, ()):
                problems.append(f"{where} ({mine} must not import {top})")
            elif top == "noisenerf" and layer_of(imported[len("noisenerf."):]) not in (None, *allowed):
                problems.append(f"{where} ({mine} may import only {', '.join(allowed)})")
    return problems


OUTSIDE_THE_PACKAGE = ("tests", "tools", "web")  # scripts and tests that no install ships


def source_files() -> dict[Path, str]:
    """Every module of the package: each .py file of the repository outside tests/, tools/ and web/."""
    return {path: path.read_text() for path in sorted(REPO.rglob("*.py"))
            if path.relative_to(REPO).parts[0] not in OUTSIDE_THE_PACKAGE and ".git" not in path.parts}


def test_imports_point_down_the_layers():
    assert violations(source_files()) == []


def test_every_source_file_is_in_a_layer():
    files = source_files()
    assert {REPO / "api.py", REPO / "__init__.py", REPO / "cli" / "main.py", REPO / "runtime" / "api.py"} <= set(files)
    stray = [str(path.relative_to(REPO)) for path in files
             if layer_of(module_name(path)) is None and module_name(path) not in ("", "train")]
    assert stray == []


def test_the_package_root_imports_nothing_and_names_only_the_two_libraries():
    """noisenerf/__init__.py resolves its public names lazily, from runtime/api.py (the recipient's) and api.py
    (the sender's) and the modules they re-export, so `import noisenerf` loads neither torch nor onnxruntime."""
    import noisenerf

    assert [name for _, name in imports((REPO / "__init__.py").read_text(), "__init__.py")] == ["importlib"]
    assert {layer_of(module[len("noisenerf."):]) for module in noisenerf.API.values()} == {"runtime", "api"}


def test_every_source_folder_is_a_package_the_install_ships():
    """pyproject.toml lists the packages a (non-editable) install copies: a folder of modules missing there
    imports in the checkout and fails in every installed copy."""
    import tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {"noisenerf" + "".join(f".{part}" for part in path.parent.relative_to(REPO).parts)
               for path in source_files() | {REPO / "api.py": ""}}
    assert folders - listed == set()


@pytest.mark.parametrize("source, reason", [
    ("from noisenerf.export.onnx_export import export_scene\n", "runtime may import only runtime"),
    ("def f():\n    from noisenerf.train.hide.run import hide\n", "runtime may import only runtime"),
    ("from noisenerf.train import scene\n", "runtime may import only runtime"),
    ("import torch\n", "runtime must not import torch"),
    ("from . import bundle\n", "a relative import"),
])
def test_a_wrong_import_is_reported_even_a_lazy_one(source, reason):
    (problem,) = violations({REPO / "runtime" / "probe.py": source})
    assert problem.startswith("runtime/probe.py:") and reason in problem


def test_a_lower_layer_import_is_allowed():
    assert violations({REPO / "train" / "hide" / "probe.py":
                       "from noisenerf.train.scene.scene import Scene\nfrom noisenerf.runtime.bundle import Bundle\n"}) == []
