"""The exception types the CLIs turn into a single stderr line and an exit code."""


class UserError(Exception):
    """Bad input from the user: a message meant to be read, never a traceback. Exit code 2."""

    exit_code = 2


class InexactResult(UserError):
    """A result the program knows to be wrong (an exact hide that left pixels off): exit code 3, so a
    script can tell it from bad input and, say, try another view."""

    exit_code = 3
