"""The exception types the CLIs turn into a single stderr line and an exit code.

A refusal of the recipient's half (everything under runtime/) carries a stable `code` and the `params` its
message was made from; web/src/errors.js raises the same code with the same params for the same input, which is
what ties the two languages (their messages may be spelled differently). Codes are `area.what` in snake_case.
The sender's half (train/, export/, cli/) refuses with a message only (code None)."""

from __future__ import annotations

import numpy as np


def plain(value):
    """A refusal's parameter as a JSON value: numpy scalars as Python numbers, tuples as lists."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, list)):
        return [plain(item) for item in value]
    if isinstance(value, dict):
        return {str(key): plain(item) for key, item in value.items()}
    return value


class UserError(Exception):
    """Bad input from the user: a message meant to be read, never a traceback. Exit code 2."""

    exit_code = 2

    def __init__(self, message: str, code: str | None = None, **params):
        super().__init__(message)
        self.code = code
        self.params = {name: plain(value) for name, value in params.items()}

    def reworded(self, message: str) -> UserError:
        """The same refusal (code and params) with another message, e.g. the file it came from in front."""
        return type(self)(message, self.code, **self.params)


class InexactResult(UserError):
    """A result the program knows to be wrong (an exact hide that left pixels off): exit code 3, so a
    script can tell it from bad input and, say, try another view."""

    exit_code = 3


def one_line(text) -> str:
    """Any message on a single line (a library's own error text may span several)."""
    return " ".join(str(text).split())
