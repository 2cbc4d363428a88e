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

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.m2loc._clique import max_clique_symmetric
from jaxloc.m2loc._descriptors import DescriptorConfig, describe_points
from jaxloc.m2loc._hypotheses import (
    best_hypothesis,
    grid_verified_fraction,
    hypothesis_slots,
    verified_hypotheses,
)
from jaxloc.m2loc._map import TripletMap, verification_grid
from jaxloc.m2loc._matching import consistency_graph, match_descriptors
from jaxloc.m2loc._registration import register

#: Scan vertices that determine a rigid pose (a minimal set), left out of the verification by
#: ``TripletConfig.verify_beyond_minimal_set``.
MINIMAL_SET = 3


@eqx.filter_jit
def describe_query(
    points: Array, classes: Array, mask: Array, config: DescriptorConfig
) -> tuple[Array, Array]:
    """Jitted :func:`describe_points` for padded queries ((Nq, 3), (Nq,), (Nq,))."""
    return describe_points(points, classes, mask, config)


class QueryOutput(eqx.Module):
    """Padded output of :func:`register_query` (A = S * Nq * k associations).

    ``ambiguous``: a pose valid by every other test was refused by the uniqueness check
    (``ambiguity_margin``);
    ``rival_fraction``: the best verification of a hypothesis that puts the scan elsewhere (-1
    when the check is off or no such hypothesis exists)."""

    T_map_scan: Array
    valid: Array
    clique: Array
    association_query: Array
    association_map: Array
    association_valid: Array
    scales_used: Array
    clique_exact: Array
    inlier_fraction: Array
    ambiguous: Array
    rival_fraction: Array


def verified_fraction(
    T_map_scan: Array,
    points: Array,
    classes: Array,
    mask: Array,
    map_points: Array,
    map_classes: Array,
    radius: float | Array,
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
    moved = jnp.matmul(points, T_map_scan[:3, :3].T, precision="highest") + T_map_scan[:3, 3]
    # (Nm, Nq) layout: XLA:CPU reduces the leading axis fastest
    squared = sum((map_points[:, None, c] - moved[None, :, c]) ** 2 for c in range(3))
    squared = jnp.where(map_classes[:, None] == classes[None, :], squared, jnp.inf)
    near = (jnp.min(squared, axis=0) <= radius * radius) & mask
    kept = jnp.maximum(jnp.sum(near) - discount, 0)
    return kept / jnp.maximum(jnp.sum(mask) - discount, 1)


def matches_per_vertex(triplet_map: TripletMap) -> int:
    """k: the map vertices each query vertex is matched to at each scale (static): ``top_k``,
    or every map vertex where the map holds fewer. ``triplet_map`` may be the map's shapes."""
    return min(triplet_map.config.top_k, triplet_map.points.shape[0])


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
    config = triplet_map.config
    num_scales, nq, _ = descriptors.shape
    k = matches_per_vertex(triplet_map)
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

    def enhanced_clique(usable, first_scale):
        """Clique with the dynamic enhancement over the ``usable`` associations from scale
        ``first_scale`` on. Returns (clique, exact, scale)."""

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
        return clique, exact, scale

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

    def final_graph(scale):
        """The consistency graph of the associations up to ``scale`` (the hypotheses' graph)."""
        usable = assoc_valid & (assoc_scale <= scale)
        ends = (assoc_query, assoc_map) if config.one_to_one else (None, None)
        adjacency = consistency_graph(
            query_xyz, map_xyz, usable, config.consistency_threshold, *ends
        )
        return adjacency, usable

    def hypotheses_of(scale):
        """The verified clique hypotheses of the graph up to ``scale`` (through the map's grid)."""
        grid = verification_grid(triplet_map)

        def verify_fast(matrix):
            return grid_verified_fraction(
                matrix, points, classes, mask, grid, config.verify_radius, discount
            )

        return verified_hypotheses(
            *final_graph(scale), query_xyz, map_xyz, verify_fast, config.hypotheses
        )

    def disagrees(matrix):
        moved = jnp.matmul(query_xyz, matrix[:3, :3].T, precision="highest") + matrix[:3, 3]
        return jnp.sum((moved - map_xyz) ** 2, axis=-1) > config.verify_radius**2

    # One loop, one robust solve (the solve is the largest part of this program; a second call site
    # cost about a second of compilation). Iterations 0 .. registration_attempts - 1 are attempts:
    # the clique of the usable associations and its pose; another attempt runs while the best pose
    # so far verifies poorly, without every association that agrees with the poses tried (within
    # verify_radius), so a rejected hypothesis and its near-copies cannot win again, and from the
    # scale the previous attempt ended at (with fewer associations, the cliques of the smaller
    # scales can only be smaller). The best-verified attempt is kept. Then, with ``hypotheses``, one
    # search iteration: the verified clique hypotheses of the best attempt's final graph (kept for
    # the uniqueness check), and where the best pose still verifies poorly, the pose of the
    # best-verified hypothesis.
    searching_on = config.hypotheses > 0
    checking_on = config.ambiguity_margin is not None

    def poor(best):
        return best[5] < config.retry_inlier_fraction

    def attempt_wanted(state):
        count, usable, _, best, _, searched = state
        retry_wanted = (count < config.registration_attempts) & jnp.any(usable)
        return ~searched & ((count == 0) | (retry_wanted & poor(best)))

    def search_wanted(state):
        *_, best, _, searched = state
        return ~searched & (poor(best) | checking_on) if searching_on else jnp.array(False)

    def from_attempt(state):
        _, usable, last_scale, _, checked, _ = state
        clique, exact, scale = enhanced_clique(usable, last_scale)
        return clique, exact, scale, jnp.eye(4, dtype=jnp.float32), jnp.float32(-1.0), checked

    def from_search(state):
        best = state[3]
        cliques, poses, fractions = hypotheses_of(best[2])
        found, closed_form, _ = best_hypothesis(cliques, poses, fractions)
        closed_fraction = verify(closed_form)
        return found, jnp.array(False), best[2], closed_form, closed_fraction, (poses, fractions)

    def no_pose(clique):
        return jnp.array(False), jnp.eye(4, dtype=jnp.float32), jnp.float32(-1.0)

    def solve_step(state):
        count, usable, last_scale, best, checked, searched = state
        attempting = attempt_wanted(state)
        if searching_on:
            clique, exact, scale, closed_form, closed_fraction, checked = jax.lax.cond(
                attempting, from_attempt, from_search, state
            )
            solved, matrix, fraction = jax.lax.cond(
                attempting | poor(best), pose_of, no_pose, clique
            )
        else:
            clique, exact, scale, closed_form, closed_fraction, checked = from_attempt(state)
            solved, matrix, fraction = pose_of(clique)
        # An attempt: kept if it verifies better than the best so far.
        tried = (clique, exact, scale, solved, matrix, fraction)
        better_attempt = attempting & (fraction > best[5])
        # The search: the robust refinement of a small clique (3-6 associations) can fit it at
        # the cost of the rest of the scan (right DCC04 poses: 0.76-0.81 closed-form, 0.52-0.59
        # refined), so it keeps whichever of the two poses explains more of the scan. Picking
        # the best of many poses favours chance fits (in foreign scans of
        # experiments/m2loc_rejection.py: tiny scans verifying 2-3 vertices beyond the minimal
        # set, ~25-vertex scans of a similar world verifying exactly 0.5): a searched pose must
        # verify enough vertices, and a larger fraction than a single pose must.
        if searching_on:
            use_closed = (closed_fraction > fraction) & (jnp.sum(clique) >= MINIMAL_SET)
            fraction = jnp.where(use_closed, closed_fraction, fraction)
            searched_pose = (
                clique,
                exact,
                scale,
                solved | use_closed,
                jnp.where(use_closed, closed_form, matrix),
                fraction,
            )
            enough = (verified_count(fraction) >= config.hypothesis_min_support - 0.5) & (
                fraction >= config.hypothesis_min_fraction
            )
            better_search = ~attempting & poor(best) & enough & (fraction > best[5])
            tried = keep_better(attempting, tried, searched_pose)
            better_attempt = better_attempt | better_search
        best = keep_better(better_attempt, tried, best)
        usable = jnp.where(attempting, usable & ~clique & disagrees(matrix), usable)
        last_scale = jnp.where(attempting, scale, last_scale)
        return count + attempting, usable, last_scale, best, checked, searched | ~attempting

    def more(state):
        return attempt_wanted(state) | search_wanted(state)

    empty = (
        jnp.zeros_like(assoc_valid),
        jnp.array(False),
        jnp.int32(0),
        jnp.array(False),
        jnp.eye(4, dtype=jnp.float32),
        jnp.float32(-1.0),
    )
    slots = hypothesis_slots(total, config.hypotheses)  # the hypotheses' (poses, fractions)
    checked = (jnp.zeros((slots, 4, 4)), jnp.zeros(slots)) if searching_on else ()
    start = (jnp.int32(0), assoc_valid, jnp.int32(0), empty, checked, jnp.array(False))
    *_, best, checked, _ = jax.lax.while_loop(more, solve_step, start)
    clique, exact, scale, solved, matrix, fraction = best
    ambiguous, rival = jnp.array(False), jnp.float32(-1.0)
    if checking_on:
        # Uniqueness: does a pose that puts the scan elsewhere explain it (almost) as well?
        poses, fractions = checked

        def moved(T):
            return jnp.matmul(points, T[:3, :3].T, precision="highest") + T[:3, 3]

        real = mask.astype(jnp.float32)
        here = moved(matrix)
        shift = jax.vmap(
            lambda T: (
                jnp.sum(jnp.linalg.norm(moved(T) - here, axis=-1) * real)
                / jnp.maximum(jnp.sum(real), 1.0)
            )
        )(poses)
        rival = jnp.max(jnp.where(shift > config.ambiguity_distance, fractions, -1.0))
    clique_size = jnp.sum(clique)
    valid = (
        solved
        & (clique_size >= config.min_inliers)
        & (fraction >= config.min_inlier_fraction)
        & (verified_count(fraction) >= config.min_verified - 0.5)  # counts, in float32
    )
    if checking_on:  # ambiguous: a pose valid by every other test, refused for its rival
        ambiguous = valid & (rival >= fraction - config.ambiguity_margin)
        valid = valid & ~ambiguous
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
        ambiguous=ambiguous,
        rival_fraction=rival,
    )
