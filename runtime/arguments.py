"""The public functions' arguments checked for their kind before any work (`noisenerf.reveal`, `render`, `hide`,
`fit`, `export_model`, `import_nerfstudio`): a wrong one is one UserError naming the argument (code
`api.argument`), never a TypeError from deep inside. Values are checked where they are used (caps, ranges).
"""

from __future__ import annotations

import numbers
import os
from typing import Any, Callable

from noisenerf.runtime.errors import UserError

PATH = "a path (str or os.PathLike)"


def wrong(name: str, expected: str, value: Any) -> UserError:
    return UserError(f"{name} must be {expected}, not {type(value).__name__}", code="api.argument", argument=name,
                     expected=expected, got=type(value).__name__)


def accepting(expected: str, accepts: Callable[[Any], bool], convert: Callable[[Any], Any] = lambda value: value):
    """A check of one kind: check(value, name) -> the value (converted) where accepts(value), else a UserError
    saying what `name` must be."""
    def check(value: Any, name: str):
        if accepts(value):
            return convert(value)
        raise wrong(name, expected, value)
    return check


def integral(value: Any) -> bool:
    """A Python or numpy integer, not a bool (nor a float that happens to be whole)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


checked_path = accepting(PATH, lambda value: isinstance(value, (str, os.PathLike)))
# a file given as a path or as its bytes (bytearray and memoryview taken as bytes)
checked_source = accepting(f"{PATH} or bytes",
                           lambda value: isinstance(value, (str, os.PathLike, bytes, bytearray, memoryview)),
                           lambda value: bytes(value) if isinstance(value, (bytearray, memoryview)) else value)
checked_int = accepting("an integer", integral, int)
checked_number = accepting("a number", lambda value: isinstance(value, numbers.Real) and not isinstance(value, bool),
                           float)
checked_flag = accepting("True or False", lambda value: isinstance(value, bool))
checked_text = accepting("a str", lambda value: isinstance(value, str))
checked_callback = accepting("a function", callable)


def optional(check, value: Any, name: str):
    """check(value, name), or None where value is None."""
    return None if value is None else check(value, name)
