"""Verified clique hypotheses: when the maximum clique's pose is rejected, rank other cliques by
how much of the scan their pose explains (pure JAX, static sizes).

In dense, repetitive maps (DCC04's pole rows) a query's true clique is often no larger than
several cliques of false associations, so the maximum clique is a coin toss among them, while the
verification (the fraction of scan vertices that land on a map vertex of their class) tells the
true pose apart: 0.76-0.92 for the true pose of every DCC04 development query that failed, below
0.5 for the poses the pipeline had found (``experiments/results/m2loc/hypotheses.md``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.m2loc._clique import _popcount, greedy_cliques, padded_size, unpack_ranked

#: Odd 32-bit multipliers of the clique hash (constants: results must not depend on a key).
_HASH_SEED = 0x9E3779B9


def _clique_hashes(cliques: Array) -> Array:
    """(n,) uint32 hash of packed cliques (n, W) uint32 (equal cliques, equal hashes)."""
    words = cliques.shape[1]
    multipliers = (jnp.arange(words, dtype=jnp.uint32) * jnp.uint32(2654435761)) ^ jnp.uint32(
        _HASH_SEED
    )
    multipliers = multipliers | jnp.uint32(1)
    mixed = cliques * multipliers[None, :]
    mixed = mixed ^ (mixed >> 15)
    return jnp.sum(mixed * jnp.uint32(2246822519), axis=1, dtype=jnp.uint32)


class MapGrid(eqx.Module):
    """Map vertices sorted by a square XY cell of side ``cell`` metres (for radius queries).

    Attributes:
        keys: (Nm,) int32 sorted cell keys; points: (Nm, 3) float32 vertices in key order;
        classes: (Nm,) int32; low: (2,) float32 lower XY corner; cell: static side (metres);
        columns: static cells per side.
    """

    keys: Array
    points: Array
    classes: Array
    low: Array
    cell: float = eqx.field(static=True)
    columns: int = eqx.field(static=True)


#: Cells per side of a :class:`MapGrid`. Keys are int32: cells beyond 46k per side (69 km at
#: 1.5 m) fold together, which only adds candidates that the distance test then rejects.
GRID_COLUMNS = 46000


def _sorted_cells(xp, map_points, map_classes, cell: float) -> tuple:
    """(keys, points, classes, low) of :class:`MapGrid` in the array namespace ``xp`` (numpy on
    the host, jax.numpy when traced): the same float32 and int32 operations in both."""
    low = xp.min(map_points[:, :2], axis=0) - xp.float32(cell)
    index = xp.floor((map_points[:, :2] - low) / xp.float32(cell))
    index = xp.clip(index, 0, GRID_COLUMNS - 1).astype(xp.int32)
    keys = index[:, 0] * xp.int32(GRID_COLUMNS) + index[:, 1]
    order = xp.argsort(keys, stable=True)
    return keys[order], map_points[order], map_classes[order], low


@functools.partial(jax.jit, static_argnames="cell")  # one program, not a dozen eager ones
def map_grid(map_points: Array, map_classes: Array, cell: float) -> MapGrid:
    """Sort the map's vertices into XY cells of side ``cell`` metres (jitted; static size).

    Args:
        map_points: (Nm, 3) float32 vertices (metres); map_classes: (Nm,) int32.
        cell: the cells' side (metres).
    """
    return MapGrid(*_sorted_cells(jnp, map_points, map_classes, cell), cell, GRID_COLUMNS)


def host_map_grid(map_points: np.ndarray, map_classes: np.ndarray, cell: float) -> MapGrid:
    """:func:`map_grid` of host arrays, computed by numpy (equal to it, array for array) and put
    on the device: a map is built without compiling a program for its size."""
    points = np.asarray(map_points, np.float32)
    classes = np.asarray(map_classes, np.int32)
    keys, points, classes, low = _sorted_cells(np, points, classes, cell)
    return MapGrid(*jax.device_put((keys, points, classes, low)), cell, GRID_COLUMNS)


def grid_verified_fraction(
    T_map_scan: Array,
    points: Array,
    classes: Array,
    mask: Array,
    grid: MapGrid,
    radius: float,
    discount: int,
    bucket: int = 16,
) -> Array:
    """``verified_fraction`` through a :class:`MapGrid` (cell >= radius):
    each moved scan vertex is tested against the first ``bucket`` vertices of the 3 x 3 cells
    around it, not the whole map. Equal to the brute force unless a cell holds more than
    ``bucket`` vertices, where it can only count fewer (a stricter check, never a laxer one).

    Args:
        T_map_scan: (4, 4) pose; points: (Nq, 3); classes: (Nq,) int32; mask: (Nq,) bool.
        grid: from :func:`map_grid`; radius: metres (<= ``grid.cell``); discount: as
            ``verified_fraction``; bucket: static vertices read per cell.

    Returns:
        float32 scalar in [0, 1].
    """
    moved = jnp.matmul(points, T_map_scan[:3, :3].T, precision="highest") + T_map_scan[:3, 3]
    index = jnp.floor((moved[:, :2] - grid.low) / grid.cell).astype(jnp.int32)
    offsets = jnp.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)], jnp.int32)
    cells = jnp.clip(index[:, None, :] + offsets[None], 0, grid.columns - 1)  # (Nq, 9, 2)
    keys = cells[..., 0] * grid.columns + cells[..., 1]
    start = jnp.searchsorted(grid.keys, keys.reshape(-1), side="left").reshape(keys.shape)
    slots = jnp.minimum(start[..., None] + jnp.arange(bucket), grid.keys.shape[0] - 1)
    same_cell = grid.keys[slots] == keys[..., None]  # (Nq, 9, bucket)
    squared = jnp.sum((grid.points[slots] - moved[:, None, None, :]) ** 2, axis=-1)
    hit = same_cell & (grid.classes[slots] == classes[:, None, None]) & (squared <= radius**2)
    near = jnp.any(hit, axis=(1, 2)) & mask
    kept = jnp.maximum(jnp.sum(near) - discount, 0)
    return kept / jnp.maximum(jnp.sum(mask) - discount, 1)


def closed_form_poses(masks: Array, query_xyz: Array, map_xyz: Array) -> Array:
    """Kabsch poses ``T_map_scan`` (N, 4, 4) of N association subsets at once.

    The per-subset sums (counts, means, cross moments) are one (N, A) x (A, 15) product, so N
    subsets cost one pass over the associations, not N (as N calls of
    ``weighted_kabsch`` would: 11 ms for 256 subsets of 2400 associations on
    DCC04, ~1 ms this way). Subsets of fewer than 3 associations give the identity.

    Args:
        masks: (N, A) bool subsets; query_xyz: (A, 3) scan points; map_xyz: (A, 3) map points.
    """
    weights = masks.astype(query_xyz.dtype)
    moments = jnp.concatenate(
        [
            jnp.ones_like(query_xyz[:, :1]),
            query_xyz,
            map_xyz,
            (map_xyz[:, :, None] * query_xyz[:, None, :]).reshape(-1, 9),
        ],
        axis=1,
    )
    sums = jnp.matmul(weights, moments, precision="highest")  # (N, 16)
    count = jnp.maximum(sums[:, :1], 1.0)
    mean_query, mean_map = sums[:, 1:4] / count, sums[:, 4:7] / count
    covariance = (sums[:, 7:] / count).reshape(-1, 3, 3) - mean_map[:, :, None] * mean_query[
        :, None, :
    ]
    u, _, vt = jnp.linalg.svd(covariance)
    sign = jnp.sign(jnp.linalg.det(jnp.matmul(u, vt, precision="highest")))
    sign = jnp.where(sign == 0, 1.0, sign)
    u = u.at[:, :, 2].multiply(sign[:, None])
    rotation = jnp.matmul(u, vt, precision="highest")
    translation = mean_map - jnp.einsum("nij,nj->ni", rotation, mean_query, precision="highest")
    poses = jnp.zeros((masks.shape[0], 4, 4), query_xyz.dtype).at[:, 3, 3].set(1.0)
    poses = poses.at[:, :3, :3].set(rotation).at[:, :3, 3].set(translation)
    usable = (sums[:, 0] >= 3) & jnp.all(jnp.isfinite(poses), axis=(1, 2))
    return jnp.where(usable[:, None, None], poses, jnp.eye(4, dtype=query_xyz.dtype))


def hypothesis_slots(num_associations: int, count: int) -> int:
    """H, the hypotheses :func:`verified_hypotheses` returns for ``num_associations`` (A) and
    ``count`` (one greedy clique per padded vertex at most)."""
    return min(count, padded_size(num_associations))


def verified_hypotheses(
    adjacency: Array,
    valid: Array,
    query_xyz: Array,
    map_xyz: Array,
    verify: Callable[[Array], Array],
    count: int,
) -> tuple[Array, Array, Array]:
    """The ``count`` largest distinct greedy cliques grown from every association (at least 3
    associations), a closed-form pose each, and each pose's verification.

    Args:
        adjacency: (A, A) bool consistency graph (symmetric, masked by ``valid``).
        valid: (A,) bool usable associations.
        query_xyz: (A, 3) scan-frame positions; map_xyz: (A, 3) map positions (centred frame).
        verify: ``T (4, 4) -> fraction`` scalar, the place check of the pipeline.
        count: static number of hypotheses verified.

    Returns:
        ``(cliques (H, A) bool, T_map_scan (H, 4, 4), fractions (H,))`` with H = min(count, A);
        a slot without a clique of 3 or more has fraction -1.
    """
    n = adjacency.shape[0]
    cliques, order = greedy_cliques(adjacency, valid)
    sizes = _popcount(cliques)
    hashes = _clique_hashes(cliques)
    by_hash = jnp.lexsort((-sizes, hashes))  # equal cliques next to each other
    repeated = (
        jnp.zeros(sizes.shape, bool)
        .at[by_hash[1:]]
        .set(hashes[by_hash[1:]] == hashes[by_hash[:-1]])
    )
    score = jnp.where(repeated | (sizes < 3), -1, sizes).astype(jnp.float32)
    top_score, chosen = jax.lax.top_k(score, hypothesis_slots(n, count))
    masks = jax.vmap(lambda clique: unpack_ranked(clique, order, n))(cliques[chosen])
    poses = closed_form_poses(masks, query_xyz, map_xyz)
    fractions = jnp.where(top_score >= 3, jax.vmap(verify)(poses), -1.0)
    return masks, poses, fractions


def best_verified_clique(
    adjacency: Array,
    valid: Array,
    query_xyz: Array,
    map_xyz: Array,
    verify: Callable[[Array], Array],
    count: int,
) -> tuple[Array, Array, Array]:
    """Among :func:`verified_hypotheses` (same arguments), the clique whose pose verifies best.

    Returns:
        ``(clique (A,) bool, T_map_scan (4, 4), fraction)``: the best-verified clique, its
        closed-form pose and that pose's verification (all False, the identity and -1 when no
        clique of 3 or more exists).
    """
    return best_hypothesis(
        *verified_hypotheses(adjacency, valid, query_xyz, map_xyz, verify, count)
    )


def best_hypothesis(masks: Array, poses: Array, fractions: Array) -> tuple[Array, Array, Array]:
    """The best-verified of :func:`verified_hypotheses`' outputs, as :func:`best_verified_clique`
    returns it."""
    best = jnp.argmax(fractions)
    found = fractions[best] >= 0
    pose = jnp.where(found, poses[best], jnp.eye(4, dtype=poses.dtype))
    return masks[best] & found, pose, fractions[best]
