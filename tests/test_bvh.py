"""The level-by-level BVH build against the recursive build it replaced (one subtree at a time, the
textbook full-sweep SAH): the same tree, array for array, on scenes with tied centroids, flat
and degenerate triangles, median splits and every leaf size."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import box_room, random_meshes

from jaxloc.raycasting.bvh import BOX_EPSILON, build_bvh


def _half_area(lo, hi):
    ext = np.maximum(hi - lo, 0.0)
    return ext[..., 0] * ext[..., 1] + ext[..., 1] * ext[..., 2] + ext[..., 2] * ext[..., 0]


def recursive_bvh(triangles, leaf_size=4, median_depth=32):
    """The reference: (bounds, node_children, leaf_triangle_ids, root, depth), nodes and leaves
    numbered as they are created by a depth-first recursion (preorder)."""
    triangles = np.asarray(triangles, np.float64)
    tri_lo, tri_hi = triangles.min(axis=1), triangles.max(axis=1)
    centroids = triangles.mean(axis=1)
    pad = BOX_EPSILON * max(float(np.max(tri_hi.max(0) - tri_lo.min(0))), 1.0)
    boxes, children, leaves, depths = [], [], [], []

    def box(indices):
        return np.concatenate([tri_lo[indices].min(0) - pad, tri_hi[indices].max(0) + pad])

    def sah_split(indices):
        n, best = indices.shape[0], (np.inf, None, indices.shape[0] // 2)
        for axis in range(3):
            order = np.argsort(centroids[indices, axis], kind="stable")
            lo, hi = tri_lo[indices][order], tri_hi[indices][order]
            left = _half_area(np.minimum.accumulate(lo, 0), np.maximum.accumulate(hi, 0))[:-1]
            right = _half_area(
                np.minimum.accumulate(lo[::-1], 0)[::-1], np.maximum.accumulate(hi[::-1], 0)[::-1]
            )[1:]
            counts = np.arange(1, n)
            cost = left * counts + right * (n - counts)
            i = int(np.argmin(cost))
            if cost[i] < best[0]:
                best = (cost[i], order, i + 1)
        return best[1], best[2]

    def build(indices, depth):
        depths.append(depth)
        if indices.shape[0] <= leaf_size:
            leaves.append(indices)
            return -2 - (len(leaves) - 1)
        if depth < median_depth:
            order, count = sah_split(indices)
        else:
            c = centroids[indices]
            axis = int(np.argmax(c.max(0) - c.min(0)))
            order, count = np.argsort(c[:, axis], kind="stable"), indices.shape[0] // 2
        node = len(children)
        children.append([0, 0])
        boxes.append(box(indices))
        children[node] = [build(indices[order[:count]], depth + 1),
                          build(indices[order[count:]], depth + 1)]  # fmt: skip
        return node

    root = build(np.arange(triangles.shape[0]), 0)
    leaf_ids = np.full((len(leaves), leaf_size), -1, np.int32)
    for i, leaf in enumerate(leaves):
        leaf_ids[i, : leaf.shape[0]] = leaf
    children = np.asarray(children or [[root, root]], np.int32)
    internal = np.asarray(boxes) if boxes else np.zeros((1, 6))
    bounds = np.concatenate([internal, [box(leaf) for leaf in leaves]]).astype(np.float32)
    return bounds, children, leaf_ids, root, max(depths)


def _triangles(meshes) -> np.ndarray:
    return np.concatenate([m.triangles for m in meshes]).astype(np.float32)


def _cases():
    rng = np.random.default_rng(7)
    grid = trimesh.creation.box(extents=[4.0, 3.0, 2.5]).subdivide().subdivide()
    flat = rng.normal(size=(300, 3, 3))
    flat[..., 2] = 0.0  # all in one plane: zero-area boxes, the cost ties on one axis
    return {
        "random objects": (_triangles(random_meshes(3)), {}),
        "box room (tied centroids)": (_triangles(box_room()), {}),
        "subdivided box": (grid.triangles.astype(np.float32), {}),
        "rounded coordinates": (np.round(rng.normal(size=(500, 3, 3))).astype(np.float32), {}),
        "one plane": (flat.astype(np.float32), {}),
        "identical triangles": (np.repeat(rng.normal(size=(1, 3, 3)), 40, 0), {}),
        "median splits from depth 3": (rng.normal(size=(400, 3, 3)), {"median_depth": 3}),
        "leaf size 1": (rng.normal(size=(200, 3, 3)), {"leaf_size": 1}),
        "leaf size 8": (_triangles(random_meshes(4, 12)), {"leaf_size": 8}),
        "one triangle": (rng.normal(size=(1, 3, 3)), {}),
        "a full leaf": (rng.normal(size=(4, 3, 3)), {}),
        "one over a leaf": (rng.normal(size=(5, 3, 3)), {}),
    }


@pytest.mark.parametrize("case", list(_cases()))
def test_level_by_level_build_equals_the_recursive_build(case):
    triangles, options = _cases()[case]
    bvh = build_bvh(triangles, **options)
    bounds, children, leaf_ids, root, depth = recursive_bvh(triangles, **options)
    np.testing.assert_array_equal(bvh.node_children, children)
    np.testing.assert_array_equal(bvh.leaf_triangle_ids, leaf_ids)
    np.testing.assert_array_equal(bvh.bounds, bounds)
    assert (bvh.root, bvh.depth) == (root, depth)
    # every triangle in exactly one leaf, its corners packed as v0, e1, e2
    ids = bvh.leaf_triangle_ids[bvh.leaf_triangle_ids >= 0]
    np.testing.assert_array_equal(np.sort(ids), np.arange(len(triangles)))
    leaf, slot = np.nonzero(bvh.leaf_triangle_ids >= 0)
    v0 = np.asarray(triangles, np.float64)[bvh.leaf_triangle_ids[leaf, slot], 0]
    np.testing.assert_array_equal(bvh.leaf_triangles[leaf, 0:3, slot], v0.astype(np.float32))
    assert not bvh.leaf_triangles.transpose(0, 2, 1)[bvh.leaf_triangle_ids < 0].any()
