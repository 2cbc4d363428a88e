"""One-shot global localization of a scan's instance centroids in an instance map (M2Loc).

``build_map`` describes the map once (host neighbour lists, jitted descriptor chunks);
``localize_scan`` validates a scan, describes it (jitted), matches per class and scale, finds the
maximum clique of the consistency graph with the dynamic enhancement of M2Loc (eq. 6: start with
scale-1 matches; while the clique has fewer than ``min_clique`` vertices and scales remain, add the
next scale's matches and solve again), and estimates ``T_map_scan`` (Kabsch, then GNC-TLS with the
optional road-surface-normal roll/pitch prior). Queries of the same capacity reuse one compilation.

Place-not-in-the-map rejection: a scan from elsewhere still yields a (chance) clique and a pose, so
the pose is verified: the fraction of the scan's vertices that land within ``verify_radius`` of a
map vertex of their class must reach ``min_inlier_fraction`` (default 0.5: true queries keep about
80 %, chance poses about 10 %; see ``experiments/results/m2loc/rejection.md``), besides the clique
holding at least ``min_inliers`` vertices. M2Loc's configuration (``m2loc_config``) leaves the 3
vertices that fix the pose out of that fraction (``verify_beyond_minimal_set``): a chance 3-clique
in a small scan otherwise verifies itself.

Small, noisy scans (``m2loc_config(robust=True)``, the default): one-to-one cliques
(``one_to_one``) and, when the maximum clique's pose verifies poorly, verified clique hypotheses
(``hypotheses``: greedy cliques ranked by how much of the scan their pose explains). Optional
registration retries (``registration_attempts``) solve again without the associations that agree
with the poses already rejected. ``experiments/m2loc_losses.py`` shows where scan-sized queries
lose their true correspondences and what each option changes.
"""

from __future__ import annotations

import collections
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.lsq import RobustLoss
from jaxloc.triplet._clique import check_clique_sizes, max_clique_symmetric
from jaxloc.triplet._descriptors import (
    DescriptorConfig,
    describe_map,
    describe_points,
)
from jaxloc.triplet._hypotheses import (
    MapGrid,
    best_verified_clique,
    grid_verified_fraction,
    map_grid,
)
from jaxloc.triplet._io import RoadNormals
from jaxloc.triplet._matching import consistency_graph, match_descriptors
from jaxloc.triplet._registration import register

#: Scan vertices that determine a rigid pose (a minimal set), left out of the verification by
#: ``TripletConfig.verify_beyond_minimal_set``.
MINIMAL_SET = 3

#: Trace counts of the jitted query functions (tests use them to prove there is no retrace).
TRACE_COUNTS: collections.Counter[str] = collections.Counter()


class TripletConfig(eqx.Module):
    """Localization parameters.

    Attributes:
        descriptor: descriptor configuration (classes, scales, histograms).
        top_k: map matches per query vertex, class and scale.
        consistency_threshold: metres, ``| |q_i - q_j| - |m_i - m_j| |`` bound of an edge.
        one_to_one: no edge between associations that share a query or a map vertex, so a
            clique is a one-to-one matching (default False: TripletLoc's graph, where nearby map
            vertices of one query vertex can all join a clique).
        min_clique: M2Loc's T: add scales while the clique is smaller than this.
        min_inliers: fewer clique vertices than this gives ``valid = False``.
        min_inlier_fraction: place-not-in-the-map rejection: after registration, the fraction of
            the scan's vertices that land within ``verify_radius`` of a map vertex of their class
            must reach this (0 disables; see ``experiments/results/m2loc/rejection.md``).
        min_verified: fewer verified scan vertices than this (beyond those counted out by
            ``verify_beyond_minimal_set``) gives ``valid = False``, whatever the fraction: in a
            7-vertex scan 3 chance fits make 75 % (default 0; ``m2loc_config``: 4).
        verify_radius: metres, the verification radius.
        verify_beyond_minimal_set: leave the 3 vertices a pose is determined by out of that
            fraction, ``(verified - 3) / (n - 3)``: they fit the pose by construction, and in a
            small scan they are a large share of it (a chance 3-clique in a 6-vertex scan from
            elsewhere verifies 50 % on its own). Default False (all vertices, as before).
        registration_attempts: cliques and poses tried at most (1: one, TripletLoc's and
            M2Loc's way). While the best pose so far verifies below ``retry_inlier_fraction``,
            another attempt drops the associations that agree with the poses tried (within
            ``verify_radius``) and solves the clique and the pose again; the attempt with the
            highest inlier fraction is kept.
        retry_inlier_fraction: the verification level below which an attempt is retried (and
            below which the hypotheses are searched).
        hypotheses: 0 (default) or the number of clique hypotheses verified when the best pose
            verifies below ``retry_inlier_fraction``: greedy cliques grown from every
            association of the final graph, the largest distinct ones, each with a closed-form
            pose; the best-verified one is refined and kept if it verifies better
            (:func:`jaxloc.triplet.best_verified_clique`).
        hypothesis_min_support: a pose from the hypotheses is kept only if it verifies at least
            this many scan vertices beyond those counted out by ``verify_beyond_minimal_set``
            (the best of many poses fits a small scan by chance far more often than one pose).
        hypothesis_min_fraction: ... and only if it verifies at least this fraction (default
            0.55, above ``min_inlier_fraction``: on development seeds, 6 of the 8 searched poses
            of foreign scans that reached 0.5 stayed below 0.55, against 3 of 70 right poses of
            DCC04 queries; ``experiments/results/m2loc/searched_poses.md``).
        loss: robust loss of the pose refinement (GNC-TLS, 1 m, by default).
        use_rsn: use the road-surface-normal prior when the map has RSN cells.
        rot_delta_deg: added to an RSN cell's normal std (degrees) for the prior's sigma.
        query_capacity: static padded query size (None: next power of two >= 32).
        clique_prefilter_size, clique_greedy_tiers, clique_compact_size, clique_max_nodes,
            clique_seeds: :func:`max_clique` parameters.
        solver_steps: optimiser steps per solve.
    """

    descriptor: DescriptorConfig = DescriptorConfig()
    top_k: int = eqx.field(static=True, default=25)
    consistency_threshold: float = eqx.field(static=True, default=1.0)
    one_to_one: bool = eqx.field(static=True, default=False)
    registration_attempts: int = eqx.field(static=True, default=1)
    retry_inlier_fraction: float = eqx.field(static=True, default=0.5)
    hypotheses: int = eqx.field(static=True, default=0)
    hypothesis_min_support: int = eqx.field(static=True, default=6)
    hypothesis_min_fraction: float = eqx.field(static=True, default=0.55)
    min_clique: int = eqx.field(static=True, default=10)
    min_inliers: int = eqx.field(static=True, default=3)
    min_inlier_fraction: float = eqx.field(static=True, default=0.5)
    min_verified: int = eqx.field(static=True, default=0)
    verify_radius: float = eqx.field(static=True, default=1.5)
    verify_beyond_minimal_set: bool = eqx.field(static=True, default=False)
    loss: RobustLoss = RobustLoss("gnc_tls", 1.0)
    use_rsn: bool = eqx.field(static=True, default=True)
    rot_delta_deg: float = eqx.field(static=True, default=1.0)
    query_capacity: int | None = eqx.field(static=True, default=None)
    clique_prefilter_size: int = eqx.field(static=True, default=256)
    clique_greedy_tiers: tuple[int, ...] = eqx.field(static=True, default=(256, 512))
    clique_compact_size: int = eqx.field(static=True, default=128)
    clique_max_nodes: int = eqx.field(static=True, default=4000)
    clique_seeds: int = eqx.field(static=True, default=64)
    solver_steps: int = eqx.field(static=True, default=30)

    def __check_init__(self) -> None:
        if self.top_k < 1 or self.min_inliers < 3 or self.min_clique < 1:
            raise ValueError("top_k >= 1, min_inliers >= 3 and min_clique >= 1 are required")
        if not self.consistency_threshold > 0:
            raise ValueError("consistency_threshold must be > 0")
        if self.registration_attempts < 1 or not 0.0 <= self.retry_inlier_fraction <= 1.0:
            raise ValueError("registration_attempts >= 1 and retry_inlier_fraction in [0, 1]")
        if min(self.hypotheses, self.hypothesis_min_support, self.min_verified) < 0:
            raise ValueError("hypotheses, hypothesis_min_support and min_verified must be >= 0")
        if not 0.0 <= self.min_inlier_fraction <= 1.0 or not self.verify_radius > 0:
            raise ValueError("min_inlier_fraction must be in [0, 1] and verify_radius > 0")
        if not 0.0 <= self.hypothesis_min_fraction <= 1.0:
            raise ValueError("hypothesis_min_fraction must be in [0, 1]")
        check_clique_sizes(self.clique_compact_size, self.clique_greedy_tiers)


def tripletloc_config(**overrides) -> TripletConfig:
    """TripletLoc: one scale [0, 20] m, angle + edge-length histograms (456 dims)."""
    return TripletConfig(**overrides)


def m2loc_config(
    num_scales: int = 3,
    scale_edges: tuple[float, ...] = (20.0, 30.0, 40.0),
    length_feature: str = "ratio",
    robust: bool = True,
    **overrides,
) -> TripletConfig:
    """M2Loc "Multi-n-En": the first ``num_scales`` intervals of ``scale_edges``, angle +
    length-ratio histograms, dynamic clique enhancement with T = 10, and the place-not-in-the-map
    check on the evidence beyond the pose's minimal set (``verify_beyond_minimal_set=True``).

    ``robust`` (default True) adds what helps small, noisy scans most in our measurements
    (``experiments/results/m2loc/losses*.md``, ``hypotheses.md``, ``table1.md``): one-to-one
    cliques and, when the maximum clique's pose verifies poorly, 256 verified clique hypotheses
    (``one_to_one=True, hypotheses=256``); ``robust=False`` is the paper's M2Loc. ``overrides``
    win over both (``registration_attempts=3, hypotheses=0`` is session 7's robust setting)."""
    descriptor = DescriptorConfig(
        scale_edges=tuple(scale_edges[:num_scales]), length_feature=length_feature
    )
    defaults = {"verify_beyond_minimal_set": True, "min_verified": 4}
    if robust:
        defaults.update(one_to_one=True, hypotheses=256)
    return TripletConfig(descriptor=descriptor, **{**defaults, **overrides})


def _per_scale(descriptors) -> tuple[Array, ...]:
    """(S, Nm, D) stacked descriptors, or S arrays (Nm, D), as a tuple of S arrays."""
    if isinstance(descriptors, (tuple, list)):
        return tuple(descriptors)
    return tuple(descriptors[s] for s in range(descriptors.shape[0]))


class TripletMap(eqx.Module):
    """A described instance map (a pytree; build with :func:`build_map`).

    Attributes:
        points: (Nm, 3) float32 vertices, map frame minus ``origin`` (metres).
        classes: (Nm,) int32 class positions (index into ``config.descriptor.classes``).
        descriptors: S arrays (Nm, D) float32, one per scale (a stacked (S, Nm, D) array is split
            on construction: each scale's matching then reads its own buffer, where slicing a
            stacked array under jit copies it, 3x the matching time on DCC04); valid: (S, Nm)
            bool.
        origin: (3,) float32, subtracted from map coordinates (precision).
        rsn_xy: (M, 2) float32 RSN cell centres minus origin; rsn_normals: (M, 3) unit normals;
            rsn_sigma: (M,) float32 prior sigma (radians). M = 1 dummy cell when absent.
        has_rsn: static bool.
        config: the configuration the descriptors were built with.
        grid: the vertices sorted into XY cells of side ``config.verify_radius`` for the
            hypotheses' verification (:func:`map_grid`; :func:`build_map` and
            :func:`load_triplet_map` build it; None: built inside each query, ~2 ms on DCC04).
            Rebuild it if you replace ``points`` or ``classes``.
    """

    points: Array
    classes: Array
    descriptors: tuple[Array, ...] = eqx.field(converter=_per_scale)
    valid: Array
    origin: Array
    rsn_xy: Array
    rsn_normals: Array
    rsn_sigma: Array
    has_rsn: bool = eqx.field(static=True)
    config: TripletConfig
    grid: MapGrid | None = None


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


def _check_points_labels(points, labels, classes: tuple[int, ...], what: str):
    points = np.asarray(points)
    labels = np.asarray(labels)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"{what} points must have shape (N, 3), got {points.shape}")
    if labels.shape != (points.shape[0],):
        raise ValueError(f"{what} labels must have shape ({points.shape[0]},), got {labels.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{what} labels must be integer class ids, got dtype {labels.dtype}")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{what} points contain NaN or inf")
    unknown = np.setdiff1d(np.unique(labels), np.asarray(classes))
    if unknown.size:
        raise ValueError(f"{what} labels {unknown.tolist()} are not in the classes {classes}")
    if points.shape[0] > 1:
        unique = np.unique(points, axis=0)
        if unique.shape[0] != points.shape[0]:
            raise ValueError(
                f"{what} has {points.shape[0] - unique.shape[0]} duplicate point(s); fuse "
                "coincident instances first (jaxloc.triplet.fuse_instances)"
            )
    return points.astype(np.float64), labels.astype(np.int64)


def build_map(
    map_points: np.ndarray,
    map_labels: np.ndarray,
    config: TripletConfig | None = None,
    road_normals: RoadNormals | None = None,
) -> TripletMap:
    """Describe an instance map once, for reuse by every query.

    Args:
        map_points: (N, 3) instance centroids, map frame, metres.
        map_labels: (N,) int class ids (e.g. 15 trunk, 17 pole, 18 traffic sign).
        config: localization configuration (default M2Loc, ``m2loc_config(3)``; TripletLoc is
            ``tripletloc_config()``).
        road_normals: optional RSN cells for the roll/pitch prior.

    Raises:
        ValueError: bad shapes, NaN/inf, unknown labels, duplicates, or fewer than 3 vertices.
    """
    config = m2loc_config(3) if config is None else config
    classes = config.descriptor.classes
    points, labels = _check_points_labels(map_points, map_labels, classes, "map")
    if points.shape[0] < 3:
        raise ValueError(f"a map needs at least 3 vertices, got {points.shape[0]}")
    if config.top_k > points.shape[0]:
        raise ValueError(f"top_k={config.top_k} exceeds the {points.shape[0]} map vertices")
    positions = np.searchsorted(np.sort(classes), labels)
    positions = np.argsort(classes)[positions]
    origin = points.mean(axis=0)
    descriptors, valid = describe_map(points - origin, positions, config.descriptor)
    if road_normals is not None and len(road_normals.xy):
        rsn_xy = road_normals.xy - origin[:2]
        normals = road_normals.normals
        sigma = np.deg2rad(road_normals.std_deg + config.rot_delta_deg)
        has_rsn = True
    else:
        rsn_xy, normals, sigma, has_rsn = (
            np.zeros((1, 2)),
            np.array([[0.0, 0, 1]]),
            np.ones(1),
            False,
        )
    centred = jnp.asarray(points - origin, jnp.float32)
    positions = jnp.asarray(positions, jnp.int32)
    return TripletMap(
        points=centred,
        classes=positions,
        descriptors=tuple(jnp.asarray(d) for d in descriptors),
        valid=jnp.asarray(valid),
        origin=jnp.asarray(origin, jnp.float32),
        rsn_xy=jnp.asarray(rsn_xy, jnp.float32),
        rsn_normals=jnp.asarray(normals, jnp.float32),
        rsn_sigma=jnp.asarray(np.maximum(sigma, 1e-4), jnp.float32),
        has_rsn=has_rsn,
        config=config,
        grid=map_grid(centred, positions, config.verify_radius),
    )


@eqx.filter_jit
def describe_query(
    points: Array, classes: Array, mask: Array, config: DescriptorConfig
) -> tuple[Array, Array]:
    """Jitted :func:`describe_points` for padded queries ((Nq, 3), (Nq,), (Nq,))."""
    TRACE_COUNTS["describe_query"] += 1
    return describe_points(points, classes, mask, config)


class QueryOutput(eqx.Module):
    """Padded output of :func:`register_query` (A = S * Nq * k associations)."""

    T_map_scan: Array
    valid: Array
    clique: Array
    association_query: Array
    association_map: Array
    association_valid: Array
    scales_used: Array
    clique_exact: Array
    inlier_fraction: Array


def verified_fraction(
    T_map_scan: Array,
    points: Array,
    classes: Array,
    mask: Array,
    map_points: Array,
    map_classes: Array,
    radius: float,
    discount: int = 0,
) -> Array:
    """Fraction of real scan vertices within ``radius`` of a same-class map vertex after ``T``.

    Args:
        T_map_scan: (4, 4) pose in the frame of ``map_points``.
        points: (Nq, 3) scan vertices; classes: (Nq,) int32; mask: (Nq,) bool real vertices.
        map_points: (Nm, 3); map_classes: (Nm,) int32.
        radius: metres.
        discount: vertices taken off both counts (the minimal set that fixed the pose).

    Returns:
        float32 scalar in [0, 1]: ``(verified - discount) / (real - discount)``, clipped at 0
        (0 for no more than ``discount`` real vertices).
    """
    moved = points @ T_map_scan[:3, :3].T + T_map_scan[:3, 3]
    # (Nm, Nq) layout: XLA:CPU reduces the leading axis fastest
    squared = sum((map_points[:, None, c] - moved[None, :, c]) ** 2 for c in range(3))
    squared = jnp.where(map_classes[:, None] == classes[None, :], squared, jnp.inf)
    near = (jnp.min(squared, axis=0) <= radius * radius) & mask
    kept = jnp.maximum(jnp.sum(near) - discount, 0)
    return kept / jnp.maximum(jnp.sum(mask) - discount, 1)


@eqx.filter_jit
def register_query(
    triplet_map: TripletMap,
    points: Array,
    classes: Array,
    descriptors: Array,
    descriptor_valid: Array,
    mask: Array | None = None,
) -> QueryOutput:
    """Match, build the consistency graph, clique with dynamic enhancement, pose; pure and jitted.

    Args:
        triplet_map: the described map.
        points: (Nq, 3) float32 query vertices (scan frame); classes: (Nq,) int32 class positions.
        descriptors: (S, Nq, D) and descriptor_valid (S, Nq) from :func:`describe_query`.
        mask: (Nq,) bool real vertices (None: vertices with a descriptor at some scale).

    Returns:
        A :class:`QueryOutput` with ``T_map_scan`` (4, 4) in the map frame (origin added back).
    """
    TRACE_COUNTS["register_query"] += 1
    config = triplet_map.config
    num_scales, nq, _ = descriptors.shape
    k = config.top_k
    # A Python loop over the (at most a few) scales, not vmap: XLA:CPU runs the batched
    # (1, Nq, D) x (1, Nm, D) similarity ~2.7x slower than the plain matrix product
    # (benchmarks/triplet.py --stages; 14.2 vs 5.2 ms on Town01).
    map_index = jnp.stack(
        [
            match_descriptors(
                descriptors[s],
                descriptor_valid[s],
                classes,
                triplet_map.descriptors[s],
                triplet_map.valid[s],
                triplet_map.classes,
                k,
            )[0]
            for s in range(num_scales)
        ]
    )  # (S, Nq, k)
    duplicate = jnp.zeros(map_index.shape, bool)
    for s in range(1, num_scales):  # an association repeated from an earlier scale is dropped
        same = map_index[s, :, :, None, None] == map_index[:s].transpose(1, 0, 2)[:, None]
        duplicate = duplicate.at[s].set(jnp.any(same, axis=(2, 3)))
    assoc_valid = ((map_index >= 0) & ~duplicate).reshape(-1)
    assoc_query = jnp.broadcast_to(jnp.arange(nq)[None, :, None], map_index.shape).reshape(-1)
    assoc_map = map_index.reshape(-1)
    assoc_scale = jnp.broadcast_to(jnp.arange(num_scales)[:, None, None], map_index.shape).reshape(
        -1
    )
    query_xyz = points[assoc_query]
    map_xyz = triplet_map.points[jnp.maximum(assoc_map, 0)]
    per_scale = nq * k
    total = num_scales * per_scale

    def clique_of_prefix(size):
        # Associations are scale-major: scales <= s are the first (s + 1) * Nq * k of them, so
        # each stage builds only its own graph (a static prefix), and lax.switch runs only it.
        def run(usable):
            ends = (assoc_query[:size], assoc_map[:size]) if config.one_to_one else (None, None)
            adjacency = consistency_graph(
                query_xyz[:size],
                map_xyz[:size],
                usable[:size],
                config.consistency_threshold,
                *ends,
            )
            clique, exact = max_clique_symmetric(
                adjacency,
                usable[:size],
                prefilter_size=config.clique_prefilter_size,
                greedy_tiers=config.clique_greedy_tiers,
                compact_size=config.clique_compact_size,
                max_nodes=config.clique_max_nodes,
                num_seeds=config.clique_seeds,
            )
            return jnp.zeros(total, bool).at[:size].set(clique), exact

        return run

    stages = [clique_of_prefix((s + 1) * per_scale) for s in range(num_scales)]
    mask = jnp.any(descriptor_valid, axis=0) if mask is None else mask

    def attempt(usable, first_scale=0):
        """Clique with the dynamic enhancement over the ``usable`` associations from scale
        ``first_scale`` on, then the pose and its verification. Returns (clique, exact, scale, ok,
        T (4, 4) centred, fraction)."""

        def keep_going(state):
            scale, clique, _ = state
            return (scale < first_scale) | (
                (jnp.sum(clique) < config.min_clique) & (scale < num_scales - 1)
            )

        def next_scale(state):
            scale = state[0] + 1
            clique, exact = jax.lax.switch(scale, stages, usable)
            return scale, clique, exact

        start = (jnp.int32(first_scale) - 1, jnp.zeros_like(usable), jnp.array(False))
        scale, clique, exact = jax.lax.while_loop(keep_going, next_scale, start)
        return clique, exact, scale, *pose_of(clique)

    discount = MINIMAL_SET if config.verify_beyond_minimal_set else 0

    def verified_count(fraction):
        """Scan vertices a verified fraction stands for (beyond the discount), float32."""
        return fraction * jnp.maximum(jnp.sum(mask) - discount, 1)

    def keep_better(better, new, old):
        return jax.tree.map(lambda n, o: jnp.where(better, n, o), new, old)

    def verify(matrix):
        return verified_fraction(
            matrix,
            points,
            classes,
            mask,
            triplet_map.points,
            triplet_map.classes,
            config.verify_radius,
            discount=discount,
        )

    def pose_of(clique):
        """Robust pose of a clique (A,) bool and its verification: (ok, T (4, 4) centred,
        fraction)."""
        normal, sigma = None, None
        if triplet_map.has_rsn and config.use_rsn:
            weight = clique.astype(jnp.float32)
            centre = jnp.sum(map_xyz[:, :2] * weight[:, None], 0) / jnp.maximum(
                jnp.sum(weight), 1.0
            )
            cell = jnp.argmin(jnp.sum((triplet_map.rsn_xy - centre) ** 2, axis=1))
            normal, sigma = triplet_map.rsn_normals[cell], triplet_map.rsn_sigma[cell]
        # The pose only needs the clique: compact it to a static 2 * Nq pairs (a clique rarely
        # holds more than one association per query vertex) so the solver sees small residuals.
        _, chosen = jax.lax.top_k(clique.astype(jnp.float32), min(2 * nq, total))  # f32: fast
        solution, _ = register(
            query_xyz[chosen],
            map_xyz[chosen],
            clique[chosen],
            loss=config.loss,
            normal=normal,
            normal_sigma=sigma,
            max_steps=config.solver_steps,
        )
        matrix = solution.pose.as_matrix()
        return solution.ok, matrix, verify(matrix)

    if config.registration_attempts == 1:
        clique, exact, scale, solved, matrix, fraction = attempt(assoc_valid)
    else:
        # Retry while the best pose so far verifies poorly; each retry drops every association
        # that agrees with the poses tried (within verify_radius), so a rejected hypothesis and
        # its near-copies cannot win again. The best-verified attempt is kept. A retry starts at
        # the scale the previous attempt ended at: with fewer associations, the cliques of the
        # smaller scales can only be smaller, so the enhancement would pass them again.
        def disagrees(matrix):
            moved = query_xyz @ matrix[:3, :3].T + matrix[:3, 3]
            return jnp.sum((moved - map_xyz) ** 2, axis=-1) > config.verify_radius**2

        def retry(state):
            count, usable, last_scale, best = state
            result = attempt(usable, last_scale)
            best = keep_better(result[5] > best[5], result, best)
            usable = usable & ~result[0] & disagrees(result[4])
            return count + 1, usable, result[2], best

        def again(state):
            count, usable, _, best = state
            retry_wanted = (count < config.registration_attempts) & jnp.any(usable)
            return (count == 0) | (retry_wanted & (best[5] < config.retry_inlier_fraction))

        empty = (
            jnp.zeros_like(assoc_valid),
            jnp.array(False),
            jnp.int32(0),
            jnp.array(False),
            jnp.eye(4, dtype=jnp.float32),
            jnp.float32(-1.0),
        )
        start = (jnp.int32(0), assoc_valid, jnp.int32(0), empty)
        *_, best = jax.lax.while_loop(again, retry, start)
        clique, exact, scale, solved, matrix, fraction = best
    if config.hypotheses:
        # The best pose still verifies poorly: rank the greedy cliques of its final graph by the
        # verification of their closed-form poses and refine the best one.
        def search(best):
            usable = assoc_valid & (assoc_scale <= best[2])
            ends = (assoc_query, assoc_map) if config.one_to_one else (None, None)
            adjacency = consistency_graph(
                query_xyz, map_xyz, usable, config.consistency_threshold, *ends
            )
            grid = triplet_map.grid
            if grid is None or grid.cell < config.verify_radius:
                grid = map_grid(triplet_map.points, triplet_map.classes, config.verify_radius)

            def verify_fast(matrix):
                return grid_verified_fraction(
                    matrix, points, classes, mask, grid, config.verify_radius, discount
                )

            found, closed_form, _ = best_verified_clique(
                adjacency, usable, query_xyz, map_xyz, verify_fast, config.hypotheses
            )
            solved, refined, fraction = pose_of(found)
            # The robust refinement of a small clique (3-6 associations) can fit it at the cost
            # of the rest of the scan (right DCC04 poses: 0.76-0.81 closed-form, 0.52-0.59
            # refined); keep whichever of the two poses explains more of the scan.
            closed_fraction = verify(closed_form)
            use_closed = (closed_fraction > fraction) & (jnp.sum(found) >= MINIMAL_SET)
            result = (
                found,
                jnp.array(False),
                best[2],
                solved | use_closed,
                jnp.where(use_closed, closed_form, refined),
                jnp.where(use_closed, closed_fraction, fraction),
            )
            # Picking the best of many poses favours chance fits (in foreign scans of
            # experiments/m2loc_rejection.py: tiny scans verifying 2-3 vertices beyond the minimal
            # set, ~25-vertex scans of a similar world verifying exactly 0.5): a searched pose
            # must verify enough vertices, and a larger fraction than a single pose must.
            enough = (verified_count(result[5]) >= config.hypothesis_min_support - 0.5) & (
                result[5] >= config.hypothesis_min_fraction
            )
            return keep_better(enough & (result[5] > best[5]), result, best)

        best = (clique, exact, scale, solved, matrix, fraction)
        poor = fraction < config.retry_inlier_fraction
        clique, exact, scale, solved, matrix, fraction = jax.lax.cond(
            poor, search, lambda best: best, best
        )
    clique_size = jnp.sum(clique)
    valid = (
        solved
        & (clique_size >= config.min_inliers)
        & (fraction >= config.min_inlier_fraction)
        & (verified_count(fraction) >= config.min_verified - 0.5)  # counts, in float32
    )
    matrix = matrix.at[:3, 3].add(triplet_map.origin)
    matrix = jnp.where(valid, matrix, jnp.eye(4, dtype=matrix.dtype))
    return QueryOutput(
        T_map_scan=matrix,
        valid=valid,
        clique=clique,
        association_query=assoc_query,
        association_map=assoc_map,
        association_valid=assoc_valid & (assoc_scale <= scale),
        scales_used=scale + 1,
        clique_exact=exact,
        inlier_fraction=fraction,
    )


def _capacity(n: int, config: TripletConfig) -> int:
    if config.query_capacity is not None:
        if n > config.query_capacity:
            raise ValueError(f"scan has {n} vertices, above query_capacity={config.query_capacity}")
        return config.query_capacity
    return max(32, 1 << (n - 1).bit_length())


def _invalid_result() -> LocalizationResult:
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
    points, labels = _check_points_labels(scan_points, scan_labels, classes, "scan")
    n = points.shape[0]
    if n < 3:
        return _invalid_result()
    capacity = _capacity(n, config)
    positions = np.array([classes.index(int(label)) for label in labels], np.int32)
    padded_points = np.zeros((capacity, 3), np.float32)
    padded_points[:n] = points
    padded_classes = np.zeros(capacity, np.int32)
    padded_classes[:n] = positions
    mask = np.arange(capacity) < n

    start = time.perf_counter()
    descriptors, descriptor_valid = jax.block_until_ready(
        describe_query(
            jnp.asarray(padded_points),
            jnp.asarray(padded_classes),
            jnp.asarray(mask),
            config.descriptor,
        )
    )
    middle = time.perf_counter()
    out = jax.block_until_ready(
        register_query(
            triplet_map,
            jnp.asarray(padded_points),
            jnp.asarray(padded_classes),
            descriptors,
            descriptor_valid,
            jnp.asarray(mask),
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
    )
