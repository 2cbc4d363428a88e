"""Multi-scale triplet descriptors (TripletLoc, M2Loc) as padded arrays.

A vertex ``v`` (instance centroid) and each pair ``(a, b)`` of its neighbours whose 3D distance to
``v`` lies in a scale's interval (``[0, L1]`` for the first scale, ``(L_{s-1}, L_s]`` after) form a
triangle. Per semantic label combination ``{label_a, label_b}`` (unordered, 6 for 3 classes) the
descriptor holds a histogram of the angle ``a-v-b`` in the xy plane (36 bins of 5 degrees over
[0, 180]) and a histogram of either the mean xy edge length ``(|va| + |vb|) / 2`` (TripletLoc:
40 bins over the scale's interval, 0.5 m for [0, 20]), the length ratio ``min/max`` (M2Loc, 40
bins over [0, 1]) or both. The vector is L2-normalised; a vertex with fewer than 2 neighbours in a
scale has no descriptor (``valid = False``, zeros). One scale at 20 m with "length" reproduces
TripletLoc's 456-dimensional descriptor.

The kernel describes one vertex from a padded neighbour list; :func:`describe_points` vmaps it
over all vertices and scales of a small point set (a query scan, under jit), :func:`describe_map`
feeds it host-built neighbour lists (scipy KD-tree) in jitted chunks for large maps.
"""

from __future__ import annotations

import itertools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from scipy.spatial import cKDTree

from jaxloc.compilation_cache import cached_call
from jaxloc.m2loc._classes import GRAPH_CLASSES

LengthFeature = Literal["length", "ratio", "both"]


class DescriptorConfig(eqx.Module):
    """Descriptor parameters (all static).

    Attributes:
        classes: class ids of the graph vertices (other labels are rejected at the API boundary).
        scale_edges: increasing interval ends ``(L1, ..., Ln)``, metres; ``(20.0,)`` is TripletLoc.
        angle_bins: angle histogram bins over [0, 180] degrees.
        length_bins: bins of the edge-length (or length-ratio) histogram.
        length_feature: "length" (TripletLoc), "ratio" (M2Loc) or "both".
        soft_bins: split each pair's vote between the two bins whose centres enclose its value
            (linear weights) instead of one bin, so centroid jitter near a bin edge moves a
            fraction of a vote, not all of it (default False: TripletLoc's and M2Loc's hard bins).
    """

    classes: tuple[int, ...] = eqx.field(static=True, default=GRAPH_CLASSES)
    scale_edges: tuple[float, ...] = eqx.field(static=True, default=(20.0,))
    angle_bins: int = eqx.field(static=True, default=36)
    length_bins: int = eqx.field(static=True, default=40)
    length_feature: LengthFeature = eqx.field(static=True, default="length")
    soft_bins: bool = eqx.field(static=True, default=False)

    def __check_init__(self) -> None:
        edges = self.scale_edges
        if len(edges) == 0 or any(e <= 0 for e in edges) or list(edges) != sorted(set(edges)):
            raise ValueError(f"scale_edges must be positive and increasing, got {edges}")
        if len(set(self.classes)) != len(self.classes) or len(self.classes) == 0:
            raise ValueError(f"classes must be distinct and non-empty, got {self.classes}")
        if self.length_feature not in ("length", "ratio", "both"):
            raise ValueError(f"unknown length_feature {self.length_feature!r}")
        if self.angle_bins < 1 or self.length_bins < 1:
            raise ValueError("histogram bin counts must be >= 1")

    @property
    def num_scales(self) -> int:
        return len(self.scale_edges)

    @property
    def num_combinations(self) -> int:
        n = len(self.classes)
        return n * (n + 1) // 2

    @property
    def num_length_histograms(self) -> int:
        return 2 if self.length_feature == "both" else 1

    @property
    def dim(self) -> int:
        """Descriptor length: combinations x (angle bins + length bins per length histogram)."""
        per_combination = self.angle_bins + self.num_length_histograms * self.length_bins
        return self.num_combinations * per_combination

    def scale_bounds(self) -> np.ndarray:
        """(S, 2) float32 ``(low, high]`` interval of each scale (the first includes 0)."""
        edges = (0.0, *self.scale_edges)
        return np.array([(edges[s], edges[s + 1]) for s in range(self.num_scales)], np.float32)

    def combination_table(self) -> np.ndarray:
        """(C, C) int32 combination index of an unordered class-position pair (TripletLoc order:
        equal pairs first, then distinct pairs lexicographically)."""
        n = len(self.classes)
        table = np.zeros((n, n), np.int32)
        for i in range(n):
            table[i, i] = i
        for index, (i, j) in enumerate(itertools.combinations(range(n), 2), start=n):
            table[i, j] = table[j, i] = index
        return table


def class_positions(labels: Array, classes: tuple[int, ...]) -> Array:
    """Position of each label in ``classes`` (int32, -1 for labels not in ``classes``)."""
    match = labels[..., None] == jnp.asarray(classes, labels.dtype)
    return jnp.where(jnp.any(match, axis=-1), jnp.argmax(match, axis=-1), -1).astype(jnp.int32)


def _votes(u: Array, bins: int, soft: bool, start: Array) -> list[tuple[Array, Array | float]]:
    """Histogram votes of values at bin coordinates ``u`` (P,) (the value in bin widths from the
    histogram's low end): ``[(start + bin, 1.0)]`` (hard), or the two bins whose centres enclose
    ``u`` with linear weights (soft; beyond the outer centres all goes to the edge bin)."""
    if not soft:
        return [(start + jnp.clip(jnp.floor(u).astype(jnp.int32), 0, bins - 1), 1.0)]
    centred = u - 0.5
    lower = jnp.floor(centred)
    upper_share = centred - lower
    lower = lower.astype(jnp.int32)
    return [
        (start + jnp.clip(lower, 0, bins - 1), 1.0 - upper_share),
        (start + jnp.clip(lower + 1, 0, bins - 1), upper_share),
    ]


def vertex_descriptor(
    center: Array,
    neighbour_xyz: Array,
    neighbour_class: Array,
    neighbour_mask: Array,
    bounds: Array,
    config: DescriptorConfig,
) -> tuple[Array, Array]:
    """Descriptor of one vertex at one scale from a padded neighbour list.

    Args:
        center: (3,) vertex position (metres).
        neighbour_xyz: (K, 3) candidate neighbour positions (same frame).
        neighbour_class: (K,) int32 class positions (index into ``config.classes``).
        neighbour_mask: (K,) bool, True for real neighbours (the vertex itself excluded).
        bounds: (2,) the scale's ``(low, high]`` 3D distance interval (low = 0 includes 0).
        config: the descriptor configuration.

    Returns:
        ``(descriptor (D,) float32 L2-normalised, valid bool)``; < 2 neighbours gives zeros.
    """
    offsets = neighbour_xyz - center
    distance = jnp.sqrt(jnp.sum(offsets * offsets, axis=-1))
    low, high = bounds[0], bounds[1]
    in_scale = neighbour_mask & (distance <= high) & ((distance > low) | (low <= 0.0))
    # Each unordered pair once: static index arrays of the strict upper triangle.
    first, second = (jnp.asarray(i, jnp.int32) for i in np.triu_indices(neighbour_xyz.shape[0], 1))
    pair_mask = in_scale[first] & in_scale[second]

    xy = offsets[:, :2]
    xy_a, xy_b = xy[first], xy[second]
    cross = xy_a[:, 0] * xy_b[:, 1] - xy_a[:, 1] * xy_b[:, 0]
    dot = xy_a[:, 0] * xy_b[:, 0] + xy_a[:, 1] * xy_b[:, 1]
    angle = jnp.arctan2(jnp.abs(cross), dot)  # [0, pi]
    length = jnp.sqrt(jnp.sum(xy * xy, axis=-1))
    length_a, length_b = length[first], length[second]
    safe_class = jnp.clip(neighbour_class, 0)
    combination = jnp.asarray(config.combination_table())[safe_class[first], safe_class[second]]
    per_combination = config.angle_bins + config.num_length_histograms * config.length_bins
    base = combination * per_combination
    # (index, weight) votes of each pair; the bin coordinate u is the value in bin widths
    votes = _votes(angle * (config.angle_bins / jnp.pi), config.angle_bins, config.soft_bins, base)
    offset = config.angle_bins
    nb = config.length_bins
    if config.length_feature in ("length", "both"):
        mean_length = 0.5 * (length_a + length_b)
        span = jnp.maximum(high - low, 1e-6)
        votes += _votes((mean_length - low) / span * nb, nb, config.soft_bins, base + offset)
        offset += nb
    if config.length_feature in ("ratio", "both"):
        longer = jnp.maximum(length_a, length_b)
        shorter = jnp.minimum(length_a, length_b)
        ratio = jnp.where(longer > 0, shorter / jnp.where(longer > 0, longer, 1.0), 1.0)
        votes += _votes(ratio * nb, nb, config.soft_bins, base + offset)
    weight = pair_mask.astype(jnp.float32)
    histogram = jnp.zeros(config.dim, jnp.float32)
    for index, share in votes:
        histogram = histogram.at[index].add(weight * share)
    norm = jnp.sqrt(jnp.sum(histogram * histogram))
    valid = jnp.sum(in_scale) >= 2
    descriptor = jnp.where(valid, histogram / jnp.where(norm > 0, norm, 1.0), 0.0)
    return descriptor, valid


def describe_points(
    points: Array, classes: Array, mask: Array, config: DescriptorConfig
) -> tuple[Array, Array]:
    """Descriptors of every vertex of a small padded point set (a query), all scales; jit/vmap-able.

    Args:
        points: (N, 3) float vertex positions (any frame; descriptors are rigid-motion invariant
            about z, and invariant to any rotation for the 3D neighbourhoods).
        classes: (N,) int32 class positions (index into ``config.classes``).
        mask: (N,) bool real vertices.
        config: descriptor configuration.

    Returns:
        ``descriptors (S, N, D) float32`` and ``valid (S, N) bool`` (False for padding).
    """
    points, classes, mask = jnp.asarray(points), jnp.asarray(classes), jnp.asarray(mask, bool)
    n = points.shape[0]
    not_self = ~jnp.eye(n, dtype=bool)

    def one_vertex(i, bounds):
        return vertex_descriptor(points[i], points, classes, mask & not_self[i], bounds, config)

    per_scale = jax.vmap(jax.vmap(one_vertex, in_axes=(0, None)), in_axes=(None, 0))
    descriptors, valid = per_scale(jnp.arange(n), jnp.asarray(config.scale_bounds()))
    return descriptors, valid & mask[None, :]


def map_neighbour_lists(points: np.ndarray, low: float, high: float) -> list[np.ndarray]:
    """Host-side neighbour indices of each point (N, 3) within the 3D interval (low, high] (int64
    arrays, the point itself excluded)."""
    tree = cKDTree(points)
    lists = []
    for i, candidates in enumerate(tree.query_ball_point(points, high)):
        candidates = np.asarray(candidates, np.int64)
        candidates = candidates[candidates != i]
        if low > 0 and candidates.size:
            distance = np.linalg.norm(points[candidates] - points[i], axis=1)
            candidates = candidates[distance > low]
        lists.append(candidates)
    return lists


def neighbour_capacity(count: int) -> int:
    """Static neighbour-list capacity for ``count`` neighbours: the smallest of 32, 64, 96, 128,
    192, 256, ... (powers of two, and 1.5x between them from 64 on) that holds it. Few distinct
    shapes (each is traced and compiled on a map's first description: ~0.3 s on 2 cores, more
    beside other compilations) while padding costs at most ~1.8x the pairs of the exact count
    where most pairs are (large lists); short lists (< 16) share the 32 slots, which costs a
    first description less than one more program (a real map: ~10 % more pairs)."""
    capacity = 32
    while capacity < count:
        half_step = capacity + capacity // 2
        capacity = half_step if capacity >= 64 and half_step >= count else 2 * capacity
    return capacity


#: Upper bound on chunk x capacity^2 pair slots per jitted call of :func:`describe_map` (memory).
MAP_PAIR_BUDGET = 1 << 22


@eqx.filter_jit
def _describe_chunk(centers, neighbour_xyz, neighbour_class, neighbour_mask, bounds, config):
    return jax.vmap(vertex_descriptor, in_axes=(0, 0, 0, 0, None, None))(
        centers, neighbour_xyz, neighbour_class, neighbour_mask, bounds, config
    )


def describe_map(
    points: np.ndarray,
    class_positions_: np.ndarray,
    config: DescriptorConfig,
    pair_budget: int = MAP_PAIR_BUDGET,
) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors of all vertices of a (large) map, host-built neighbour lists, jitted chunks.

    Vertices are grouped by the capacity their neighbour list needs (:func:`neighbour_capacity`),
    so the cost follows each vertex's own neighbour count, not the densest vertex's; each group is
    described in chunks of at most ``pair_budget`` pair slots (bounded memory). The result equals
    :func:`describe_points` on the whole map.

    Args:
        points: (N, 3) float map vertices (metres; centred coordinates are more accurate).
        class_positions_: (N,) int class positions (index into ``config.classes``).
        config: descriptor configuration.
        pair_budget: chunk x capacity^2 bound of one jitted call.

    Returns:
        ``descriptors (S, N, D) float32`` and ``valid (S, N) bool`` (numpy).
    """
    points = np.asarray(points, np.float64)
    n = points.shape[0]
    descriptors = np.zeros((config.num_scales, n, config.dim), np.float32)
    valid = np.zeros((config.num_scales, n), bool)
    bounds_all = config.scale_bounds()
    centred = (points - points.mean(axis=0)).astype(np.float32) if n else points.astype(np.float32)
    classes = np.asarray(class_positions_, np.int32)
    for s in range(config.num_scales):
        lists = map_neighbour_lists(points, float(bounds_all[s, 0]), float(bounds_all[s, 1]))
        capacities = np.array([neighbour_capacity(c.size) for c in lists], np.int64)
        for capacity in np.unique(capacities):
            members = np.flatnonzero(capacities == capacity)
            fits = int(pair_budget // capacity**2)
            chunk = min(1 << max(fits.bit_length() - 1, 0), 1024)  # a power of two, >= 1
            for start in range(0, members.size, chunk):
                rows = members[start : start + chunk]
                neighbours = np.zeros((chunk, capacity), np.int64)
                mask = np.zeros((chunk, capacity), bool)
                for slot, row in enumerate(rows):
                    neighbours[slot, : lists[row].size] = lists[row]
                    mask[slot, : lists[row].size] = True
                centers = np.zeros((chunk, 3), np.float32)
                centers[: rows.size] = centred[rows]
                d, v = cached_call(  # traced once per machine when the cache is on
                    "describe_chunk",
                    _describe_chunk,
                    tuple,
                    centers,
                    centred[neighbours],
                    classes[neighbours],
                    mask,
                    bounds_all[s],
                    config,
                )
                descriptors[s, rows] = np.asarray(d)[: rows.size]
                valid[s, rows] = np.asarray(v)[: rows.size]
    return descriptors, valid
