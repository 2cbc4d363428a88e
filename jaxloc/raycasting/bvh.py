"""Host-side (numpy) BVH build, flattened into fixed-shape arrays for traversal in JAX.

The tree is a binary BVH built with the full-sweep surface-area heuristic (SAH) over triangle
centroids, falling back to a median split below ``median_depth`` levels of recursion so the depth,
and with it the traversal stack, stays bounded. Leaves hold at most ``leaf_size`` triangles.

The build is level by level: every subtree of one depth is split at once with segmented numpy
operations (sorts keyed by subtree, running minima and maxima over integer ranks of the
coordinates, so they are exact), and the nodes are then numbered in depth-first preorder. It gives
the same tree as splitting one subtree at a time recursively (tests/test_bvh.py keeps that
reference), ~4-5x faster: 0.37 s instead of 1.7 s for 53k triangles (the work a map's loading
waits for).

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

from typing import NamedTuple, Protocol

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


def _half_area(lo, hi) -> np.ndarray:
    """Half the surface area of boxes given as their corners' x, y and z arrays."""
    ext = [np.maximum(h - low, 0.0) for low, h in zip(lo, hi, strict=True)]
    return ext[0] * ext[1] + ext[1] * ext[2] + ext[2] * ext[0]


class _Ranked(NamedTuple):
    """A (T, 3) float64 coordinate array as, per axis, its sorted distinct values and (T,) ranks."""

    values: tuple[np.ndarray, ...]
    ranks: tuple[np.ndarray, ...]

    @staticmethod
    def of(coordinates: np.ndarray) -> _Ranked:
        axes = [np.unique(coordinates[:, d], return_inverse=True) for d in range(3)]
        return _Ranked(tuple(a[0] for a in axes), tuple(a[1] for a in axes))

    def running(self, order, offset, op) -> tuple[list, list]:
        """Per axis, the (n,) running ``op`` (np.minimum or np.maximum) of the triangles ``order``
        within each subtree, from its first triangle and from its last. ``offset`` (n,) is the
        subtree's index times a bound on the ranks: shifted by it, every subtree's ranks lie
        beyond those of the subtrees scanned before it, so one scan restarts at each subtree."""
        shift = offset if op is np.maximum else -offset
        back_shift = shift[::-1]
        forward, backward = [], []
        for values, ranks in zip(self.values, self.ranks, strict=True):
            ranks = ranks[order]
            forward.append(values[op.accumulate(ranks + shift) - shift])
            back = op.accumulate(ranks[::-1] - back_shift) + back_shift
            backward.append(values[back[::-1]])
        return forward, backward


def _sah_costs(order, subtree, position, size, lo: _Ranked, hi: _Ranked) -> np.ndarray:
    """(n,) SAH cost of splitting each subtree after each of its triangles in ``order`` (the
    triangles, sorted along one axis within each subtree); inf after a subtree's last one."""
    offset = subtree * (lo.ranks[0].shape[0] + 1)
    (lo_first, lo_last), (hi_first, hi_last) = (
        lo.running(order, offset, np.minimum),
        hi.running(order, offset, np.maximum),
    )
    left, right = _half_area(lo_first, hi_first), _half_area(lo_last, hi_last)
    count = position + 1
    cost = left * count + np.r_[right[1:], 0.0] * (size - count)
    cost[count == size] = np.inf
    return cost


def _first_minimum(values, subtree, starts) -> tuple[np.ndarray, np.ndarray]:
    """Per subtree (contiguous runs of ``values``): its minimum and where it first occurs."""
    minimum = np.minimum.reduceat(values, starts)
    at = np.flatnonzero(values == minimum[subtree])
    first = at[np.r_[True, subtree[at][1:] != subtree[at][:-1]]]
    return minimum, first


def _starts(sizes: np.ndarray) -> np.ndarray:
    """(S,) where each of the contiguous runs of ``sizes`` (S,) entries starts."""
    return np.r_[0, np.cumsum(sizes)[:-1]]


def _run_ids(sizes: np.ndarray) -> np.ndarray:
    """(sum(sizes),) the run each entry belongs to."""
    return np.repeat(np.arange(sizes.shape[0]), sizes)


class _Level(NamedTuple):
    """The subtrees of one depth, in breadth-first order (a node's two children side by side).

    Attributes:
        order: (n,) triangle indices, each subtree's a contiguous run (in its parent's split order).
        sizes: (S,) triangles per subtree.
        is_leaf: (S,) bool, the subtree is a leaf (at most ``leaf_size`` triangles).
        boxes: (S, 6) float64 padded boxes ``[lo, hi]``.
    """

    order: np.ndarray
    sizes: np.ndarray
    is_leaf: np.ndarray
    boxes: np.ndarray

    @property
    def starts(self) -> np.ndarray:
        return _starts(self.sizes)

    @property
    def subtree(self) -> np.ndarray:
        """(n,) the subtree of each entry of ``order``."""
        return _run_ids(self.sizes)


def _split(order, sizes, depth, median_depth, centroids, centroid_ranks, lo, hi):
    """Split every subtree (``order``, ``sizes`` as :class:`_Level`'s) in two, as the recursive
    build does: along the axis and after the triangle of least SAH cost (the first axis and
    position on ties), or, from ``median_depth`` on, at the median along the longest axis of the
    centroids. Returns the children's ``order`` and ``sizes`` (left, right per subtree)."""
    starts, subtree = _starts(sizes), _run_ids(sizes)
    position = np.arange(order.shape[0]) - starts[subtree]
    key = subtree * (centroid_ranks[0].shape[0] + 1)  # beyond every rank: sorts by subtree first
    # each subtree's triangles sorted along each axis, ties in their current order (stable)
    sorted_orders = np.stack(
        [order[np.argsort(key + centroid_ranks[axis][order], kind="stable")] for axis in range(3)]
    )
    if depth < median_depth:
        best_cost = np.full(sizes.shape[0], np.inf)
        axis, count = np.zeros(sizes.shape[0], np.int64), sizes // 2
        for a in range(3):
            cost = _sah_costs(sorted_orders[a], subtree, position, sizes[subtree], lo, hi)
            minimum, first = _first_minimum(cost, subtree, starts)
            better = minimum < best_cost
            best_cost[better] = minimum[better]
            axis[better], count[better] = a, first[better] - starts[better] + 1
    else:
        spread = np.maximum.reduceat(centroids[order], starts) - np.minimum.reduceat(
            centroids[order], starts
        )
        axis, count = np.argmax(spread, axis=1), sizes // 2
    children = sorted_orders[axis[subtree], np.arange(order.shape[0])]
    return children, np.stack([count, sizes - count], 1).reshape(-1)


def _preorder(levels: list[_Level]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per level, each subtree's number among the internal nodes and among the leaves in
    depth-first preorder (a node, then its left subtree, then its right one)."""
    internal_below, leaves_below = [], []  # per level: internal nodes / leaves of each subtree
    for level in reversed(levels):
        internal, leaves = (~level.is_leaf).astype(np.int64), level.is_leaf.astype(np.int64)
        if internal_below:
            internal[~level.is_leaf] += internal_below[0].reshape(-1, 2).sum(1)
            leaves[~level.is_leaf] += leaves_below[0].reshape(-1, 2).sum(1)
        internal_below.insert(0, internal)
        leaves_below.insert(0, leaves)
    internal_number, leaf_number = [np.zeros(1, np.int64)], [np.zeros(1, np.int64)]
    for depth, level in enumerate(levels[:-1]):
        parent = internal_number[depth][~level.is_leaf]
        parent_leaves = leaf_number[depth][~level.is_leaf]
        left_internal = internal_below[depth + 1][0::2]
        left_leaves = leaves_below[depth + 1][0::2]
        internal_number.append(np.stack([parent + 1, parent + 1 + left_internal], 1).reshape(-1))
        leaf_number.append(np.stack([parent_leaves, parent_leaves + left_leaves], 1).reshape(-1))
    return internal_number, leaf_number


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
    lo, hi, centres = _Ranked.of(tri_lo), _Ranked.of(tri_hi), _Ranked.of(centroids)

    levels: list[_Level] = []
    order, sizes = np.arange(num_tris), np.array([num_tris])
    while True:
        starts = _starts(sizes)
        boxes = np.concatenate(
            [
                np.minimum.reduceat(tri_lo[order], starts) - pad,
                np.maximum.reduceat(tri_hi[order], starts) + pad,
            ],
            axis=1,
        )
        level = _Level(order, sizes, sizes <= leaf_size, boxes)
        levels.append(level)
        if level.is_leaf.all():
            break
        inner = ~level.is_leaf[level.subtree]
        order, sizes = _split(
            order[inner], sizes[~level.is_leaf], len(levels) - 1, median_depth,
            centroids, centres.ranks, lo, hi,
        )  # fmt: skip

    internal_number, leaf_number = _preorder(levels)
    num_internal = int(sum((~level.is_leaf).sum() for level in levels))
    num_leaves = int(sum(level.is_leaf.sum() for level in levels))
    children_arr = np.zeros((max(num_internal, 1), 2), np.int32)
    internal_boxes = np.zeros((max(num_internal, 1), 6))
    leaf_boxes = np.zeros((num_leaves, 6))
    leaf_ids = np.full((num_leaves, leaf_size), -1, np.int32)
    for depth, level in enumerate(levels):
        leaf, inner = level.is_leaf, ~level.is_leaf
        refs = np.where(leaf, -2 - leaf_number[depth], internal_number[depth])
        if depth > 0:
            children_arr[internal_number[depth - 1][~levels[depth - 1].is_leaf]] = refs.reshape(
                -1, 2
            )
        internal_boxes[internal_number[depth][inner]] = level.boxes[inner]
        leaf_boxes[leaf_number[depth][leaf]] = level.boxes[leaf]
        subtree = level.subtree
        in_leaf = leaf[subtree]
        slot = np.arange(level.order.shape[0]) - level.starts[subtree]
        leaf_ids[leaf_number[depth][subtree[in_leaf]], slot[in_leaf]] = level.order[in_leaf]
    root = int(np.where(levels[0].is_leaf, -2, 0)[0])
    if num_internal == 0:  # a single leaf: keep one unused internal node so no array is empty
        children_arr[:] = root

    safe = np.maximum(leaf_ids, 0)
    v0 = triangles[safe, 0]
    e1 = triangles[safe, 1] - v0
    e2 = triangles[safe, 2] - v0
    packed = np.concatenate([v0, e1, e2], axis=-1)  # (L, K, 9)
    packed[leaf_ids < 0] = 0.0
    leaf_triangles = np.ascontiguousarray(packed.transpose(0, 2, 1)).astype(np.float32)
    bounds = np.concatenate([internal_boxes, leaf_boxes]).astype(np.float32)
    return FlatBVH(bounds, children_arr, leaf_triangles, leaf_ids, root, len(levels) - 1)
