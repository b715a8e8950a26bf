"""Errors the CLI turns into one clear line and exit status 2."""


class UsageError(ValueError):
    """Bad input from the user (flag, config, output folder); nothing has been written."""
