"""The scene graph's map file: one versioned ``.npz``, written atomically, loaded without pickle."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxloc.io._atomic import write_npz_atomic
from jaxloc.io._map_file import read_map_file
from jaxloc.io.errors import MapFormatError
from jaxloc.scene import Capacity, SceneGraph

FORMAT_NAME = "jaxloc.SceneGraph"
FORMAT_VERSION = 1

_SAVED = {
    # name: (dtype, trailing shape or None for 1-D)
    "labels": (np.int32, ()),
    "embeddings": (np.float32, None),
    "edges": (np.int32, (2,)),
    "triangles": (np.float32, (3, 3)),
    "triangle_object": (np.int32, ()),
    "triangle_colors": (np.float32, (3, 3)),
    "object_colors": (np.float32, (3,)),
    "capacity": (np.int64, ()),
}


def save_scene(scene: SceneGraph, path: str | os.PathLike) -> None:
    """Write ``scene`` to one versioned ``.npz`` file, atomically (temp file, then rename).

    The file holds the map's content (objects, triangles, colours, edges) and its capacity; the
    BVH is rebuilt deterministically on load, so a load gives back identical arrays.
    """
    path = Path(path)
    n = scene.num_objects
    keep_tri = np.asarray(scene.triangle_object) >= 0
    keep_edge = np.asarray(scene.edges)[:, 0] >= 0
    payload = {
        "format": np.array(FORMAT_NAME),
        "version": np.array(FORMAT_VERSION, np.int64),
        "labels": np.asarray(scene.labels)[:n],
        "embeddings": np.asarray(scene.embeddings)[:n],
        "object_colors": np.asarray(scene.colors)[:n],
        "edges": np.asarray(scene.edges)[keep_edge],
        "triangles": np.asarray(scene.triangles)[keep_tri],
        "triangle_object": np.asarray(scene.triangle_object)[keep_tri],
        "triangle_colors": np.asarray(scene.triangle_colors)[keep_tri],
        "capacity": np.asarray(tuple(scene.capacity), np.int64),
    }
    write_npz_atomic(path, payload)


def load_scene(path: str | os.PathLike) -> SceneGraph:
    """Load and validate a map written by :func:`save_scene` (never unpickles).

    Raises :class:`MapFormatError` for a corrupt, truncated, foreign or newer-version file, or one
    whose arrays have wrong shapes, dtypes or non-finite values.
    """
    path = Path(path)
    content = read_map_file(path, FORMAT_NAME, FORMAT_VERSION, "scene graph")
    for key, (dtype, trailing) in _SAVED.items():
        if key not in content:
            raise MapFormatError(f"{path}: missing array '{key}'")
        arr = content[key]
        if arr.dtype != dtype:
            raise MapFormatError(
                f"{path}: '{key}' has dtype {arr.dtype}, expected {np.dtype(dtype)}"
            )
        if trailing is not None and arr.shape[1:] != trailing:
            raise MapFormatError(f"{path}: '{key}' has shape {arr.shape}")
        if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
            raise MapFormatError(f"{path}: '{key}' contains NaN or inf")
    n = content["labels"].shape[0]
    t = content["triangles"].shape[0]
    emb = content["embeddings"]
    checks = [
        (n >= 1 and emb.ndim == 2 and emb.shape[0] == n, "embeddings do not match labels"),
        (
            emb.ndim == 2 and np.allclose(np.linalg.norm(emb, axis=-1), 1.0, atol=1e-4),
            "embeddings are not unit-norm",
        ),
        (content["object_colors"].shape[0] == n, "object_colors do not match labels"),
        (t >= 1, "no triangles"),
        (content["triangle_object"].shape[0] == t, "triangle_object does not match triangles"),
        (content["triangle_colors"].shape[0] == t, "triangle_colors do not match triangles"),
        (content["capacity"].shape == (len(Capacity._fields),), "bad capacity record"),
    ]
    for ok, message in checks:
        if not ok:
            raise MapFormatError(f"{path}: {message}")
    tri_obj, edges = content["triangle_object"], content["edges"]
    if (
        tri_obj.min() < 0
        or tri_obj.max() >= n
        or (edges.size and (edges.min() < 0 or edges.max() >= n))
    ):
        raise MapFormatError(f"{path}: object indices out of range")
    if np.any(content["labels"] < 0):
        raise MapFormatError(f"{path}: negative labels")
    capacity = Capacity(*(int(c) for c in content["capacity"]))
    try:
        return SceneGraph.from_arrays(
            content["labels"],
            emb,
            content["object_colors"],
            edges,
            content["triangles"],
            tri_obj,
            content["triangle_colors"],
            capacity=capacity,
        )
    except ValueError as err:
        raise MapFormatError(f"{path}: {err}") from err
