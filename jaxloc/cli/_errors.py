"""Input errors of the command line: one line on stderr, exit code 2; notes: one line, no exit."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator


class InputError(Exception):
    """A problem with the user's files or arguments; reported in one line, exit code 2."""


def note(command: str, message: str) -> None:
    """One line on stderr that is not an error: ``jaxloc COMMAND: note: message``."""
    print(f"jaxloc {command}: note: {message}", file=sys.stderr)


@contextlib.contextmanager
def reading(prefix: str | None = None) -> Iterator[None]:
    """The library's input errors as InputError: a ValueError (its one-line message names the
    file or setting; after ``prefix: `` where given, the options at fault), and a
    FileNotFoundError that names its file in its message only (one with a ``filename`` goes on
    to :func:`run_guarded`: ``missing file: ...``)."""
    try:
        yield
    except FileNotFoundError as error:
        if error.filename is not None:
            raise
        raise InputError(str(error)) from error
    except ValueError as error:
        raise InputError(str(error) if prefix is None else f"{prefix}: {error}") from error


def _describe_os_error(error: OSError) -> str:
    what = {FileNotFoundError: "missing file", IsADirectoryError: "expected a file, got a folder"}
    return f"{what.get(type(error)) or error.strerror or error}: {error.filename}"


def run_guarded(command: str, action: Callable[[], int]) -> int:
    """Run ``action``; turn input errors (InputError, OSError) into a message and exit code 2."""
    try:
        return action()
    except (InputError, OSError) as error:
        message = str(error) if isinstance(error, InputError) else _describe_os_error(error)
        print(f"jaxloc {command}: error: {message}", file=sys.stderr)
        return 2
