"""Descriptor matching and the pairwise-consistency graph of associations (pure JAX)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array


def match_descriptors(
    query_descriptors: Array,
    query_valid: Array,
    query_classes: Array,
    map_descriptors: Array,
    map_valid: Array,
    map_classes: Array,
    k: int,
) -> tuple[Array, Array]:
    """The ``k`` nearest map descriptors (L2) of the same class for each query vertex (one scale).

    Args:
        query_descriptors: (Nq, D) L2-normalised descriptors; query_valid (Nq,) bool;
            query_classes (Nq,) int32 class positions.
        map_descriptors: (Nm, D); map_valid (Nm,) bool; map_classes (Nm,) int32.
        k: matches per query vertex (static; at most Nm).

    Returns:
        ``map_index (Nq, k) int32`` (-1 where no valid match) and ``distance (Nq, k) float32``
        (inf where no valid match), nearest first.
    """
    similarity = jnp.matmul(query_descriptors, map_descriptors.T, precision="highest")
    squared = jnp.maximum(2.0 - 2.0 * similarity, 0.0)
    allowed = (
        query_valid[:, None] & map_valid[None, :] & (query_classes[:, None] == map_classes[None, :])
    )
    score = jnp.where(allowed, -squared, -jnp.inf)
    top, index = jax.lax.top_k(score, k)
    found = jnp.isfinite(top)
    distance = jnp.where(found, jnp.sqrt(jnp.where(found, -top, 0.0)), jnp.inf)
    return jnp.where(found, index, -1).astype(jnp.int32), distance


def consistency_graph(
    query_points: Array,
    map_points: Array,
    valid: Array,
    threshold: float | Array,
    query_index: Array | None = None,
    map_index: Array | None = None,
) -> Array:
    """Pairwise-consistency adjacency of associations (query point i <-> map point i).

    Edge ``(a, b)`` when ``| |q_a - q_b| - |m_a - m_b| | <= threshold`` (metres), both valid,
    ``a != b``; with ``query_index`` and ``map_index`` also only when the two associations share
    neither their query vertex nor their map vertex (a clique is then a one-to-one matching).

    Args:
        query_points: (A, 3) query positions of the associations (scan frame).
        map_points: (A, 3) map positions (map frame; centred coordinates are more accurate).
        valid: (A,) bool.
        threshold: consistency tolerance in metres.
        query_index: optional (A,) int32 query vertex of each association.
        map_index: optional (A,) int32 map vertex of each association.

    Returns:
        (A, A) bool symmetric adjacency, False on the diagonal and for invalid associations.
    """

    def distances(points):
        # per coordinate: XLA:CPU fuses (A, A) planes far better than an (A, A, 3) reduction
        squared = sum((points[:, None, c] - points[None, :, c]) ** 2 for c in range(3))
        return jnp.sqrt(squared)

    consistent = jnp.abs(distances(query_points) - distances(map_points)) <= threshold
    n = valid.shape[0]
    adjacency = consistent & valid[:, None] & valid[None, :] & ~jnp.eye(n, dtype=bool)
    if query_index is not None and map_index is not None:
        shared = (query_index[:, None] == query_index[None, :]) | (
            map_index[:, None] == map_index[None, :]
        )
        adjacency = adjacency & ~shared
    return adjacency
