"""Helpers the test modules share (no test module imports another's)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Result:
    code: int
    out: str
    err: str


def run_main(main, args, capfd) -> Result:
    """A CLI's main in-process, its exit code and what reached file descriptors 1 and 2."""
    capfd.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exit_:
        code = exit_.code
    out, err = capfd.readouterr()
    return Result(code, out, err)
