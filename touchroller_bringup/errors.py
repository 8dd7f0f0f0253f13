"""Errors that the CLI reports as one clear line (bad input, missing files, degenerate data)."""


class UserError(Exception):
    """Bad input from the user: reported as one line with exit code 2."""
