"""Option values checked where they are parsed (``type=`` functions: ``--particles 0`` ends with
exit status 2 and one line naming the option), list options that take ``20 8 4`` or ``20,8,4``, a
parser whose usage errors are one line and a help formatter that shows defaults."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import NoReturn


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line (``jaxloc demo: error: ...``) and
    exit status 2; its subcommands' parsers are of the same class."""

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


class Formatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs as written; an option's help ends with its default, if not None."""

    def _get_help_string(self, action: argparse.Action) -> str:
        default = action.default
        if default is None or default is False or default == argparse.SUPPRESS:
            return action.help or ""
        shown = " ".join(map(str, default)) if isinstance(default, list | tuple) else default
        return f"{action.help} (default {shown})".replace("%", "%%")


def command(commands, name: str, description: str, epilog: str | None = None) -> Parser:
    """The subcommand ``name`` of ``commands``; its help is the first line of ``description``."""
    help = description.split("\n")[0].rstrip(".")
    return commands.add_parser(
        name, help=help, description=description, epilog=epilog, formatter_class=Formatter
    )


def given(**options) -> dict:
    """The ``options`` that are not None (the others keep the library's defaults)."""
    return {name: value for name, value in options.items() if value is not None}


RERUN_HELP = "also write the run as a Rerun recording, for `rerun F.rrd` (needs rerun-sdk)"


class OptionTable(tuple):
    """Text options as ``(flag, metavar, help)`` rows: :meth:`add` puts them in a group of a
    parser, :meth:`values` reads the given ones back as keywords (``--gt-topic``: ``gt_topic``)."""

    def add(self, parser: argparse.ArgumentParser, title: str) -> None:
        add = parser.add_argument_group(title).add_argument
        for flag, metavar, text in self:
            add(flag, metavar=metavar, help=text)

    def values(self, args: argparse.Namespace) -> dict:
        names = [flag[2:].replace("-", "_") for flag, *_ in self]
        return given(**{name: getattr(args, name) for name in names})


def _checker(name: str, convert: Callable, ok: Callable, what: str, plural: str = "") -> Callable:
    """A ``type=`` function: ``convert(text)`` if ``ok`` of it, else an error wanting ``what``
    (``plural``: what a list of them wants, :func:`list_of`)."""

    def check(text: str):
        try:
            value = convert(text)
        except ValueError:
            value = None
        if value is None or not ok(value):
            raise argparse.ArgumentTypeError(f"want {what}, got {text!r}")
        return value

    check.__name__ = check.__qualname__ = name
    check.__doc__ = f"{what[0].upper()}{what[1:]}."
    check.plural = plural
    return check


positive_int = _checker(
    "positive_int", int, lambda v: v >= 1, "an integer >= 1", "positive integers"
)
count = _checker("count", int, lambda v: v >= 0, "an integer >= 0")
seed = _checker("seed", int, lambda v: 0 <= v < 2**32, "a seed from 0 to 2**32 - 1")
positive_float = _checker(
    "positive_float",
    float,
    lambda v: math.isfinite(v) and v > 0,
    "a finite number > 0",
    "finite numbers > 0",
)
nonnegative_float = _checker(
    "nonnegative_float",
    float,
    lambda v: math.isfinite(v) and v >= 0,
    "a finite number >= 0",
    "finite numbers >= 0",
)


def at_least(minimum: int) -> Callable:
    """The ``type=`` of an integer option >= ``minimum``."""
    return _checker(f"at_least_{minimum}", int, lambda v: v >= minimum, f"an integer >= {minimum}")


def list_of(item: Callable, example: str) -> Callable:
    """The ``type=`` of a list option (:func:`add_list`): a comma-separated list of ``item``
    values, so that ``--strides 20 8 4`` and ``--strides 20,8,4`` read the same."""

    def check(text: str) -> tuple:
        try:
            return tuple(item(part) for part in text.split(","))
        except argparse.ArgumentTypeError:
            spaced = example.replace(",", " ")
            message = f"want {item.plural} like {example} or {spaced}, got {text!r}"
            raise argparse.ArgumentTypeError(message) from None

    check.__name__ = check.__qualname__ = f"list_of_{item.__name__}"
    return check


class _Flatten(argparse.Action):
    """Stores the values of a list option as one tuple (``count`` of them, where given)."""

    def __init__(self, *args, count: int | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.count = count

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        flat = tuple(value for part in values for value in part)
        if self.count is not None and len(flat) != self.count:
            parser.error(f"argument {option_string}: want {self.count} values, got {len(flat)}")
        setattr(namespace, self.dest, flat)


def add_list(add: Callable, name: str, item: Callable, example: str, help: str, **kwargs) -> None:
    """A list option ``name`` (``add``: a parser's ``add_argument``): ``item`` values separated by
    spaces or commas (``example``, e.g. ``20,8,4``), as a tuple (None when not given)."""
    spaced = example.replace(",", " ")
    add(
        name,
        type=list_of(item, example),
        nargs="+",
        action=_Flatten,
        help=f"{help}; '{spaced}' or '{example}'",
        **kwargs,
    )
