"""The public functions' arguments checked for their kind before any work (`noisenerf.reveal`, `render`, `hide`,
`fit`, `export_model`, `import_nerfstudio`): a wrong one is one UserError naming the argument (code
`api.argument`), never a TypeError from deep inside. Values are checked where they are used (caps, ranges).
"""

from __future__ import annotations

import numbers
import os
from typing import Any

from noisenerf.runtime.errors import UserError

PATH = "a path (str or os.PathLike)"


def wrong(name: str, expected: str, value: Any) -> UserError:
    return UserError(f"{name} must be {expected}, not {type(value).__name__}", code="api.argument", argument=name,
                     expected=expected, got=type(value).__name__)


def checked_path(value: Any, name: str) -> str | os.PathLike:
    if isinstance(value, (str, os.PathLike)):
        return value
    raise wrong(name, PATH, value)


def checked_source(value: Any, name: str) -> str | os.PathLike | bytes:
    """A file given as a path or as its bytes (bytearray and memoryview taken as bytes)."""
    if isinstance(value, (bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, (str, os.PathLike, bytes)):
        return value
    raise wrong(name, f"{PATH} or bytes", value)


def checked_int(value: Any, name: str) -> int:
    """A Python or numpy integer (not a bool, not a float that happens to be whole)."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return int(value)
    raise wrong(name, "an integer", value)


def checked_flag(value: Any, name: str) -> bool:
    if isinstance(value, bool):
        return value
    raise wrong(name, "True or False", value)


def checked_number(value: Any, name: str) -> float:
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return float(value)
    raise wrong(name, "a number", value)


def checked_text(value: Any, name: str) -> str:
    if isinstance(value, str):
        return value
    raise wrong(name, "a str", value)


def checked_callback(value: Any, name: str):
    if callable(value):
        return value
    raise wrong(name, "a function", value)


def optional(check, value: Any, name: str):
    """check(value, name), or None where value is None."""
    return None if value is None else check(value, name)
