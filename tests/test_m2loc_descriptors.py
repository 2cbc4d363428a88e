"""Triplet descriptors vs a brute-force TripletLoc-style reference; invariance; jit; map path."""

import itertools
import math

import jax
import numpy as np
import pytest

from jaxloc.m2loc import DescriptorConfig, describe_points
from jaxloc.m2loc._descriptors import describe_map, map_neighbour_lists, neighbour_capacity

CLASSES = (15, 17, 18)

#: The compiled descriptor (eager dispatch compiles every inner op apart, which is slow); the
#: eager path is checked against the jitted, vmapped one in test_vmap_over_queries_equals_loop.
DESCRIBE = jax.jit(describe_points, static_argnums=3)


def vote(hist, start, u, bins, config):
    """One pair's vote at bin coordinate u: one bin (hard) or the two enclosing bin centres."""
    if not config.soft_bins:
        hist[start + min(max(int(math.floor(u)), 0), bins - 1)] += 1
        return
    lower = math.floor(u - 0.5)
    share = (u - 0.5) - lower
    hist[start + min(max(lower, 0), bins - 1)] += 1 - share
    hist[start + min(max(lower + 1, 0), bins - 1)] += share


def reference(points, classes, config):
    """Loop over every vertex, scale and neighbour pair (TripletLoc's get_descriptor_fast)."""
    n, s_count = len(points), config.num_scales
    table = config.combination_table()
    per = config.angle_bins + config.num_length_histograms * config.length_bins
    out = np.zeros((s_count, n, config.dim))
    valid = np.zeros((s_count, n), bool)
    for s, (low, high) in enumerate(config.scale_bounds().astype(np.float64)):
        for i in range(n):
            nbrs = [
                j
                for j in range(n)
                if j != i
                and (np.linalg.norm(points[j] - points[i]) <= high)
                and (low == 0 or np.linalg.norm(points[j] - points[i]) > low)
            ]
            if len(nbrs) < 2:
                continue
            valid[s, i] = True
            hist = np.zeros(config.dim)
            for a, b in itertools.combinations(nbrs, 2):
                va, vb = points[a, :2] - points[i, :2], points[b, :2] - points[i, :2]
                theta = math.atan2(va[0], va[1]) - math.atan2(vb[0], vb[1])
                if theta >= math.pi:
                    theta -= 2 * math.pi
                if theta <= -math.pi:
                    theta += 2 * math.pi
                angle = abs(math.degrees(theta))
                base = table[classes[a], classes[b]] * per
                vote(hist, base, angle / (180 / config.angle_bins), config.angle_bins, config)
                la, lb = np.linalg.norm(va), np.linalg.norm(vb)
                offset = config.angle_bins
                nb = config.length_bins
                if config.length_feature in ("length", "both"):
                    vote(hist, base + offset, ((la + lb) / 2 - low) / (high - low) * nb, nb, config)
                    offset += nb
                if config.length_feature in ("ratio", "both"):
                    ratio = min(la, lb) / max(la, lb) if max(la, lb) > 0 else 1.0
                    vote(hist, base + offset, ratio * nb, nb, config)
            out[s, i] = hist / np.linalg.norm(hist)
    return out, valid


def random_vertices(n, seed, extent=30.0):
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(-extent, extent, (n, 2)), rng.uniform(0, 4, n)])
    return points.astype(np.float32), rng.integers(0, 3, n).astype(np.int32)


@pytest.mark.parametrize(
    "config",
    [
        DescriptorConfig(CLASSES, (20.0,), length_feature="length"),
        DescriptorConfig(CLASSES, (10.0, 20.0, 30.0), length_feature="ratio"),
        DescriptorConfig(CLASSES, (15.0, 25.0), length_feature="both"),
        DescriptorConfig(CLASSES, (10.0, 20.0, 30.0), length_feature="ratio", soft_bins=True),
        DescriptorConfig(CLASSES, (20.0,), length_feature="both", soft_bins=True),
    ],
)
def test_descriptors_match_brute_force_under_jit(config):
    points, classes = random_vertices(24, 0)
    mask = np.ones(24, bool)
    mask[-3:] = False  # padding
    got, valid = DESCRIBE(points, classes, mask, config)
    ref, ref_valid = reference(points[:21].astype(np.float64), classes[:21], config)
    assert got.shape == (config.num_scales, 24, config.dim)
    np.testing.assert_array_equal(np.asarray(valid)[:, :21], ref_valid)
    assert not np.asarray(valid)[:, 21:].any()
    np.testing.assert_allclose(np.asarray(got)[:, :21], ref, atol=1e-5)


def test_tripletloc_dimension_and_invalid_vertices():
    config = DescriptorConfig()
    assert config.dim == 456
    points = np.array([[0, 0, 0], [1, 0, 0], [50, 0, 0], [51, 1, 0]], np.float32)
    _, valid = DESCRIBE(points, np.zeros(4, np.int32), np.ones(4, bool), config)
    assert not np.asarray(valid).any()  # each vertex has only one neighbour within 20 m


def test_invariant_to_rigid_motion_about_z_and_permutation():
    config = DescriptorConfig(CLASSES, (10.0, 20.0, 30.0), length_feature="both")
    points, classes = random_vertices(20, 1)
    yaw = 0.7
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    moved = (points @ rot.T + np.array([100.0, -40.0, 3.0])).astype(np.float32)
    perm = np.random.default_rng(2).permutation(20)
    mask = np.ones(20, bool)
    a, va = DESCRIBE(points, classes, mask, config)
    b, vb = DESCRIBE(moved[perm], classes[perm], mask, config)
    np.testing.assert_array_equal(np.asarray(va)[:, perm], np.asarray(vb))
    np.testing.assert_allclose(np.asarray(a)[:, perm], np.asarray(b), atol=1e-5)


def test_vmap_over_queries_equals_loop():
    """The jitted vmap over queries equals an eager loop (so eager equals jit too)."""
    config = DescriptorConfig(CLASSES, (20.0,))
    batch = [random_vertices(16, seed) for seed in range(3)]
    points = np.stack([b[0] for b in batch])
    classes = np.stack([b[1] for b in batch])
    mask = np.ones((3, 16), bool)
    batched, _ = jax.jit(jax.vmap(describe_points, in_axes=(0, 0, 0, None)), static_argnums=3)(
        points, classes, mask, config
    )
    for i in range(3):
        single, _ = describe_points(points[i], classes[i], mask[i], config)
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(single), atol=1e-6)


def test_map_path_equals_points_path():
    """The bucketed, chunked map path equals the dense query path on a map whose vertices need
    different neighbour capacities (a dense cluster beside sparse vertices)."""
    config = DescriptorConfig(CLASSES, (10.0, 20.0), length_feature="ratio")
    sparse_points, sparse_classes = random_vertices(40, 3, extent=40.0)
    dense_points, dense_classes = random_vertices(40, 4, extent=3.0)
    denser_points, denser_classes = random_vertices(70, 5, extent=4.0)
    denser_points += np.array([30.0, 30.0, 0.0], np.float32)
    points = np.concatenate([sparse_points, dense_points, denser_points])
    classes = np.concatenate([sparse_classes, dense_classes, denser_classes])
    counts = [c.size for c in map_neighbour_lists(points.astype(np.float64), 0.0, 10.0)]
    assert len({neighbour_capacity(c) for c in counts}) >= 3
    dense, dense_valid = DESCRIBE(points, classes, np.ones(len(points), bool), config)
    mapped, mapped_valid = describe_map(
        points.astype(np.float64) + 500.0, classes, config, pair_budget=2048
    )
    np.testing.assert_array_equal(np.asarray(dense_valid), mapped_valid)
    np.testing.assert_allclose(np.asarray(dense), mapped, atol=1e-5)
