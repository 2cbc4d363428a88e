"""Option values checked where they are parsed: argparse ``type=`` functions and a parser whose
usage errors are one line.

A bad value (``--particles 0``, ``--seed -3``, ``--threshold nan``) ends the command with exit
status 2 and one line on stderr that names the option and what it accepts, before any file is read
or anything is compiled.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import NoReturn


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line (``jaxloc demo: error: ...``) and
    exit status 2; its subcommands' parsers are of the same class."""

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def _integer(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"want {what}, got {text!r}") from None


def _real(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"want {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"want {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = _integer(text, "an integer >= 1")
    if value < 1:
        raise argparse.ArgumentTypeError(f"want an integer >= 1, got {text!r}")
    return value


def count(text: str) -> int:
    """An integer >= 0."""
    value = _integer(text, "an integer >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"want an integer >= 0, got {text!r}")
    return value


def seed(text: str) -> int:
    """A random seed: an integer in [0, 2**32)."""
    value = _integer(text, "a seed, an integer from 0 to 2**32 - 1")
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"want a seed from 0 to 2**32 - 1, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _real(text, "a finite number > 0")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"want a finite number > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    value = _real(text, "a finite number >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"want a finite number >= 0, got {text!r}")
    return value


def at_least(minimum: int):
    """The ``type=`` of an integer option >= ``minimum`` (``at_least(4)("2")`` fails with
    ``want an integer >= 4, got '2'``)."""

    def check(text: str) -> int:
        value = _integer(text, f"an integer >= {minimum}")
        if value < minimum:
            raise argparse.ArgumentTypeError(f"want an integer >= {minimum}, got {text!r}")
        return value

    check.__name__ = check.__qualname__ = f"at_least_{minimum}"
    return check


def stride_list(text: str) -> tuple[int, ...]:
    """Comma-separated integers >= 1, one pixel stride per round (``20,8,4``)."""
    try:
        strides = tuple(int(part) for part in text.split(","))
    except ValueError:
        strides = ()
    if not strides or min(strides) < 1:
        raise argparse.ArgumentTypeError(f"want positive integers like 20,8,4, got {text!r}")
    return strides


def fraction(text: str) -> float:
    """A finite number in [0, 1]."""
    value = _real(text, "a number from 0 to 1")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"want a number from 0 to 1, got {text!r}")
    return value
