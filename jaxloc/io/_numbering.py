"""Host-side check that files named by numbers (camera frames, LiDAR scans) use each once."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path


def check_distinct_numbers(numbered: Sequence[tuple[int, Path]], clash: str) -> None:
    """Raise ``ValueError`` naming both files when two of the ``(number, file)`` pairs, sorted by
    number, share a number (``1.jpg`` and ``01.jpg``): which file is that number's would be a
    guess. The message reads ``"{file} and {file}: two {clash} {number}"``, e.g. ``clash =
    "frame files with the same number"``."""
    for (number, first), (other, second) in zip(numbered, numbered[1:], strict=False):
        if number == other:
            raise ValueError(f"{first} and {second}: two {clash} {number}")
