"""Validated parsing of whitespace-separated text lines of numbers (shared by the file loaders).

:func:`data_lines` yields the non-blank lines of a UTF-8 text file (optionally without ``#``
comments) with their 1-based line numbers; :func:`parse_finite_floats` turns fields into finite
floats or raises a ``ValueError`` that names the location and what was being read;
:func:`read_float_table` reads a whole table with a fixed number of columns.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np


def data_lines(path: str | os.PathLike, *, comments: bool = False) -> Iterator[tuple[int, str]]:
    """Non-blank lines ``(line_number, stripped text)`` of a UTF-8 file.

    Args:
        path: the text file.
        comments: strip everything from ``#`` to the end of a line first.

    Raises:
        ValueError: the file is not UTF-8 text (naming the file).
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a UTF-8 text file ({err})") from None
    for line_number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0] if comments else raw
        line = line.strip()
        if line:
            yield line_number, line


#: The largest magnitude a number read from a user's file may have: float32's, as every value
#: jaxloc reads ends up in float32 arrays (a larger finite value would become inf there, far
#: from the file that held it).
FLOAT32_MAX = float(np.finfo(np.float32).max)


def parse_finite_floats(fields: Sequence[str], where: str, what: str) -> list[float]:
    """Fields as finite floats within float32's range (:data:`FLOAT32_MAX`).

    Args:
        fields: the text fields.
        where: location prefix for errors (e.g. ``"objects.txt:3"``).
        what: what the fields are, for errors (e.g. ``"embedding of object 'chair'"``).

    Raises:
        ValueError: ``"{where}: {what} has a non-numeric value (...)"``,
            ``"{where}: {what} has NaN or inf"`` or ``"{where}: {what} has a value beyond
            float32's range (...)"``.
    """
    try:
        values = [float(field) for field in fields]
    except ValueError as err:
        raise ValueError(f"{where}: {what} has a non-numeric value ({err})") from None
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{where}: {what} has NaN or inf")
    check_float32_range(np.asarray(values), f"{where}: {what}")
    return values


def check_float32_range(values: np.ndarray, where: str) -> None:
    """Raise ``ValueError`` ``"{where} has a value beyond float32's range (...)"`` if a finite
    value of ``values`` is larger in magnitude than :data:`FLOAT32_MAX`."""
    if values.size and np.max(np.abs(values)) > FLOAT32_MAX:
        largest = values.flat[int(np.argmax(np.abs(values)))]
        raise ValueError(
            f"{where} has a value beyond float32's range ({largest:g}; at most {FLOAT32_MAX:.3g})"
        )


def read_float_table(path: str | os.PathLike, columns: int, what: str) -> np.ndarray:
    """A table of ``columns`` finite numbers per non-blank line, as (rows, columns) float64.

    Args:
        path: the text file.
        columns: the number of fields every non-blank line must hold.
        what: the column names, for errors (e.g. ``"id x y z"``).

    Raises:
        ValueError: ``"{path}:{line}: expected {columns} fields ({what}), got ..."``, or a field
            that is not a finite number (see :func:`parse_finite_floats`).
    """
    rows = []
    for line_number, line in data_lines(path):
        fields = line.split()
        where = f"{path}:{line_number}"
        if len(fields) != columns:
            raise ValueError(
                f"{where}: expected {columns} fields ({what}), got {len(fields)}: {line!r}"
            )
        rows.append(parse_finite_floats(fields, where, f"line {line!r}"))
    return np.asarray(rows, np.float64).reshape(-1, columns)
