"""Versioned ``.npz`` map files: the reader shared by every map format, never unpickling."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from jaxloc.io.errors import MapFormatError


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
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as err:
        raise MapFormatError(f"{path}: not a readable jaxloc map ({err})") from err
    found = content.get("format", np.array(""))
    if found.shape != () or str(found) != format_name:
        raise MapFormatError(f"{path}: not a jaxloc {what} file")
    found = content.get("version")
    if found is None or found.shape != () or int(found) != version:
        raise MapFormatError(
            f"{path}: format version {found} is not supported (this jaxloc reads {version})"
        )
    return content
