"""Reading a user's ``.npy`` array: never unpickled, numeric, finite, of the expected rank."""

from __future__ import annotations

import tokenize
from pathlib import Path

import numpy as np

from jaxloc.io._text import check_float32_range

#: What numpy can raise on a damaged ``.npy`` (an empty or cut file, a broken header dict, a
#: shape that cannot be allocated).
NPY_ERRORS = (
    ValueError,
    EOFError,
    OSError,
    SyntaxError,
    tokenize.TokenError,
    UnicodeDecodeError,
    MemoryError,
    OverflowError,
)


def read_numeric_npy(path: Path, ndim: int, layout: str, what: str) -> np.ndarray:
    """The ``ndim``-D finite numeric array in ``path`` (``layout`` names the axes in errors, e.g.
    ``"(rows, cols, d)"``; ``what`` names the content in the missing-file error).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: not an ``.npy`` of real numbers (pickled objects and
            complex numbers are refused), another rank, an empty axis, NaN or inf, or a value
            beyond float32's range.
    """
    if not path.is_file():
        raise FileNotFoundError(2, f"No such file ({what})", str(path))
    try:
        array = np.load(path, allow_pickle=False)
    except NPY_ERRORS as err:
        raise ValueError(
            f"{path}: not a numeric .npy array ({type(err).__name__}: {err})"
        ) from None
    real = np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)
    if array.ndim != ndim or not real:
        raise ValueError(
            f"{path}: expected a {layout} array of real numbers, got shape {array.shape} of "
            f"{array.dtype}"
        )
    if 0 in array.shape:
        raise ValueError(f"{path}: expected a {layout} array, got the empty shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{path}: embeddings contain NaN or inf")
    check_float32_range(array, str(path))
    return array
