"""The error of the ``osdar-ar`` command line."""

from __future__ import annotations


class CliError(Exception):
    """An error the user can act on: printed without a traceback, exit code 2."""
