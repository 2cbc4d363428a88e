"""Object embedding tables: text lines ``key e_1 ... e_d`` or an ``.npy`` (K, d) array.

Keys are label names or class ids (``by="label"``) or object ids (``by="object"``); an ``.npy``
row k belongs to class id / object id k. :func:`jaxloc.mapping.scene_graph_from_reconstruction`
looks each object's embedding up in one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.io._npy import read_numeric_npy
from jaxloc.io._text import data_lines, parse_finite_floats
from jaxloc.io.reconstruction import ReconstructionObject


class EmbeddingTable(NamedTuple):
    """Object embeddings by key.

    Attributes:
        vectors: key -> (d,) float64 embedding. Keys are label names or class ids (as text) for
            ``by="label"``, object ids (as text) for ``by="object"``.
        by: what the keys name.
        source: the file (for error messages).
    """

    vectors: dict[str, np.ndarray]
    by: Literal["label", "object"]
    source: Path

    @property
    def dim(self) -> int:
        return len(next(iter(self.vectors.values())))

    def lookup(self, obj: ReconstructionObject) -> np.ndarray:
        """The embedding of an object: by its object id, or by its label name, then class id."""
        keys = [str(obj.object_id)] if self.by == "object" else [obj.label, str(obj.class_id)]
        for key in keys:
            if key in self.vectors:
                return self.vectors[key]
        raise ValueError(
            f"{self.source}: no embedding for object {obj.object_id} ({obj.label!r}, class "
            f"{obj.class_id}); looked for the key(s) {keys}"
        )


def read_embedding_table(
    path: str | os.PathLike, by: Literal["label", "object"] = "label"
) -> EmbeddingTable:
    """Read an embedding table: text lines ``key e_1 ... e_d`` ('#' comments), or an ``.npy``
    (K, d) array whose row k is class id k (``by="label"``) or object id k (``by="object"``).

    Raises:
        FileNotFoundError, ValueError: a missing file, malformed lines, NaN/inf values, rows of
            different lengths, duplicate keys, a pickled or non-2-D ``.npy``.
    """
    path = Path(path)
    if by not in ("label", "object"):
        raise ValueError(f"by must be 'label' or 'object', got {by!r}")
    if path.suffix == ".npy":
        array = read_numeric_npy(path, 2, "(K, d)", "the embedding table")
        vectors = {str(k): row.astype(np.float64) for k, row in enumerate(array)}
    else:
        if not path.is_file():
            raise FileNotFoundError(2, "No such file (the embedding table)", str(path))
        vectors = {}
        for line_number, line in data_lines(path, comments=True):
            key, *values = line.split()
            where = f"{path}:{line_number}"
            row = np.asarray(parse_finite_floats(values, where, f"embedding of {key!r}"))
            if row.size == 0:
                raise ValueError(f"{where}: expected 'key e_1 ... e_d'")
            if vectors and row.size != len(next(iter(vectors.values()))):
                raise ValueError(f"{where}: {row.size} values, other lines have a different count")
            if key in vectors:
                raise ValueError(f"{where}: duplicate key {key!r}")
            vectors[key] = row
    if not vectors:
        raise ValueError(f"{path}: no embeddings")
    return EmbeddingTable(vectors, by, path)


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_embedding_table": "read_embedding_table",
    },
)
