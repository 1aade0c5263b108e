"""Refusals of the recipient's half carry a stable code in both languages (runtime/errors.py, web/src/errors.js).

Every UserError raised under runtime/ names its code (a literal `area.what`, or a name a helper was given), every
`new UserError(...)` under web/src/ too, and a code the JavaScript writes anywhere is one the Python runtime raises: the
two are tied by code and params (tests/test_web.py compares them on every tampered fixture), not by spelling."""

from __future__ import annotations

import ast
import re
import pickle
from pathlib import Path

import numpy as np

from noisenerf.runtime.errors import InexactResult, UserError

REPO = Path(__file__).resolve().parents[1]
CODE = re.compile(r"^[a-z][a-z0-9]*(\.[a-z][a-z0-9_]*)+$")
REFUSALS = {"UserError", "InexactResult"}


def python_refusals() -> list[tuple[str, int, ast.expr | None]]:
    """(file, line, the code argument or None) of every UserError/InexactResult built under runtime/."""
    found = []
    for path in sorted((REPO / "runtime").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) in REFUSALS:
                code = next((keyword.value for keyword in node.keywords if keyword.arg == "code"), None)
                found.append((str(path.relative_to(REPO)), node.lineno, code))
    return found


def python_codes() -> set[str]:
    """Every code runtime/ raises: `code=` literals, and `area.what` literals given to a helper that raises
    (refuse(source, why, "graph.node", ...), os_failure(..., "file.read_failed"))."""
    codes = set()
    for path in (REPO / "runtime").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                values = [*node.args, *(keyword.value for keyword in node.keywords if keyword.arg == "code")]
                codes |= {value.value for value in values if isinstance(value, ast.Constant)
                          and isinstance(value.value, str) and CODE.match(value.value)}
    return codes


def call_arguments(text: str, start: int) -> str:
    """The text between the parenthesis at `start` and its match, skipping strings, template literals (with
    their ${…} nesting) and comments."""
    depth, i, modes = 0, start, []  # modes: the quote or "${" we are inside
    while i < len(text):
        c, mode = text[i], modes[-1] if modes else None
        if mode in ("'", '"'):
            i += 2 if c == "\\" else 1
            if c == mode:
                modes.pop()
            continue
        if mode == "`":
            if c == "\\":
                i += 2
                continue
            if text.startswith("${", i):
                modes.append("${")
                i += 2
                continue
            if c == "`":
                modes.pop()
            i += 1
            continue
        if text.startswith("//", i):
            i = text.index("\n", i)
            continue
        if c in "'\"`":
            modes.append(c)
        elif c in "([{":
            depth += 1
        elif c in ")]}":
            if c == "}" and mode == "${":
                modes.pop()
            else:
                depth -= 1
                if depth == 0:
                    return text[start + 1:i]
        i += 1
    raise AssertionError(f"unbalanced call at {start}")


def javascript_refusals() -> list[tuple[str, int, str]]:
    """(file, line, the call's argument text) of every `new UserError(` under web/src/."""
    found = []
    for path in sorted((REPO / "web" / "src").rglob("*.js")):
        text = path.read_text()
        for match in re.finditer(r"new UserError\(", text):
            found.append((str(path.relative_to(REPO)), text.count("\n", 0, match.start()) + 1,
                          call_arguments(text, match.end() - 1)))
    return found


def test_every_python_refusal_of_the_runtime_names_its_code():
    refusals = python_refusals()
    assert len(refusals) > 100
    missing = [f"{file}:{line}" for file, line, code in refusals if code is None]
    assert not missing, f"UserError without code= at {missing}"
    malformed = [f"{file}:{line}: {code.value!r}" for file, line, code in refusals
                 if isinstance(code, ast.Constant) and not (isinstance(code.value, str) and CODE.match(code.value))]
    assert not malformed, malformed


def test_every_javascript_refusal_names_a_code_python_raises():
    python = python_codes()
    refusals = javascript_refusals()
    assert len(refusals) > 80
    missing = [f"{file}:{line}" for file, line, arguments in refusals if not re.search(r"\bcode\b", arguments)]
    assert not missing, f"new UserError without a code at {missing}"
    codes = {code for path in (REPO / "web" / "src").rglob("*.js")  # at the call, or given to a helper that makes one
             for code in re.findall(r'\bcode: "([^"]*)"', path.read_text())}
    assert codes and all(CODE.match(code) for code in codes), sorted(codes)
    assert not codes - python, f"codes the JavaScript raises and Python never does: {sorted(codes - python)}"


def test_the_scanner_reads_nested_templates():
    text = 'new UserError(`a ${f(`b ${")"}`)} (c)`, { code: "x.y", n: g(1) }); next()'
    assert call_arguments(text, text.index("(")) == 'new UserError(`a ${f(`b ${")"}`)} (c)`, { code: "x.y", n: g(1) })'[14:-1]


def test_a_refusal_keeps_its_code_and_params_across_processes():
    """Pickled as a worker process or a Ray task sends it back; numpy values become plain JSON values."""
    error = pickle.loads(pickle.dumps(UserError("tile 3 is off", code="bundle.tile_outside", rect=(1, np.int64(2)),
                                                width=np.int32(4))))
    assert (type(error), str(error), error.code, error.params) == (
        UserError, "tile 3 is off", "bundle.tile_outside", {"rect": [1, 2], "width": 4})
    assert type(error.params["width"]) is int
    inexact = pickle.loads(pickle.dumps(InexactResult("2 pixels off")))
    assert (type(inexact), inexact.exit_code, inexact.code, inexact.params) == (InexactResult, 3, None, {})
