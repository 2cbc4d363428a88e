"""One scan in, one pose out: :func:`localize_scan`, the host-side entry point of M2Loc."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from jaxloc.compilation_cache import cached_call, legacy_emitter_options, prepare_call
from jaxloc.m2loc._config import TripletConfig
from jaxloc.m2loc._map import TripletMap, build_map, check_points_labels
from jaxloc.m2loc._query import QueryOutput, describe_query, matches_per_vertex, register_query


class LocalizationResult(NamedTuple):
    """Result of :func:`localize_scan` (host numpy values).

    Attributes:
        pose: (4, 4) float64 ``T_map_scan`` (identity when not valid).
        valid: clique of at least ``min_inliers`` and a converged, finite pose.
        clique_size: vertices of the final clique.
        inliers: (clique_size, 2) int64 (scan index, map index) pairs of the clique.
        scales_used: how many scales the dynamic enhancement used.
        clique_exact: whether the clique solver certified the clique as maximum.
        num_associations: associations in the final graph.
        inlier_fraction: fraction of scan vertices within ``verify_radius`` of a same-class map
            vertex under the estimated pose (the place-not-in-the-map check).
        descriptor_time_ms: query descriptor time; match_time_ms: match + clique + pose time.
        ambiguous: the pose was refused because another place explains the scan about as well
            (``TripletConfig.ambiguity_margin``); False when the check is off.
    """

    pose: np.ndarray
    valid: bool
    clique_size: int
    inliers: np.ndarray
    scales_used: int
    clique_exact: bool
    num_associations: int
    inlier_fraction: float
    descriptor_time_ms: float
    match_time_ms: float
    ambiguous: bool = False


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
    """A scan's instance centroids padded to a static capacity (:func:`pad_scan`).

    Attributes:
        points: (C, 3) float32 centroids, scan frame, metres (zeros past the real ones).
        classes: (C,) int32 class positions (index into ``config.descriptor.classes``).
        mask: (C,) bool, True for the real instances.
    """

    points: np.ndarray
    classes: np.ndarray
    mask: np.ndarray


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
    config: TripletConfig,
    capacity: int | None = None,
) -> PaddedScan:
    """Validate a scan's instances and pad them to a static size, for the jitted steps.

    Args:
        scan_points: (N, 3) instance centroids (scan frame, metres).
        scan_labels: (N,) int class ids (from ``config.descriptor.classes``).
        config: the map's configuration (``triplet_map.config``).
        capacity: the padded size (None: :func:`query_capacity` of N, as :func:`localize_scan`);
            stack scans of one capacity to ``lax.scan`` over them.

    Returns:
        A :class:`PaddedScan` of numpy arrays.

    Raises:
        ValueError: bad shapes, NaN/inf, unknown labels, duplicate points, more than ``capacity``.
    """
    classes = config.descriptor.classes
    points, labels = check_points_labels(scan_points, scan_labels, classes, "scan")
    return _padded(points, labels, config, capacity)


def prepare_queries(triplet_map: TripletMap, capacities: Sequence[int]) -> None:
    """Trace :func:`localize_scan`'s query programs for scans padded to each of ``capacities``
    (:func:`query_capacity`) and compile them in a background thread, so that the first
    ``localize_scan`` of such a scan finds them ready
    (:func:`jaxloc.compilation_cache.prepare_call`; nothing without the compilation cache).

    Args:
        triplet_map: the map, or its shapes before it is described (:func:`triplet_map_spec`):
            compiling while :func:`build_map` runs is the point.
        capacities: padded scan sizes.
    """
    config = triplet_map.config
    for capacity in capacities:
        query = (
            jax.ShapeDtypeStruct((capacity, 3), np.float32),
            jax.ShapeDtypeStruct((capacity,), np.int32),
            jax.ShapeDtypeStruct((capacity,), bool),
        )
        described = prepare_call("describe_query", describe_query, *query, config.descriptor)
        if described is None:  # the cache is off
            return
        # The arguments of localize_scan's calls, so that the keys agree.
        points, classes, mask = query
        arguments = (triplet_map, points, classes, *described, mask)
        options = _register_options(triplet_map, capacity)
        prepare_call("register_query", register_query, *arguments, compiler_options=options)


def invalid_result() -> LocalizationResult:
    """The result of a scan too small to localize (``valid = False``, identity pose)."""
    no_pairs = np.zeros((0, 2), np.int64)
    return LocalizationResult(np.eye(4), False, 0, no_pairs, 0, True, 0, 0.0, 0.0, 0.0)


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
            :class:`TripletMap` (then ``map_labels`` must be None and ``config`` is the map's).
        map_labels: (N,) int class ids (15 trunk, 17 pole, 18 traffic sign by default).
        scan_points: (Nq, 3) scan instance centroids (scan frame, metres).
        scan_labels: (Nq,) int class ids.
        config: localization configuration (default M2Loc, ``m2loc_config(3)``, as the command
            line; TripletLoc is ``tripletloc_config()``; ignored with a prebuilt map).

    Returns:
        A :class:`LocalizationResult`; ``pose`` is the 4x4 ``T_map_scan``. Fewer than 3 scan
        vertices (or an empty scan) give ``valid = False``.

    Raises:
        ValueError: bad shapes, NaN/inf, unknown labels or duplicate points in the map or the scan.
    """
    if isinstance(map_points, TripletMap):
        if map_labels is not None:
            raise ValueError("pass map_labels=None with a prebuilt TripletMap")
        triplet_map = map_points
    else:
        triplet_map = build_map(map_points, map_labels, config)
    config = triplet_map.config
    classes = config.descriptor.classes
    points, labels = check_points_labels(scan_points, scan_labels, classes, "scan")
    if points.shape[0] < 3:
        return invalid_result()
    start = time.perf_counter()
    query = tuple(jax.device_put(a) for a in _padded(points, labels, config, None))
    # With the compilation cache on, both programs are traced once per machine (cached_call).
    descriptors, descriptor_valid = jax.block_until_ready(
        cached_call("describe_query", describe_query, tuple, *query, config.descriptor)
    )
    middle = time.perf_counter()
    out = jax.block_until_ready(
        cached_call(
            "register_query",
            register_query,
            lambda outputs: QueryOutput(*outputs),
            triplet_map,
            query[0],
            query[1],
            descriptors,
            descriptor_valid,
            query[2],
            compiler_options=_register_options(triplet_map, query[0].shape[0]),
        )
    )
    end = time.perf_counter()
    clique = np.asarray(out.clique)
    inliers = np.stack(
        [np.asarray(out.association_query)[clique], np.asarray(out.association_map)[clique]], 1
    ).astype(np.int64)
    return LocalizationResult(
        pose=np.asarray(out.T_map_scan, np.float64),
        valid=bool(out.valid),
        clique_size=int(clique.sum()),
        inliers=inliers,
        scales_used=int(out.scales_used),
        clique_exact=bool(out.clique_exact),
        num_associations=int(np.asarray(out.association_valid).sum()),
        inlier_fraction=float(out.inlier_fraction),
        descriptor_time_ms=1e3 * (middle - start),
        match_time_ms=1e3 * (end - middle),
        ambiguous=bool(out.ambiguous),
    )
