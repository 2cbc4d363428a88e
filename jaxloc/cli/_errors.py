"""Input errors of the command line: one line on stderr, exit code 2."""

from __future__ import annotations

import sys
from collections.abc import Callable


class InputError(Exception):
    """A problem with the user's files or arguments; reported in one line, exit code 2."""


def _fail(command: str, message: str) -> int:
    print(f"jaxloc {command}: error: {message}", file=sys.stderr)
    return 2


def _describe_os_error(error: OSError) -> str:
    if isinstance(error, FileNotFoundError):
        return f"missing file: {error.filename}"
    if isinstance(error, IsADirectoryError):
        return f"expected a file, got a directory: {error.filename}"
    return f"{error.strerror or error}: {error.filename}"


def run_guarded(command: str, action: Callable[[], int]) -> int:
    """Run ``action``; turn input errors (InputError, OSError) into a message and exit code 2."""
    try:
        return action()
    except InputError as error:
        return _fail(command, str(error))
    except OSError as error:
        return _fail(command, _describe_os_error(error))
