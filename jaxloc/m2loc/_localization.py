"""One scan in, one pose out: the pure :func:`query` of a padded scan, and :func:`localize_scan`,
its host-side entry point (validation, padding, the compilation cache, timings)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.compilation_cache import cached_call, legacy_emitter_options, prepare_call
from jaxloc.m2loc._config import TripletConfig, m2loc_config
from jaxloc.m2loc._map import TripletMap, build_map, check_points_labels, with_config
from jaxloc.m2loc._query import (
    MINIMAL_SET,
    QueryOutput,
    describe_query,
    matches_per_vertex,
    register_query,
)


class LocalizationResult(NamedTuple):
    """Result of one scan's localization: JAX arrays from :func:`query` (a pytree; leading batch
    axes under ``vmap``), host values from :func:`localize_scan` and the batch and drive calls.

    Attributes:
        pose: (4, 4) ``T_map_scan`` (identity when not valid); float64 on the host.
        valid: bool, a clique of at least ``min_inliers``, a converged finite pose that
            verifies, and no rival place (the configuration's tests).
        clique_size: vertices of the final clique.
        inliers: (scan index, map index) pairs of the clique, in association order: (A, 2)
            int32 from :func:`query`, rows past ``clique_size`` -1 (A = scales x padded scan
            size x matches per vertex); (clique_size, 2) int64 on the host.
        scales_used: how many scales the dynamic enhancement used.
        clique_exact: whether the clique solver certified the clique as maximum.
        num_associations: associations in the final graph.
        inlier_fraction: fraction of scan vertices within ``verify_radius`` of a same-class map
            vertex under the estimated pose (the place-not-in-the-map check).
        descriptor_time_ms, match_time_ms: the query descriptor time and the match + clique +
            pose time of a host call (None from :func:`query`, which is not timed).
        ambiguous: the pose was refused because another place explains the scan about as well
            (``TripletConfig.ambiguity_margin``); False when the check is off.
    """

    pose: Array | np.ndarray
    valid: Array | bool
    clique_size: Array | int
    inliers: Array | np.ndarray
    scales_used: Array | int
    clique_exact: Array | bool
    num_associations: Array | int
    inlier_fraction: Array | float
    descriptor_time_ms: float | None = None
    match_time_ms: float | None = None
    ambiguous: Array | bool = False


def query_capacity(n: int, config: TripletConfig) -> int:
    """The padded size (static) a query of ``n`` vertices runs at: ``config.query_capacity``, else
    the next power of two >= 32 (queries of one size band share one compiled program)."""
    if config.query_capacity is not None:
        if n > config.query_capacity:
            raise ValueError(f"scan has {n} vertices, above query_capacity={config.query_capacity}")
        return config.query_capacity
    return max(32, 1 << (n - 1).bit_length())


#: The query programs (:func:`register_query`) whose consistency graph holds at most this many
#: associations (scales x padded scan size x ``top_k``) compile with XLA:CPU's legacy emitters
#: (:func:`jaxloc.compilation_cache.legacy_emitter_options`). Measured (``register_query`` alone,
#: both compiled in one process, 40 seeded queries each on KAIST04 and Town01, calls alternated):
#: one scale of a 32-vertex capacity (800 associations) compiles in 2.7-2.9 s instead of 4.4-4.8 s
#: and runs as fast (medians 8.9 / 8.9 and 9.3 / 9.3 ms), outputs bit-identical; at 1600 (two
#: scales) and 2400 (three) the legacy program runs ~20 % slower (13.4 -> 16.1, 19.9 -> 24.3 ms),
#: mostly in the graph's pairwise-distance fusion, so larger graphs keep XLA's defaults.
LEGACY_EMITTERS_MAX_ASSOCIATIONS = 1024


def _register_options(triplet_map: TripletMap, capacity: int) -> dict:
    """The compile options of the query program of ``triplet_map`` (or its shapes) for scans
    padded to ``capacity`` (:data:`LEGACY_EMITTERS_MAX_ASSOCIATIONS`)."""
    scales = triplet_map.config.descriptor.num_scales
    associations = scales * capacity * matches_per_vertex(triplet_map)
    return legacy_emitter_options() if associations <= LEGACY_EMITTERS_MAX_ASSOCIATIONS else {}


class PaddedScan(NamedTuple):
    """A scan's instance centroids padded to a static capacity (:func:`pad_scan`; a pytree).

    Attributes:
        points: (C, 3) float32 centroids, scan frame, metres (zeros past the real ones).
        classes: (C,) int32 class positions (index into ``config.descriptor.classes``).
        mask: (C,) bool, True for the real instances.
    """

    points: np.ndarray | Array
    classes: np.ndarray | Array
    mask: np.ndarray | Array


def _padded(points, labels, config: TripletConfig, capacity: int | None) -> PaddedScan:
    """Validated (points, labels) padded to ``capacity`` (None: :func:`query_capacity`)."""
    classes = config.descriptor.classes
    n = points.shape[0]
    if capacity is None:
        capacity = query_capacity(max(n, 1), config)
    elif n > capacity:
        raise ValueError(f"scan has {n} instances, above the capacity {capacity}")
    padded_points = np.zeros((capacity, 3), np.float32)
    padded_points[:n] = points
    padded_classes = np.zeros(capacity, np.int32)
    padded_classes[:n] = [classes.index(int(label)) for label in labels]
    return PaddedScan(padded_points, padded_classes, np.arange(capacity) < n)


def pad_scan(
    scan_points: np.ndarray,
    scan_labels: np.ndarray,
    config: TripletConfig | None = None,
    capacity: int | None = None,
) -> PaddedScan:
    """Validate a scan's instances and pad them to a static size, for :func:`query` and the
    jitted steps.

    Args:
        scan_points: (N, 3) instance centroids (scan frame, metres).
        scan_labels: (N,) int class ids (from ``config.descriptor.classes``).
        config: the map's configuration (``triplet_map.config``; None: M2Loc's, whose classes
            are trunk, pole and traffic sign).
        capacity: the padded size (None: :func:`query_capacity` of N, as :func:`localize_scan`);
            stack scans of one capacity to ``vmap`` or ``lax.scan`` over them.

    Returns:
        A :class:`PaddedScan` of numpy arrays.

    Raises:
        ValueError: bad shapes, NaN/inf, unknown labels, duplicate points, more than ``capacity``.
    """
    config = m2loc_config(3) if config is None else config
    classes = config.descriptor.classes
    points, labels = check_points_labels(scan_points, scan_labels, classes, "scan")
    return _padded(points, labels, config, capacity)


def summarize_query(out: QueryOutput) -> LocalizationResult:
    """The :class:`LocalizationResult` (JAX arrays, ``inliers`` padded, no timings) of
    :func:`register_query`'s padded output; pure."""
    clique = out.clique
    clique_size = jnp.sum(clique, dtype=jnp.int32)
    (members,) = jnp.nonzero(clique, size=clique.shape[0], fill_value=0)
    pairs = jnp.stack([out.association_query[members], out.association_map[members]], axis=1)
    kept = jnp.arange(clique.shape[0]) < clique_size
    return LocalizationResult(
        pose=out.T_map_scan,
        valid=out.valid,
        clique_size=clique_size,
        inliers=jnp.where(kept[:, None], pairs, -1).astype(jnp.int32),
        scales_used=out.scales_used,
        clique_exact=out.clique_exact,
        num_associations=jnp.sum(out.association_valid, dtype=jnp.int32),
        inlier_fraction=out.inlier_fraction,
        ambiguous=out.ambiguous,
    )


@eqx.filter_jit
def registered(triplet_map, points, classes, descriptors, descriptor_valid, mask):
    """:func:`register_query` of a padded scan, summarized (:func:`summarize_query`): the
    program that follows the descriptors' in :func:`query` and :func:`localize_scan`."""
    out = register_query(triplet_map, points, classes, descriptors, descriptor_valid, mask)
    enough = jnp.sum(mask) >= MINIMAL_SET
    result = summarize_query(out)
    return result._replace(
        valid=result.valid & enough,
        pose=jnp.where(enough, result.pose, jnp.eye(4, dtype=result.pose.dtype)),
    )


def _from_leaves(leaves) -> LocalizationResult:
    """A :func:`registered` output from its flat array leaves (the compilation cache's calls)."""
    pose, valid, size, inliers, scales, exact, associations, fraction, ambiguous = leaves
    return LocalizationResult(
        pose, valid, size, inliers, scales, exact, associations, fraction, ambiguous=ambiguous
    )


def query(
    triplet_map: TripletMap, scan: PaddedScan, config: TripletConfig | None = None
) -> LocalizationResult:
    """Localize one padded scan in a described map: pure, ``jit``- and ``vmap``-able over scans
    (stacked :class:`PaddedScan`), over configurations that differ only in traced settings
    (stacked with ``jax.tree.map(lambda *x: jnp.stack(x), *configs)``) and over maps of one
    shape.

    Args:
        triplet_map: the described map (:func:`build_map`, :func:`jaxloc.io.load_triplet_map`).
        scan: from :func:`pad_scan` (numpy or JAX arrays).
        config: the query settings (None: the map's own; see :func:`with_config`). Its
            descriptor settings must be the map's.

    Returns:
        A :class:`LocalizationResult` of JAX arrays (``pose`` is ``T_map_scan``; ``inliers``
        padded; no timings). A scan of fewer than 3 real vertices is not valid.

    Raises:
        ValueError: ``config``'s descriptor settings differ from the map's.
    """
    triplet_map = with_config(triplet_map, triplet_map.config if config is None else config)
    points, classes, mask = scan
    descriptors, descriptor_valid = describe_query(
        points, classes, mask, triplet_map.config.descriptor
    )
    return registered(triplet_map, points, classes, descriptors, descriptor_valid, mask)


def prepare_queries(triplet_map: TripletMap, capacities: Sequence[int]) -> None:
    """Trace :func:`localize_scan`'s query programs for scans padded to each of ``capacities``
    (:func:`query_capacity`) and compile them in a background thread, so that the first
    ``localize_scan`` of such a scan finds them ready
    (:func:`jaxloc.compilation_cache.prepare_call`; nothing without the compilation cache).

    Args:
        triplet_map: the map, or its shapes before it is described (``triplet_map_spec``):
            compiling while :func:`build_map` runs is the point.
        capacities: padded scan sizes.
    """
    config = triplet_map.config
    for capacity in capacities:
        padded = (
            jax.ShapeDtypeStruct((capacity, 3), np.float32),
            jax.ShapeDtypeStruct((capacity,), np.int32),
            jax.ShapeDtypeStruct((capacity,), bool),
        )
        described = prepare_call("describe_query", describe_query, *padded, config.descriptor)
        if described is None:  # the cache is off
            return
        # The arguments of localize_scan's calls, so that the keys agree.
        points, classes, mask = padded
        arguments = (triplet_map, points, classes, *described, mask)
        options = _register_options(triplet_map, capacity)
        prepare_call("register_query", registered, *arguments, compiler_options=options)


def invalid_result() -> LocalizationResult:
    """The result of a scan too small to localize (``valid = False``, identity pose)."""
    no_pairs = np.zeros((0, 2), np.int64)
    return LocalizationResult(np.eye(4), False, 0, no_pairs, 0, True, 0, 0.0, 0.0, 0.0)


def host_result(
    result: LocalizationResult, descriptor_time_ms: float, match_time_ms: float
) -> LocalizationResult:
    """A :func:`query` result (one scan's arrays) as host values, ``inliers`` trimmed to the
    clique, with the call's timings."""
    size = int(result.clique_size)
    return LocalizationResult(
        pose=np.asarray(result.pose, np.float64),
        valid=bool(result.valid),
        clique_size=size,
        inliers=np.asarray(result.inliers)[:size].astype(np.int64),
        scales_used=int(result.scales_used),
        clique_exact=bool(result.clique_exact),
        num_associations=int(result.num_associations),
        inlier_fraction=float(result.inlier_fraction),
        descriptor_time_ms=descriptor_time_ms,
        match_time_ms=match_time_ms,
        ambiguous=bool(result.ambiguous),
    )


def localize_scan(
    map_points: np.ndarray | TripletMap,
    map_labels: np.ndarray | None,
    scan_points: np.ndarray,
    scan_labels: np.ndarray,
    config: TripletConfig | None = None,
) -> LocalizationResult:
    """Global localization of a scan's instance centroids in an instance map.

    Args:
        map_points: (N, 3) map instance centroids (map frame, metres), or a prebuilt
            :class:`TripletMap` (then ``map_labels`` must be None).
        map_labels: (N,) int class ids (15 trunk, 17 pole, 18 traffic sign by default).
        scan_points: (Nq, 3) scan instance centroids (scan frame, metres).
        scan_labels: (Nq,) int class ids.
        config: localization configuration (default M2Loc, ``m2loc_config(3)``, as the command
            line; TripletLoc is ``tripletloc_config()``). With a prebuilt map: its query settings
            replace the map's (:func:`with_config`; None keeps the map's); configurations that
            differ only in traced settings share one compiled program.

    Returns:
        A :class:`LocalizationResult` of host values; ``pose`` is the 4x4 ``T_map_scan``. Fewer
        than 3 scan vertices (or an empty scan) give ``valid = False``.

    Raises:
        ValueError: bad shapes, NaN/inf, unknown labels or duplicate points in the map or the
            scan; a ``config`` whose descriptor settings differ from the prebuilt map's.
    """
    if isinstance(map_points, TripletMap):
        if map_labels is not None:
            raise ValueError("pass map_labels=None with a prebuilt TripletMap")
        triplet_map = with_config(map_points, map_points.config if config is None else config)
    else:
        triplet_map = build_map(map_points, map_labels, config)
    config = triplet_map.config
    classes = config.descriptor.classes
    points, labels = check_points_labels(scan_points, scan_labels, classes, "scan")
    if points.shape[0] < MINIMAL_SET:
        return invalid_result()
    start = time.perf_counter()
    padded = tuple(jax.device_put(a) for a in _padded(points, labels, config, None))
    # With the compilation cache on, both programs are traced once per machine (cached_call).
    descriptors, descriptor_valid = jax.block_until_ready(
        cached_call("describe_query", describe_query, tuple, *padded, config.descriptor)
    )
    middle = time.perf_counter()
    result = jax.block_until_ready(
        cached_call(
            "register_query",
            registered,
            _from_leaves,
            triplet_map,
            padded[0],
            padded[1],
            descriptors,
            descriptor_valid,
            padded[2],
            compiler_options=_register_options(triplet_map, padded[0].shape[0]),
        )
    )
    end = time.perf_counter()
    return host_result(result, 1e3 * (middle - start), 1e3 * (end - middle))
