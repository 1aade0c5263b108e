"""The one exception type the CLIs turn into a single stderr line and exit code 2."""


class UserError(Exception):
    """Bad input from the user: a message meant to be read, never a traceback."""
