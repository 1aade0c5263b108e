"""Output files appear whole or not at all: everything is written to a temporary sibling, then renamed."""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from pathlib import Path

from noisenerf.runtime.errors import UserError


def check_output_path(path: str | os.PathLike, force: bool = True) -> Path:
    """Refuse an output whose folder does not exist, or (without force) that already exists."""
    path = Path(path)
    if not path.parent.is_dir():
        raise UserError(f"output folder does not exist: {path.parent}")
    if path.is_dir():
        raise UserError(f"output path is a directory: {path}")
    if path.exists() and not force:
        raise UserError(f"output exists (pass --force to overwrite): {path}")
    return path


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike):
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds."""
    path = check_output_path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would make every output owner-only
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def finite_json(data):
    """The data with every non-finite float as None: strict JSON has no Infinity (a perfect PSNR)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {key: finite_json(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite_json(value) for value in data]
    return data


def json_text(data, indent: int | None = None) -> str:
    """Strict JSON text (non-finite floats become null)."""
    return json.dumps(finite_json(data), indent=indent, allow_nan=False)


def write_json(path: str | os.PathLike, data) -> None:
    """Atomically write indented JSON."""
    with atomic_output(path) as tmp:
        tmp.write_text(json_text(data, indent=2) + "\n")


def read_json(path: str | os.PathLike, what: str) -> dict:
    """Read a JSON object or raise one clear UserError naming `what`."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UserError(f"{what} not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise UserError(f"{what} is not valid JSON: {path} ({error})") from None
    if not isinstance(data, dict):
        raise UserError(f"{what} must hold a JSON object: {path}")
    return data
