"""Host-side check that a mesh file's faces name vertices the file has."""

from __future__ import annotations

import numpy as np


def check_face_indices(faces: np.ndarray, num_vertices: int, where: str) -> None:
    """Raise ``ValueError`` naming ``where`` (the file) unless every vertex index of ``faces``
    ((F, k) integers) is in ``[0, num_vertices)``: a damaged file's negative index would otherwise
    wrap around to another vertex silently, and a large one fail deep inside a reader."""
    faces = np.asarray(faces)
    flat = faces.reshape(faces.shape[0], -1) if faces.ndim else faces.reshape(1, 1)
    bad = np.argwhere((flat < 0) | (flat >= num_vertices))
    if bad.size:
        row, column = bad[0]
        raise ValueError(
            f"{where}: face {row} refers to vertex {flat[row, column]}, but the file has "
            f"{num_vertices} vertices"
        )
