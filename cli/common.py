"""What both command lines share: bad input is exactly one line on stderr and exit code 2.

Argument errors come without argparse's usage block, a UserError, an OSError (unwritable folder, name too
long, a disk that filled) or a MemoryError becomes one line, and library chatter that would add lines
(NumPy's RuntimeWarnings; see runtime.images for the C image libraries and runtime.session for
onnxruntime's logger) is silenced: every check that matters is explicit and raises a UserError.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import warnings

import numpy as np

from noisenerf.runtime.errors import UserError


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors in our one-line form (`--help` still prints the usage)."""

    def error(self, message: str):
        print(f"{self.prog}: error: {one_line(message)} (see --help)", file=sys.stderr)
        sys.exit(2)


def one_line(text: str) -> str:
    """Any message on a single line."""
    return " ".join(str(text).split())


@contextlib.contextmanager
def quiet_warnings():
    """Non-finite arithmetic is checked where it matters; NumPy's warnings about it would be extra lines.
    Scoped to one command, so a caller running `main` in-process keeps its own settings."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def failure(prog: str, error: BaseException) -> int:
    """Print one line for a UserError, OSError or MemoryError and return exit code 2."""
    if isinstance(error, OSError):
        where = f": {error.filename}" if error.filename else ""
        message = f"{error.strerror or error}{where}"
    elif isinstance(error, MemoryError):
        message = "out of memory (the input asks for more than this machine has)"
    else:
        message = str(error)
    print(f"{prog}: error: {one_line(message)}", file=sys.stderr)
    return 2


FAILURES = (UserError, OSError, MemoryError)  # what `failure` reports; anything else is a bug with a traceback
