"""Versioned ``.npz`` map files: the reader shared by every map format, never unpickling."""

from __future__ import annotations

import struct
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from jaxloc.io.errors import MapFormatError

#: What reading a damaged ``.npz`` can raise: a broken zip structure or deflate stream, an
#: unsupported compression method or an "encrypted" flag from a flipped header bit, a bad struct
#: field, a size that cannot be allocated, an array header that does not parse.
_CORRUPT = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    EOFError,
    OSError,
    ValueError,
    KeyError,
    NotImplementedError,
    RuntimeError,
    struct.error,
    SyntaxError,
    tokenize.TokenError,
    UnicodeDecodeError,
    OverflowError,
    MemoryError,
)


def read_map_file(path: Path, format_name: str, version: int, what: str) -> dict[str, np.ndarray]:
    """The arrays of a versioned ``.npz`` map file, loaded without pickle.

    Raises:
        FileNotFoundError: no such file.
        MapFormatError: not a readable ``.npz`` (corrupt, truncated, an object array), another
            format name (``what`` names the expected kind), or another version.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            content = {key: data[key] for key in data.files}
    except FileNotFoundError:
        raise
    except _CORRUPT as err:
        raise MapFormatError(
            f"{path}: not a readable jaxloc map ({type(err).__name__}: {err})"
        ) from err
    found = content.get("format", np.array(""))
    if found.shape != () or str(found) != format_name:
        raise MapFormatError(f"{path}: not a jaxloc {what} file")
    found = content.get("version")
    if found is None or found.shape != () or int(found) != version:
        raise MapFormatError(
            f"{path}: format version {found} is not supported (this jaxloc reads {version})"
        )
    return content
