"""What both command lines share: bad input is exactly one line on stderr and exit code 2.

Argument errors come without argparse's usage block, a UserError, an OSError (unwritable folder, name too
long, a disk that filled) or a MemoryError becomes one line, and library chatter that would add lines
(NumPy's RuntimeWarnings; see runtime.images for the C image libraries and runtime.session for
onnxruntime's logger) is silenced: every check that matters is explicit and raises a UserError.
"""

from __future__ import annotations

import argparse
import contextlib
import getpass
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from noisenerf.runtime.errors import UserError, one_line


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors in our one-line form (`--help` still prints the usage)."""

    def error(self, message: str):
        print(f"{self.prog}: error: {one_line(message)} (see --help)", file=sys.stderr)
        sys.exit(2)


@contextlib.contextmanager
def quiet_warnings():
    """Non-finite arithmetic is checked where it matters; NumPy's warnings about it would be extra lines.
    Scoped to one command, so a caller running `main` in-process keeps its own settings."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def failure(prog: str, error: BaseException) -> int:
    """Print one line for a UserError, OSError or MemoryError and return its exit code (2; an
    InexactResult 3)."""
    if isinstance(error, OSError):
        where = f": {error.filename}" if error.filename else ""
        message = f"{error.strerror or error}{where}"
    elif isinstance(error, MemoryError):
        message = "out of memory (the input asks for more than this machine has)"
    else:
        message = str(error)
    print(f"{prog}: error: {one_line(message)}", file=sys.stderr)
    return getattr(error, "exit_code", 2)


class TerminalProgress:
    """A ProgressEvent callback (runtime.progress) drawing a bar per stage on stderr: on a terminal only, never when
    quiet. Use as a context manager, so the last bar is cleared."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.bar = None
        self.stage = None

    def __call__(self, event) -> None:
        if self.bar is None or self.stage != event.stage:
            from tqdm import tqdm

            self.close()
            self.stage = event.stage
            self.bar = tqdm(total=event.total, desc=event.stage, unit=event.unit, unit_scale=True, file=sys.stderr,
                            disable=True if self.quiet else None, leave=False, dynamic_ncols=True)
        if event.detail:
            self.bar.set_postfix_str(event.detail, refresh=False)
        self.bar.update(event.done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> "TerminalProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


PASSPHRASE_ENV = "NOISENERF_PASSPHRASE"
MAX_PASSPHRASE_BYTES = 4096


def passphrase_given(path: str | None) -> bool:
    """Whether the user gave a passphrase without being asked (a file, or NOISENERF_PASSPHRASE)."""
    return path is not None or PASSPHRASE_ENV in os.environ


def read_passphrase(path: str | None, confirm: bool = False) -> bytes | None:
    """The passphrase, never from the command line (it would land in shell history): the file `path`
    (one trailing newline dropped), else the NOISENERF_PASSPHRASE environment variable, else a hidden
    prompt when stdin is a terminal (asked twice when `confirm`); None when there is none of these."""
    if path is not None:
        file = Path(path)
        if not file.is_file() or file.stat().st_size > MAX_PASSPHRASE_BYTES:
            raise UserError(f"--passphrase-file must be a file of at most {MAX_PASSPHRASE_BYTES} bytes: {path}")
        passphrase = file.read_bytes().removesuffix(b"\n").removesuffix(b"\r")
    elif PASSPHRASE_ENV in os.environ:  # the flag's default: capped as the flag's file is
        passphrase = os.environb[PASSPHRASE_ENV.encode()]
        if len(passphrase) > MAX_PASSPHRASE_BYTES:
            raise UserError(f"{PASSPHRASE_ENV} must hold at most {MAX_PASSPHRASE_BYTES} bytes, not {len(passphrase)}")
    elif sys.stdin.isatty():
        passphrase = getpass.getpass("passphrase: ").encode()
        if confirm and getpass.getpass("passphrase (again): ").encode() != passphrase:
            raise UserError("the two passphrases differ")
    else:
        return None
    if not passphrase:
        raise UserError("the passphrase is empty")
    return passphrase


def payload_line(payload: dict, sealed: bool) -> str:
    """One line about a payload report (runtime.payload.Record.report): kind, name, size, digest, sealing."""
    name = f" {payload['name']!r}" if payload.get("name") else ""
    return (f"payload: {payload['kind']}{name}, {payload['bytes']} bytes, sha256 {payload['sha256']}"
            f"{', sealed' if sealed else ''}")


FAILURES = (UserError, OSError, MemoryError)  # what `failure` reports; anything else is a bug with a traceback
