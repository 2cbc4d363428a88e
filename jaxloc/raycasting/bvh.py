"""Host-side (numpy) BVH build, flattened into fixed-shape arrays for traversal in JAX.

The tree is a binary BVH built with the full-sweep surface-area heuristic (SAH) over triangle
centroids, falling back to a median split below ``median_depth`` levels of recursion so the depth,
and with it the traversal stack, stays bounded. Leaves hold at most ``leaf_size`` triangles.

Flat layout (N internal nodes, L leaves, K = leaf_size). A *reference* names a subtree:
``r >= 0`` is internal node r, ``r <= -2`` is leaf ``-r - 2`` (-1 is the traversal's "done" marker).

* ``bounds`` (N + L, 6) float32: the AABB ``[lo, hi]`` of internal node r at row r and of leaf l
  at row N + l.
* ``node_children`` (N, 2) int32: references of each internal node's two children.
* ``leaf_triangles`` (L, 9, K) float32: per leaf and slot, ``v0, e1 = v1 - v0, e2 = v2 - v0``
  (structure of arrays, one contiguous gather per leaf); empty slots are all-zero (det = 0, never
  hit).
* ``leaf_triangle_ids`` (L, K) int32: the original triangle index in each slot, -1 when empty.
* ``root``: reference of the root (internal node 0, or leaf -2 when the tree is one leaf).

Child boxes are inflated by a relative epsilon so that the float32 slab test never rejects a box
whose triangle the exact triangle test would hit.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from jax import Array

#: Boxes are grown by this fraction of the scene extent (plus an absolute floor) on every side.
BOX_EPSILON = 1e-5


class BVHScene(Protocol):
    """What ray casting reads from a scene: triangles and their BVH as device arrays.

    :class:`jaxloc.SceneGraph` is the library's one implementation (built with :func:`build_bvh`);
    the ray casting functions need nothing else from it, so any pytree with these fields works.

    Attributes:
        triangles: (T, 3, 3) float32 corners, world frame, metres; padding rows all zero.
        triangle_object: (T,) int32 object of each triangle, -1 for padding.
        node_bounds: (N + L, 6) float32 boxes of internal nodes then leaves (``bounds`` above).
        node_children: (N, 2) int32 child references.
        leaf_triangles: (L, 9, K) float32 per-slot ``v0, e1, e2``.
        leaf_triangle_ids: (L, K) int32 triangle index per slot, -1 when empty.
        root: () int32 reference of the root.
        stack_size: static int, greater than the tree's depth.
    """

    triangles: Array
    triangle_object: Array
    node_bounds: Array
    node_children: Array
    leaf_triangles: Array
    leaf_triangle_ids: Array
    root: Array
    stack_size: int


class FlatBVH:
    """The flattened arrays of a BVH (numpy, host side); see the module docstring for layout."""

    def __init__(self, bounds, node_children, leaf_triangles, leaf_triangle_ids, root, depth):
        self.bounds = bounds
        self.node_children = node_children
        self.leaf_triangles = leaf_triangles
        self.leaf_triangle_ids = leaf_triangle_ids
        self.root = root
        self.depth = depth

    @property
    def num_nodes(self) -> int:
        return self.node_children.shape[0]

    @property
    def num_leaves(self) -> int:
        return self.leaf_triangle_ids.shape[0]


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    ext = np.maximum(hi - lo, 0.0)
    return ext[..., 0] * ext[..., 1] + ext[..., 1] * ext[..., 2] + ext[..., 2] * ext[..., 0]


def _sah_split(
    tri_lo: np.ndarray, tri_hi: np.ndarray, centroids: np.ndarray
) -> tuple[np.ndarray, int]:
    """Best SAH split of a set of triangles: (order of the set, number of triangles on the left)."""
    n = centroids.shape[0]
    best_cost, best_order, best_count = np.inf, None, n // 2
    for axis in range(3):
        order = np.argsort(centroids[:, axis], kind="stable")
        lo, hi = tri_lo[order], tri_hi[order]
        left_area = _half_area(np.minimum.accumulate(lo, 0), np.maximum.accumulate(hi, 0))[:-1]
        right_area = _half_area(
            np.minimum.accumulate(lo[::-1], 0)[::-1], np.maximum.accumulate(hi[::-1], 0)[::-1]
        )[1:]
        counts = np.arange(1, n)
        cost = left_area * counts + right_area * (n - counts)
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_cost, best_order, best_count = cost[i], order, i + 1
    return best_order, best_count


def build_bvh(triangles: np.ndarray, leaf_size: int = 4, median_depth: int = 32) -> FlatBVH:
    """Build a BVH over ``triangles`` (T, 3, 3) float (T >= 1).

    Args:
        triangles: vertex positions in the world frame (metres), one row per triangle.
        leaf_size: maximum triangles per leaf (static K of the layout).
        median_depth: recursion depth after which splits are median splits on the longest axis;
            the tree depth is then at most ``median_depth + ceil(log2(T / leaf_size)) + 1``.
    """
    triangles = np.asarray(triangles, np.float64)
    num_tris = triangles.shape[0]
    if num_tris < 1:
        raise ValueError("cannot build a BVH over zero triangles")
    tri_lo, tri_hi = triangles.min(axis=1), triangles.max(axis=1)
    centroids = triangles.mean(axis=1)
    scene_extent = float(np.max(tri_hi.max(0) - tri_lo.min(0)))
    pad = BOX_EPSILON * max(scene_extent, 1.0)

    node_boxes: list[np.ndarray] = []
    node_children: list[list[int]] = []
    leaves: list[np.ndarray] = []
    max_depth = 0

    def box(indices: np.ndarray) -> np.ndarray:
        return np.concatenate([tri_lo[indices].min(0) - pad, tri_hi[indices].max(0) + pad])

    def build(indices: np.ndarray, depth: int) -> int:
        """Builds the subtree over ``indices``; returns its reference."""
        nonlocal max_depth
        max_depth = max(max_depth, depth)
        if indices.shape[0] <= leaf_size:
            leaves.append(indices)
            return -2 - (len(leaves) - 1)
        if depth < median_depth:
            order, count = _sah_split(tri_lo[indices], tri_hi[indices], centroids[indices])
        else:
            c = centroids[indices]
            axis = int(np.argmax(c.max(0) - c.min(0)))
            order, count = np.argsort(c[:, axis], kind="stable"), indices.shape[0] // 2
        node = len(node_children)
        node_children.append([0, 0])
        node_boxes.append(box(indices))
        left, right = indices[order[:count]], indices[order[count:]]
        node_children[node] = [build(left, depth + 1), build(right, depth + 1)]
        return node

    root = build(np.arange(num_tris), 0)

    num_leaves = len(leaves)
    leaf_ids = np.full((num_leaves, leaf_size), -1, np.int32)
    for i, leaf in enumerate(leaves):
        leaf_ids[i, : leaf.shape[0]] = leaf
    safe = np.maximum(leaf_ids, 0)
    v0 = triangles[safe, 0]
    e1 = triangles[safe, 1] - v0
    e2 = triangles[safe, 2] - v0
    packed = np.concatenate([v0, e1, e2], axis=-1)  # (L, K, 9)
    packed[leaf_ids < 0] = 0.0
    leaf_triangles = np.ascontiguousarray(packed.transpose(0, 2, 1)).astype(np.float32)

    if node_children:
        children_arr = np.asarray(node_children, np.int32)
        internal_boxes = np.asarray(node_boxes)
    else:  # a single leaf: keep one unused internal node so the arrays are never empty
        children_arr = np.full((1, 2), root, np.int32)
        internal_boxes = np.zeros((1, 6))
    leaf_boxes = np.stack([box(leaf) for leaf in leaves])
    bounds = np.concatenate([internal_boxes, leaf_boxes]).astype(np.float32)
    return FlatBVH(bounds, children_arr, leaf_triangles, leaf_ids, root, max_depth)
