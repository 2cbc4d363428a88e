"""The scene graph's map file: one versioned ``.npz``, written atomically, loaded without pickle.

Besides the scene graph, the file may hold the map's class embeddings (:class:`ClassEmbeddings`:
one embedding per semantic class id, e.g. one-hot), the space query patch embeddings made from
label images live in (:mod:`jaxloc.io.label_images`). Files without them (written before they
existed, or maps whose embeddings are per object) load unchanged.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc.io._atomic import write_npz_atomic
from jaxloc.io._map_file import read_map_file
from jaxloc.io.errors import MapFormatError
from jaxloc.scene import Capacity, SceneGraph

#: The ``format`` entry of a scene-graph map file (a file without it is refused).
FORMAT_NAME = "jaxloc.SceneGraph"
#: The scene-graph map file version this module writes and reads.
FORMAT_VERSION = 1
#: Most bytes a map file's capacity may pad its content by (1 GiB). Padding a map to a shared,
#: larger capacity is legitimate (one compiled function for several maps), so a capacity may
#: exceed the file's counts; but a file of a few kilobytes must not make the loader allocate
#: terabytes. Measured by :meth:`Capacity.array_bytes` above what the content can need.
MAX_PADDING_BYTES = 2**30

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


class ClassEmbeddings(NamedTuple):
    """One embedding per semantic class of a map.

    Attributes:
        class_ids: (K,) int64 distinct class ids (>= 0), sorted.
        vectors: (K, d) float32 unit-norm embeddings, row k for ``class_ids[k]``, in the map's
            embedding space.
    """

    class_ids: np.ndarray
    vectors: np.ndarray

    @staticmethod
    def onehot(class_ids) -> ClassEmbeddings:
        """One-hot embeddings of the distinct ``class_ids``: dimension k = the k-th smallest."""
        ids = np.unique(np.asarray(class_ids, np.int64))
        return ClassEmbeddings(ids, np.eye(ids.size, dtype=np.float32))

    def check(self, where: str = "class embeddings") -> ClassEmbeddings:
        """``self`` if well formed, else ValueError naming ``where``."""
        ids, vectors = np.asarray(self.class_ids), np.asarray(self.vectors)
        if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer) or ids.size == 0:
            raise ValueError(f"{where}: class_ids must be a non-empty 1-D integer array")
        if np.any(ids < 0) or np.any(np.diff(ids) <= 0):
            raise ValueError(f"{where}: class_ids must be distinct, sorted and >= 0")
        if vectors.ndim != 2 or vectors.shape[0] != ids.size:
            raise ValueError(f"{where}: vectors must have shape ({ids.size}, d)")
        if not np.all(np.isfinite(vectors)):
            raise ValueError(f"{where}: vectors contain NaN or inf")
        if not np.allclose(np.linalg.norm(vectors, axis=-1), 1.0, atol=1e-4):
            raise ValueError(f"{where}: vectors must be unit-norm")
        return self


def save_scene(
    scene: SceneGraph, path: str | os.PathLike, classes: ClassEmbeddings | None = None
) -> None:
    """Write ``scene`` to one versioned ``.npz`` file, atomically (temp file, then rename).

    The file holds the map's content (objects, triangles, colours, edges) and its capacity; the
    BVH is rebuilt deterministically on load, so a load gives back identical arrays. ``classes``
    (optional) are stored beside them (:func:`load_class_embeddings` reads them back); their
    dimension must be the scene's embedding dimension.

    Raises:
        ValueError: class embeddings of another dimension; a capacity that pads the content by
            more than ``MAX_PADDING_BYTES`` (:func:`load_scene` would refuse the file).
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
    need = _content_bound(n, int(keep_tri.sum()), int(keep_edge.sum()), scene.embeddings.shape[1])
    padding = _padding_bytes(scene.capacity, need)
    if padding > MAX_PADDING_BYTES:  # load_scene would refuse the file
        raise ValueError(
            f"{path}: capacity {tuple(scene.capacity)} pads the map by {padding / 2**20:.0f} MiB, "
            f"more than the {MAX_PADDING_BYTES / 2**20:.0f} MiB a map file may add: nothing written"
        )
    if classes is not None:
        classes.check()
        if classes.vectors.shape[1] != scene.embeddings.shape[1]:
            raise ValueError(
                f"class embeddings have {classes.vectors.shape[1]} dims, the scene's "
                f"{scene.embeddings.shape[1]}"
            )
        payload["class_ids"] = np.asarray(classes.class_ids, np.int64)
        payload["class_embeddings"] = np.asarray(classes.vectors, np.float32)
    write_npz_atomic(path, payload)


def _padding_bytes(capacity: Capacity, need: Capacity) -> int:
    """Bytes by which the arrays of ``capacity`` exceed the most the content ``need`` can use."""
    need = need._replace(leaf_size=capacity.leaf_size, stack_size=capacity.stack_size)
    return capacity.array_bytes() - need.array_bytes()


def _content_bound(objects: int, triangles: int, edges: int, embedding_dim: int) -> Capacity:
    """The most a map's content can need: its counts, and as many BVH nodes and leaves as a tree
    over its triangles can have (a leaf holds >= 1 triangle: <= T leaves, T - 1 inner nodes)."""
    return Capacity(objects, triangles, triangles - 1, triangles, edges, embedding_dim)


def _checked_capacity(path: Path, record: np.ndarray, need: Capacity) -> Capacity:
    """The capacity a map file records, if each field is in range (:meth:`Capacity.check`) and
    it pads the arrays the content needs by at most ``MAX_PADDING_BYTES``.

    Args:
        path: the map file, for messages.
        record: (8,) int64 capacity fields, in :class:`Capacity` order.
        need: :func:`_content_bound` of the content: an upper bound on the arrays it needs,
            known before the tree is built. Whether the capacity holds the content is checked
            when padding, after the build.
    """
    try:
        capacity = Capacity(*(int(field) for field in record)).check()
    except ValueError as err:
        raise MapFormatError(f"{path}: {err}") from None
    padding = _padding_bytes(capacity, need)
    if padding > MAX_PADDING_BYTES:
        raise MapFormatError(
            f"{path}: capacity {tuple(capacity)} pads the map by {padding / 2**20:.0f} MiB, more "
            f"than the {MAX_PADDING_BYTES / 2**20:.0f} MiB a map file may add"
        )
    return capacity


def load_scene(path: str | os.PathLike) -> SceneGraph:
    """Load and validate a map written by :func:`save_scene` (never unpickles).

    Raises :class:`MapFormatError` naming the array or field for a corrupt, truncated, foreign or
    newer-version file, or one whose arrays have wrong shapes, dtypes or non-finite values,
    colours outside [0, 1], an object without triangles, indices out of range, or a capacity
    field out of range (:meth:`Capacity.check`), too small for the content, or padding it by more
    than ``MAX_PADDING_BYTES`` (checked before anything is built or allocated).
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
    for key in ("object_colors", "triangle_colors"):  # from_meshes's colours: RGB in [0, 1]
        low, high = float(content[key].min()), float(content[key].max())
        if low < 0 or high > 1:
            raise MapFormatError(
                f"{path}: '{key}' must be RGB in [0, 1], found [{low:g}, {high:g}]"
            )
    bare = np.flatnonzero(np.bincount(tri_obj, minlength=n) == 0)
    if bare.size:  # from_meshes refuses an object whose mesh has no (non-degenerate) triangle
        raise MapFormatError(
            f"{path}: {bare.size} objects own no triangle (first {bare[:10].tolist()})"
        )
    need = _content_bound(n, t, edges.shape[0], emb.shape[1])
    capacity = _checked_capacity(path, content["capacity"], need)
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


def load_class_embeddings(path: str | os.PathLike) -> ClassEmbeddings | None:
    """The class embeddings a map file holds (:func:`save_scene`), or None when it has none.

    Raises :class:`MapFormatError` for a file :func:`load_scene` refuses, or malformed ones.
    """
    path = Path(path)
    content = read_map_file(path, FORMAT_NAME, FORMAT_VERSION, "scene graph")
    if "class_ids" not in content and "class_embeddings" not in content:
        return None
    if "class_ids" not in content or "class_embeddings" not in content:
        raise MapFormatError(f"{path}: class_ids and class_embeddings must come together")
    ids, vectors = content["class_ids"], content["class_embeddings"]
    if ids.dtype != np.int64 or vectors.dtype != np.float32:
        raise MapFormatError(f"{path}: class_ids must be int64 and class_embeddings float32")
    try:
        classes = ClassEmbeddings(ids, vectors).check(f"{path} (class embeddings)")
    except ValueError as err:
        raise MapFormatError(str(err)) from None
    objects = content.get("embeddings")
    if objects is None or objects.ndim != 2 or vectors.shape[1] != objects.shape[1]:
        raise MapFormatError(f"{path}: class embeddings differ in dimension from the objects'")
    return classes
