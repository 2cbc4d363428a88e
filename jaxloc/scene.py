"""The map: a scene graph of objects (label, unit embedding, colour, coarse mesh) with a BVH.

A :class:`SceneGraph` is an ``eqx.Module`` pytree of fixed-shape arrays. Its shapes are its
:class:`Capacity`; two maps of the same capacity are interchangeable inside one compiled function
(no recompilation). Build one with :meth:`SceneGraph.from_meshes`, pad it to a shared capacity with
``capacity=``, save/load it with :func:`jaxloc.save_scene` / :func:`jaxloc.load_scene`
(:mod:`jaxloc.io.scene_map`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import equinox as eqx
import jax
import numpy as np
from jax import Array

from jaxloc.raycasting.bvh import build_bvh

if TYPE_CHECKING:  # imported where meshes are read: loading a saved map needs no trimesh (~0.4 s)
    import trimesh

#: Triangles with an area below this (m^2) are dropped at build time (they can never be hit).
MIN_TRIANGLE_AREA = 1e-12
#: Default most triangles per BVH leaf (``Capacity.leaf_size``).
DEFAULT_LEAF_SIZE = 4
#: SAH splits up to this depth, median splits below it: bounds the tree depth.
MEDIAN_DEPTH = 32
#: Default traversal stack size (``Capacity.stack_size``): the BVH must be shallower than this.
DEFAULT_STACK_SIZE = 64
#: Largest ``Capacity.leaf_size``: traversal tests every slot of a leaf, so bigger leaves only cost
#: time, and a leaf's arrays grow with it (16x the default).
MAX_LEAF_SIZE = 64
#: Largest ``Capacity.stack_size``: twice the deepest tree :func:`build_bvh` makes over at most
#: ``MAX_COUNT`` triangles (``MEDIAN_DEPTH + 30 + 1`` < 64 levels); each ray lane holds a stack.
MAX_STACK_SIZE = 128
#: Largest count field of a :class:`Capacity`: node and leaf rows together (N + L) and every
#: index stay within int32.
MAX_COUNT = 2**30


class Capacity(NamedTuple):
    """Static array sizes of a scene graph. Maps of equal capacity share compiled functions.

    Attributes:
        objects: O, object rows (>= the map's objects, >= 1).
        triangles: T, triangle rows (>= the map's triangles, >= 1).
        nodes: N, internal BVH node rows (>= the tree's, >= 0: a one-leaf tree has none).
        leaves: L, BVH leaf rows (>= the tree's, >= 1).
        edges: E, adjacency rows (>= the map's edges, >= 0).
        embedding_dim: d, the embeddings' dimension (exactly the map's, >= 1).
        leaf_size: K, most triangles per BVH leaf, in [1, MAX_LEAF_SIZE].
        stack_size: traversal stack entries, in [1, MAX_STACK_SIZE], above the tree's depth.
    Counts are at most ``MAX_COUNT``; :meth:`check` enforces these ranges.
    """

    objects: int
    triangles: int
    nodes: int
    leaves: int
    edges: int
    embedding_dim: int
    leaf_size: int = DEFAULT_LEAF_SIZE
    stack_size: int = DEFAULT_STACK_SIZE

    def union(self, other: Capacity) -> Capacity:
        """The smallest capacity holding both (for padding several maps to one shape)."""
        if (self.embedding_dim, self.leaf_size, self.stack_size) != (
            other.embedding_dim,
            other.leaf_size,
            other.stack_size,
        ):
            raise ValueError("capacities differ in embedding_dim, leaf_size or stack_size")
        return self._replace(
            objects=max(self.objects, other.objects),
            triangles=max(self.triangles, other.triangles),
            nodes=max(self.nodes, other.nodes),
            leaves=max(self.leaves, other.leaves),
            edges=max(self.edges, other.edges),
        )

    def check(self) -> Capacity:
        """``self`` if every field is an integer in its range (see the class), else ValueError
        naming the field. Whether a map's arrays fit is checked when they are padded."""
        lowest = {"nodes": 0, "edges": 0}
        highest = {"leaf_size": MAX_LEAF_SIZE, "stack_size": MAX_STACK_SIZE}
        for name, value in self._asdict().items():
            low, high = lowest.get(name, 1), highest.get(name, MAX_COUNT)
            is_int = isinstance(value, int | np.integer) and not isinstance(value, bool)
            if not is_int or not low <= value <= high:
                raise ValueError(
                    f"Capacity.{name} must be an integer in [{low}, {high}], got {value}"
                )
        return self

    def array_bytes(self) -> int:
        """Bytes of the arrays of a :class:`SceneGraph` of this capacity (host or device)."""
        per_object = 4 + 4 * self.embedding_dim + 4 * 3 + 1  # label, embedding, colour, valid
        per_triangle = 4 * 9 + 4 + 4 * 9  # corners, owner, corner colours
        per_leaf = 4 * 6 + (4 * 9 + 4) * self.leaf_size  # box, slots' v0/e1/e2 and ids
        return (
            self.objects * per_object
            + self.triangles * per_triangle
            + self.nodes * (4 * 6 + 4 * 2)  # box, children
            + self.leaves * per_leaf
            + self.edges * 4 * 2
            + 4 * (1 + 6)  # root, scene bounds
        )


class SceneGraph(eqx.Module):
    """Objects and their coarse meshes, packed into fixed-shape arrays, with a flattened BVH.

    Object arrays (O = object capacity, d = embedding dimension):
        labels: (O,) int32 semantic class per object, -1 for padding.
        embeddings: (O, d) float32 unit-norm object embeddings (zeros for padding).
        colors: (O, 3) float32 mean object colour in [0, 1].
        object_valid: (O,) bool.
        edges: (E, 2) int32 object adjacency pairs, -1 rows for padding.
    Triangle arrays (T = triangle capacity), world frame, metres:
        triangles: (T, 3, 3) float32 vertex positions.
        triangle_object: (T,) int32 owning object, -1 for padding.
        triangle_colors: (T, 3, 3) float32 RGB in [0, 1] at each corner.
    BVH arrays (see :mod:`jaxloc.raycasting.bvh`): node_bounds (N + L, 6), node_children (N, 2),
        leaf_triangles (L, 9, K), leaf_triangle_ids (L, K), root (), bounds (2, 3) the scene AABB.
    stack_size: static traversal stack size (>= tree depth).
    """

    labels: Array
    embeddings: Array
    colors: Array
    object_valid: Array
    edges: Array
    triangles: Array
    triangle_object: Array
    triangle_colors: Array
    node_bounds: Array
    node_children: Array
    leaf_triangles: Array
    leaf_triangle_ids: Array
    root: Array
    bounds: Array
    stack_size: int = eqx.field(static=True)

    @property
    def capacity(self) -> Capacity:
        return Capacity(
            objects=self.labels.shape[0],
            triangles=self.triangles.shape[0],
            nodes=self.node_children.shape[0],
            leaves=self.leaf_triangle_ids.shape[0],
            edges=self.edges.shape[0],
            embedding_dim=self.embeddings.shape[1],
            leaf_size=self.leaf_triangle_ids.shape[1],
            stack_size=self.stack_size,
        )

    @property
    def num_objects(self) -> int:
        """Number of real (non-padding) objects (host value)."""
        return int(np.sum(np.asarray(self.object_valid)))

    @property
    def num_triangles(self) -> int:
        """Number of real (non-padding) triangles (host value)."""
        return int(np.sum(np.asarray(self.triangle_object) >= 0))

    def storage_bytes(self) -> int:
        """Bytes of the map's content as saved (meshes, labels, embeddings, colours, edges)."""
        n, t = self.num_objects, self.num_triangles
        per_object = 4 + 4 * self.embeddings.shape[1] + 4 * 3
        per_triangle = 4 * 9 + 4 + 4 * 9
        num_edges = int(np.sum(np.asarray(self.edges)[:, 0] >= 0))
        return n * per_object + t * per_triangle + num_edges * 8

    def storage_mb(self) -> float:
        """Map size in MB (10^6 bytes), the quantity SG2Loc's storage table compares."""
        return self.storage_bytes() / 1e6

    @staticmethod
    def from_meshes(
        meshes: Sequence[trimesh.Trimesh],
        labels: Sequence[int],
        embeddings,
        colors=None,
        edges=None,
        capacity: Capacity | None = None,
    ) -> SceneGraph:
        """Build a scene graph from one trimesh mesh per object.

        Args:
            meshes: n meshes in the world frame (metres, z up).
            labels: n integer class labels (>= 0).
            embeddings: (n, d) object embeddings; stored unit-norm (zero vectors are an error).
            colors: optional (n, 3) RGB in [0, 1]; used for meshes without vertex or face
                colours (default mid grey). Per-vertex colours of a mesh win where present.
            edges: optional (m, 2) object index pairs (adjacency).
            capacity: pad to this capacity (to share compiled code with other maps); by default
                the exact sizes.

        Degenerate triangles (area < 1e-12 m^2) are dropped; an object left with no triangle,
        non-finite vertices, mismatched counts or bad shapes raise ``ValueError``.
        """
        arrays = _objects_to_arrays(meshes, labels, embeddings, colors, edges)
        return _build(*arrays, capacity=capacity)

    @staticmethod
    def from_arrays(
        labels: np.ndarray,
        embeddings: np.ndarray,
        object_colors: np.ndarray,
        edges: np.ndarray,
        triangles: np.ndarray,
        triangle_object: np.ndarray,
        triangle_colors: np.ndarray,
        capacity: Capacity | None = None,
    ) -> SceneGraph:
        """Build a scene graph from validated, unpadded host arrays (what a map file holds).

        Args:
            labels: (n,) int32 classes; embeddings: (n, d) float32 unit-norm; object_colors:
                (n, 3) float32 RGB in [0, 1]; edges: (m, 2) int32 object pairs; triangles:
                (t, 3, 3) float32 world frame, metres; triangle_object: (t,) int32 in [0, n);
                triangle_colors: (t, 3, 3) float32 RGB per corner.
            capacity: pad to this capacity; by default the exact sizes.

        The BVH is built here, deterministically. Raises ``ValueError`` when the arrays do not fit
        ``capacity`` or the tree is deeper than its stack.
        """
        return _build(
            labels,
            embeddings,
            object_colors,
            edges,
            triangles,
            triangle_object,
            triangle_colors,
            capacity=capacity,
        )


def _objects_to_arrays(meshes, labels, embeddings, colors, edges):
    import trimesh

    if isinstance(meshes, trimesh.Trimesh):
        raise TypeError("meshes must be a list of trimesh.Trimesh, one per object")
    meshes = list(meshes)
    n = len(meshes)
    if n == 0:
        raise ValueError("a scene graph needs at least one object")
    labels_arr = np.asarray(labels)
    if labels_arr.shape != (n,):
        raise ValueError(
            f"labels must have length {n} (one per mesh), got shape {labels_arr.shape}"
        )
    if not np.issubdtype(labels_arr.dtype, np.integer):
        raise TypeError(f"labels must be integers, got dtype {labels_arr.dtype}")
    if np.any(labels_arr < 0):
        raise ValueError("labels must be >= 0 (-1 is reserved for padding)")
    emb = np.asarray(embeddings)
    if not (np.issubdtype(emb.dtype, np.floating) or np.issubdtype(emb.dtype, np.integer)):
        raise TypeError(f"embeddings must be a real numeric array, got dtype {emb.dtype}")
    emb = emb.astype(np.float64)
    if emb.ndim != 2 or emb.shape[0] != n:
        raise ValueError(f"embeddings must have shape (n, d) = ({n}, d), got {emb.shape}")
    if not np.all(np.isfinite(emb)):
        raise ValueError("embeddings contain NaN or inf")
    # each row scaled by its largest entry before the norm, so that neither 1e200 (whose square
    # overflows) nor 1e-200 (whose square underflows to a "zero" vector) loses its direction
    largest = np.max(np.abs(emb), axis=1) if emb.shape[1] else np.zeros(n)
    if np.any(largest == 0):
        raise ValueError(
            f"embeddings of objects {np.flatnonzero(largest == 0).tolist()} are zero vectors"
        )
    emb = emb / largest[:, None]
    emb = (emb / np.linalg.norm(emb, axis=1)[:, None]).astype(np.float32)
    if colors is not None:
        colors = np.asarray(colors, np.float64)
        if colors.shape != (n, 3):
            raise ValueError(f"colors must have shape ({n}, 3), got {colors.shape}")
        if not np.all(np.isfinite(colors)) or colors.min() < 0 or colors.max() > 1:
            raise ValueError("colors must be finite and in [0, 1]")

    tris, tri_obj, tri_col, obj_col = [], [], [], []
    for i, mesh in enumerate(meshes):
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"object {i}: expected trimesh.Trimesh, got {type(mesh).__name__}")
        vertices = np.asarray(mesh.vertices, np.float64)
        faces = np.asarray(mesh.faces)
        if faces.size == 0 or vertices.size == 0:
            raise ValueError(f"object {i}: empty mesh (no faces)")
        if not np.all(np.isfinite(vertices)):
            raise ValueError(f"object {i}: mesh has NaN/inf vertices")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0:
            raise ValueError(f"object {i}: faces must be (F, 3) vertex indices >= 0")
        if faces.max() >= vertices.shape[0]:
            raise ValueError(
                f"object {i}: a face refers to vertex {int(faces.max())} but the mesh has "
                f"{vertices.shape[0]} vertices"
            )
        corners = vertices[faces]  # (F, 3, 3)
        area = 0.5 * np.linalg.norm(
            np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
        )
        keep = area >= MIN_TRIANGLE_AREA
        if not np.any(keep):
            raise ValueError(f"object {i}: every triangle is degenerate (zero area)")
        default = colors[i] if colors is not None else np.full(3, 0.5)
        corner_colors = _corner_colors(mesh, faces, default)
        tris.append(corners[keep])
        tri_obj.append(np.full(int(keep.sum()), i, np.int32))
        tri_col.append(corner_colors[keep])
        obj_col.append(corner_colors[keep].reshape(-1, 3).mean(0))
    edges_arr = np.zeros((0, 2), np.int32) if edges is None else np.asarray(edges)
    if edges_arr.size and (edges_arr.ndim != 2 or edges_arr.shape[1] != 2):
        raise ValueError(f"edges must have shape (m, 2), got {edges_arr.shape}")
    edges_arr = edges_arr.reshape(-1, 2)
    if edges_arr.size and (
        not np.issubdtype(edges_arr.dtype, np.integer)
        or edges_arr.min() < 0
        or edges_arr.max() >= n
    ):
        raise ValueError(f"edges must be integer object indices in [0, {n})")
    return (
        labels_arr.astype(np.int32),
        emb,
        np.asarray(obj_col, np.float32),
        edges_arr.astype(np.int32),
        np.concatenate(tris).astype(np.float32),
        np.concatenate(tri_obj),
        np.concatenate(tri_col).astype(np.float32),
    )


def _corner_colors(mesh: trimesh.Trimesh, faces: np.ndarray, default: np.ndarray) -> np.ndarray:
    """(F, 3, 3) RGB in [0, 1] per triangle corner."""
    visual = mesh.visual
    kind = getattr(visual, "kind", None)
    if kind == "vertex":
        vc = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255.0
        return vc[faces]
    if kind == "face":
        fc = np.asarray(visual.face_colors, np.float64)[:, :3] / 255.0
        return np.repeat(fc[:, None, :], 3, axis=1)
    return np.broadcast_to(default, (faces.shape[0], 3, 3)).copy()


def _pad(array: np.ndarray, size: int, fill, name: str) -> np.ndarray:
    if array.shape[0] > size:
        raise ValueError(
            f"the map needs {array.shape[0]} {name} but the capacity holds {size}: "
            f"raise Capacity.{name}"
        )
    out = np.full((size,) + array.shape[1:], fill, array.dtype)
    out[: array.shape[0]] = array
    return out


def _pad_bounds(bvh, capacity: Capacity) -> np.ndarray:
    """Box rows as (nodes capacity + leaves capacity, 6): node r at row r, leaf l at N_cap + l."""
    _pad(bvh.node_children, capacity.nodes, -1, "nodes")  # capacity checks with clear messages
    _pad(bvh.leaf_triangle_ids, capacity.leaves, -1, "leaves")
    out = np.zeros((capacity.nodes + capacity.leaves, 6), np.float32)
    out[: bvh.num_nodes] = bvh.bounds[: bvh.num_nodes]
    out[capacity.nodes : capacity.nodes + bvh.num_leaves] = bvh.bounds[bvh.num_nodes :]
    return out


def _build(labels, emb, obj_col, edges, tris, tri_obj, tri_col, capacity=None) -> SceneGraph:
    if capacity is not None:  # before the build: leaf_size 0 would never finish splitting
        capacity = capacity.check()
        if emb.shape[1] != capacity.embedding_dim:
            raise ValueError(
                f"embedding dimension {emb.shape[1]} differs from the capacity's "
                f"{capacity.embedding_dim}"
            )
    leaf_size = DEFAULT_LEAF_SIZE if capacity is None else capacity.leaf_size
    stack_size = DEFAULT_STACK_SIZE if capacity is None else capacity.stack_size
    bvh = build_bvh(tris, leaf_size=leaf_size, median_depth=MEDIAN_DEPTH)
    if bvh.depth >= stack_size:
        raise ValueError(f"BVH depth {bvh.depth} needs a stack of more than {stack_size} entries")
    if capacity is None:
        capacity = Capacity(
            objects=labels.shape[0],
            triangles=tris.shape[0],
            nodes=bvh.num_nodes,
            leaves=bvh.num_leaves,
            edges=edges.shape[0],
            embedding_dim=emb.shape[1],
            leaf_size=leaf_size,
            stack_size=stack_size,
        )
    valid = np.zeros(capacity.objects, bool)
    valid[: labels.shape[0]] = True
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    # device_put: jnp.asarray would compile a conversion program per array
    return SceneGraph(
        labels=jax.device_put(_pad(labels, capacity.objects, -1, "objects")),
        embeddings=jax.device_put(_pad(emb, capacity.objects, 0.0, "objects")),
        colors=jax.device_put(_pad(obj_col, capacity.objects, 0.0, "objects")),
        object_valid=jax.device_put(valid),
        edges=jax.device_put(_pad(edges, capacity.edges, -1, "edges")),
        triangles=jax.device_put(_pad(tris, capacity.triangles, 0.0, "triangles")),
        triangle_object=jax.device_put(_pad(tri_obj, capacity.triangles, -1, "triangles")),
        triangle_colors=jax.device_put(_pad(tri_col, capacity.triangles, 0.0, "triangles")),
        node_bounds=jax.device_put(_pad_bounds(bvh, capacity)),
        node_children=jax.device_put(_pad(bvh.node_children, capacity.nodes, -1, "nodes")),
        leaf_triangles=jax.device_put(_pad(bvh.leaf_triangles, capacity.leaves, 0.0, "leaves")),
        leaf_triangle_ids=jax.device_put(
            _pad(bvh.leaf_triangle_ids, capacity.leaves, -1, "leaves")
        ),
        root=jax.device_put(np.asarray(bvh.root, np.int32)),
        bounds=jax.device_put(np.stack([lo, hi]).astype(np.float32)),
        stack_size=capacity.stack_size,
    )
