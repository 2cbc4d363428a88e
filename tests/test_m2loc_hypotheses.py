"""Verified clique hypotheses (M2Loc on small scans), the kernels: greedy cliques from every
vertex against a numpy reference, the grid verification against the brute-force one, closed-form
poses against numpy Kabsch, the best-verified clique against a numpy search. The pipeline option
is tested in ``test_m2loc_options.py``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc.m2loc._clique import greedy_cliques, unpack_ranked
from jaxloc.m2loc._hypotheses import (
    best_verified_clique,
    closed_form_poses,
    grid_verified_fraction,
    host_map_grid,
    map_grid,
)
from jaxloc.m2loc._matching import consistency_graph
from jaxloc.m2loc._query import verified_fraction


def random_graph(rng, n, density):
    upper = np.triu(rng.random((n, n)) < density, 1)
    valid = rng.random(n) < 0.9
    adjacency = (upper | upper.T) & valid[:, None] & valid[None, :]
    return adjacency, valid


def greedy_reference(adjacency, valid, seed):
    """The clique grown from ``seed``: add the candidate of highest degree (ties: lowest index)."""
    degree = np.where(valid, adjacency.sum(1), -1)
    clique, candidates = [seed], adjacency[seed].copy()
    while candidates.any():
        v = int(np.argmax(np.where(candidates, degree, -1)))
        clique.append(v)
        candidates &= adjacency[v]
    mask = np.zeros(len(valid), bool)
    mask[clique] = True
    return mask


@pytest.mark.parametrize("n, density", [(5, 0.5), (45, 0.4), (70, 0.15)])
def test_greedy_cliques_match_numpy(n, density):
    adjacency, valid = random_graph(np.random.default_rng(n), n, density)
    cliques, order = jax.jit(greedy_cliques)(jnp.asarray(adjacency), jnp.asarray(valid))
    assert cliques.shape[0] == order.shape[0] == -(-n // 32) * 32
    seen = set()
    for row, seed in enumerate(np.asarray(order)):
        got = np.asarray(unpack_ranked(cliques[row], order, n))
        if seed >= n or not valid[seed]:
            assert not got.any()
            continue
        seen.add(int(seed))
        np.testing.assert_array_equal(got, greedy_reference(adjacency, valid, seed))
        members = np.flatnonzero(got)
        assert np.all(adjacency[np.ix_(members, members)] | np.eye(len(members), dtype=bool))
    assert seen == set(np.flatnonzero(valid).tolist())


def yaw_pose(rng):
    angle = rng.uniform(-np.pi, np.pi)
    pose = np.eye(4, dtype=np.float32)
    pose[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    pose[:3, 3] = rng.normal(0, 3, 3)
    return pose


def test_grid_verification_equals_brute_force_and_is_never_laxer():
    rng = np.random.default_rng(1)
    map_points = rng.uniform(-100, 100, (3000, 3)).astype(np.float32)
    map_points[:, 2] *= 0.05
    map_points[:40] = map_points[40] + rng.normal(0, 0.3, (40, 3))  # one crowded cell
    map_classes = rng.integers(0, 3, 3000).astype(np.int32)
    grid = map_grid(jnp.asarray(map_points), jnp.asarray(map_classes), 1.5)
    verify = jax.jit(grid_verified_fraction, static_argnames=("radius", "discount", "bucket"))
    for trial in range(30):
        chosen = rng.choice(3000, 32, replace=False)
        chosen[:3] = [0, 1, 40]  # some scan vertices in the crowded cell
        pose = yaw_pose(rng)
        in_map = map_points[chosen] + rng.normal(0, 1.0, (32, 3)).astype(np.float32)
        scan = (in_map - pose[:3, 3]) @ pose[:3, :3]
        classes = map_classes[chosen].copy()
        classes[3:8] = rng.integers(0, 3, 5)
        mask = rng.random(32) < 0.9
        args = (jnp.asarray(pose), jnp.asarray(scan), jnp.asarray(classes), jnp.asarray(mask))
        want = float(
            verified_fraction(
                *args, jnp.asarray(map_points), jnp.asarray(map_classes), 1.5, discount=3
            )
        )
        got = float(verify(*args, grid, radius=1.5, discount=3, bucket=64))
        assert got == pytest.approx(want, abs=1e-6), trial
        small = float(verify(*args, grid, radius=1.5, discount=3, bucket=4))
        assert small <= got + 1e-6  # a full cell can only count fewer


@pytest.mark.parametrize("cell", [1.5, 0.37, 40.0])
def test_host_map_grid_equals_the_jitted_grid(cell):
    rng = np.random.default_rng(5)
    map_points = rng.uniform(-300, 300, (2000, 3)).astype(np.float32)
    map_points[:50, :2] = np.round(map_points[:50, :2] / cell) * cell  # on cell boundaries
    map_points[50:90] = map_points[90]  # one cell with many vertices: order of equal keys
    map_classes = rng.integers(0, 5, 2000).astype(np.int32)
    jitted = map_grid(jnp.asarray(map_points), jnp.asarray(map_classes), cell)
    host = host_map_grid(map_points, map_classes, cell)
    assert (host.cell, host.columns) == (jitted.cell, jitted.columns)
    for name in ("keys", "points", "classes", "low"):
        got, want = getattr(host, name), getattr(jitted, name)
        assert (got.dtype, got.shape) == (want.dtype, want.shape), name
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=name)
    assert np.all(np.diff(np.asarray(host.keys)) >= 0)


def numpy_kabsch(source, target):
    cs, ct = source.mean(0), target.mean(0)
    u, _, vt = np.linalg.svd((target - ct).T @ (source - cs))
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, ct - rotation @ cs
    return pose


def test_best_verified_clique_prefers_the_pose_that_explains_the_scan():
    """A query whose largest clique is a wrong hypothesis: a numpy search over the same greedy
    cliques (sorted by size, deduplicated, Kabsch pose, brute-force verification) picks the same
    clique, and it is the true one, smaller than the false one."""
    rng = np.random.default_rng(5)
    map_points = rng.uniform(-60, 60, (400, 3))
    map_points[:, 2] = rng.uniform(0, 4, 400)
    pose = yaw_pose(rng).astype(np.float64)
    truth = rng.choice(400, 12, replace=False)
    scan = (map_points[truth] + rng.normal(0, 0.1, (12, 3)) - pose[:3, 3]) @ pose[:3, :3]
    # true associations for 4 scan vertices; a false 6-clique: scan vertices 4-9 matched to a
    # rigidly moved copy of their true map vertices' layout, placed elsewhere in the map
    elsewhere = yaw_pose(rng).astype(np.float64)
    elsewhere[:3, 3] += (150.0, 0.0, 0.0)
    decoys = scan[4:10] @ elsewhere[:3, :3].T + elsewhere[:3, 3]
    points = np.concatenate([map_points, decoys])
    classes = np.zeros(len(points), np.int32)
    query_index = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11])
    map_index = np.concatenate([truth[:4], 400 + np.arange(6), rng.choice(400, 2)])
    query_xyz, map_xyz = scan[query_index], points[map_index]
    valid = np.ones(len(query_index), bool)
    adjacency = np.asarray(
        consistency_graph(query_xyz, map_xyz, valid, 1.0, query_index, map_index)
    )
    mask = np.ones(12, bool)

    def verify(matrix):
        return verified_fraction(
            matrix,
            jnp.asarray(scan, jnp.float32),
            jnp.zeros(12, jnp.int32),
            jnp.asarray(mask),
            jnp.asarray(points, jnp.float32),
            jnp.asarray(classes),
            1.5,
            discount=3,
        )

    found, pose, fraction = jax.jit(best_verified_clique, static_argnums=(4, 5))(
        jnp.asarray(adjacency),
        jnp.asarray(valid),
        jnp.asarray(query_xyz, jnp.float32),
        jnp.asarray(map_xyz, jnp.float32),
        verify,
        8,
    )
    # numpy search
    candidates = {}
    for seed in np.flatnonzero(valid):
        clique = greedy_reference(adjacency, valid, seed)
        if clique.sum() >= 3:
            candidates[tuple(np.flatnonzero(clique))] = clique
    scored = []
    for members, clique in candidates.items():
        matrix = numpy_kabsch(query_xyz[clique], map_xyz[clique])
        scored.append((float(verify(jnp.asarray(matrix, jnp.float32))), members))
    best_fraction, best_members = max(scored)
    largest = max(len(m) for _, m in scored)
    assert np.flatnonzero(np.asarray(found)).tolist() == list(best_members)
    assert float(fraction) == pytest.approx(best_fraction, abs=1e-6)
    np.testing.assert_allclose(
        np.asarray(pose), numpy_kabsch(query_xyz[:4], map_xyz[:4]), atol=1e-4
    )
    assert list(best_members) == [0, 1, 2, 3] and largest == 6


def test_closed_form_poses_equal_numpy_kabsch():
    rng = np.random.default_rng(3)
    pose = yaw_pose(rng)
    query = rng.uniform(-30, 30, (200, 3)).astype(np.float32)
    target = query @ pose[:3, :3].T + pose[:3, 3] + np.float32(400.0)  # far from the origin
    target[100:] = rng.uniform(-500, 500, (100, 3))  # other subsets: unrelated points
    masks = rng.random((16, 200)) < 0.05
    masks[0] = False
    masks[0, :10] = True  # an exact subset
    masks[1] = False
    masks[1, :2] = True  # too few points: identity
    got = np.asarray(jax.jit(closed_form_poses)(jnp.asarray(masks), query, target))
    for mask, matrix in zip(masks, got, strict=True):
        if mask.sum() < 3:
            np.testing.assert_array_equal(matrix, np.eye(4))
            continue
        want = numpy_kabsch(query[mask].astype(np.float64), target[mask].astype(np.float64))
        np.testing.assert_allclose(matrix, want, atol=2e-3)
    np.testing.assert_allclose(got[0][:3, 3], pose[:3, 3] + 400.0, atol=1e-3)
