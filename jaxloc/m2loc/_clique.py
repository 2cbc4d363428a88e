"""Maximum clique of a consistency graph: a jitted solver and an exact host reference.

:func:`max_clique` (pure JAX, static sizes) always returns a clique:

0. the adjacency is packed into bitsets once (its only O(n^2) pass; popcounts give the degrees);
1. a first lower bound ``g`` from greedy expansions seeded at the ``num_seeds`` highest-degree
   vertices, inside the ``prefilter_size`` vertices of highest degree (each step adds the
   candidate of highest degree; candidates = common neighbours of the clique so far);
2. peeling on the whole graph: a clique larger than ``g`` only uses vertices with ``>= g``
   neighbours inside the remaining set, so vertices are removed until that holds (bitset popcounts);
3. while more than ``compact_size`` vertices survive, for each capacity of ``greedy_tiers``: a
   greedy expansion from *every* survivor (the ``tier`` of highest degree among the survivors),
   each step adding the candidate with the most neighbours among the candidates; a larger clique
   raises ``g`` and the peeling runs again. This finds cliques whose members have low degree (on
   real maps: the true associations, while outliers along a repetitive road side are mutually
   consistent and have higher degrees), and it only runs when step 2 left too many survivors;
4. if anything survives, the survivors (the ``compact_size`` of highest degree among them) go to
   an exact Carraghan-Pardalos branch and bound (bitsets, explicit stack in a while loop, pruning
   when ``|R| + min(|candidates|, colours among the candidates) <= best`` with one greedy
   colouring of the compact graph) that searches for a clique larger than ``g`` within
   ``max_nodes`` expansions.

The answer is certified maximum (``exact = True``) when nothing survives the peeling, or the
survivors fit the compact capacity and the search finished within its budget. A truncated run
still returns the largest clique it found.

:func:`max_clique_exact` is a host-side exact solver (Tomita-style branch and bound with greedy
colouring bounds) used to validate the jitted one.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

_WORD = 32


def padded_size(n: int) -> int:
    """Vertices of an ``n``-vertex graph padded to whole 32-bit words (the bitset solvers' size)."""
    return -(-n // _WORD) * _WORD


def _top_k(counts: Array, k: int) -> tuple[Array, Array]:
    """``lax.top_k`` of int32 counts (< 2**24) ranked as float32, which XLA:CPU sorts several
    times faster than int32 (ties keep the lower index first either way)."""
    return jax.lax.top_k(counts.astype(jnp.float32), k)


def _first_index(where: Array) -> Array:
    """Index of the first True of a non-empty (n,) bool (n when none): ``jnp.argmax(where)`` as
    one plain min-reduction. XLA:CPU's legacy fusion emitters
    (:func:`jaxloc.compilation_cache.prefer_fast_compilation`) run argmax's paired value-index
    reduction ~2x slower inside the greedy loops; this form is as fast with both emitters (with
    the default ones the query is a few % faster)."""
    return jnp.min(jnp.where(where, jnp.arange(where.shape[0]), where.shape[0]))


def _first_max(values: Array) -> Array:
    """``jnp.argmax`` of (n,) int32 values: the first index of the largest."""
    return _first_index(values == jnp.max(values))


def _symmetric(adjacency: Array, valid: Array | None) -> tuple[Array, Array]:
    n = adjacency.shape[0]
    valid = jnp.ones(n, bool) if valid is None else jnp.asarray(valid, bool)
    a = jnp.asarray(adjacency, bool)
    a = a & a.T & valid[:, None] & valid[None, :] & ~jnp.eye(n, dtype=bool)
    return a, valid


def _greedy_from_seeds(adjacency: Array, valid: Array, degree: Array, num_seeds: int) -> Array:
    """Best greedy clique (n,) bool from the ``num_seeds`` highest-degree seeds (each step adds
    the candidate of highest degree)."""
    n = adjacency.shape[0]
    rows = jnp.arange(n)
    _, seeds = _top_k(jnp.where(valid, degree, -1), min(num_seeds, n))

    def grow(seed):
        def cond(state):
            return jnp.any(state[1])

        def body(state):
            clique, candidates = state
            v = _first_max(jnp.where(candidates, degree, -1))
            return clique | (rows == v), candidates & adjacency[v]

        start = (rows == seed) & valid[seed], adjacency[seed] & valid[seed]
        clique, _ = jax.lax.while_loop(cond, body, start)
        return clique

    cliques = jax.vmap(grow)(seeds)
    return cliques[jnp.argmax(jnp.sum(cliques, axis=1))]


def _inside_degree(bits: Array, keep: Array) -> Array:
    """(n,) int32 neighbours of each vertex inside ``keep`` (n,) bool, for packed ``bits``."""
    return _popcount(bits & _pack(keep)[None, :])


def _peel(bits: Array, keep: Array, bound: Array) -> Array:
    """Largest subset of ``keep`` (n,) bool where every vertex has >= ``bound`` neighbours in the
    subset, for a packed adjacency ``bits`` (n, n // 32) uint32."""

    def body(state):
        keep, _ = state
        inside = _inside_degree(bits, keep)
        new_keep = keep & (inside >= bound)
        return new_keep, jnp.any(new_keep != keep)

    keep, _ = jax.lax.while_loop(lambda s: s[1], body, (keep, jnp.array(True)))
    return keep


def _greedy_from_every_vertex(bits: Array, members: Array) -> Array:
    """Best greedy clique (P,) bool of a packed (P, P // 32) graph, grown from every member in
    parallel; each step adds the candidate with the most neighbours among the candidates."""
    p = bits.shape[0]
    rows = jnp.arange(p)

    def grow(seed):
        def cond(state):
            return jnp.any(state[1] != 0)

        def body(state):
            clique, candidates = state
            score = jnp.where(_unpack(candidates), _popcount(bits & candidates[None, :]), -1)
            v = _first_max(score)
            return clique | (rows == v), candidates & bits[v]

        start = (rows == seed) & members[seed], jnp.where(members[seed], bits[seed], 0)
        clique, _ = jax.lax.while_loop(cond, body, start)
        return clique

    cliques = jax.vmap(grow)(rows)
    return cliques[jnp.argmax(jnp.sum(cliques, axis=1))]


def greedy_cliques(adjacency: Array, valid: Array) -> tuple[Array, Array]:
    """One greedy clique grown from every valid vertex of a symmetric graph (traceable).

    Each step adds the candidate of highest degree (ties: lowest index); candidates are the
    common neighbours of the clique so far. The vertices are ranked by degree first, so that
    candidate is the lowest set bit of the packed candidate set and a step costs ``n / 32`` words
    per seed, not ``n``.

    Args:
        adjacency: (n, n) bool, symmetric, False on the diagonal and for invalid vertices (e.g.
            from ``consistency_graph``).
        valid: (n,) bool.

    Returns:
        ``(cliques, order)``: cliques (n_pad, n_pad // 32) uint32 packed bitsets in ranked
        order (row r is the clique grown from vertex ``order[r]``; bit c stands for vertex
        ``order[c]``; empty for invalid seeds and padding), order (n_pad,) int32 the ranking (ids
        >= n are padding). Unpack a row with :func:`unpack_ranked`.
    """
    n = adjacency.shape[0]
    n_pad = padded_size(n)
    a = jnp.pad(adjacency, ((0, n_pad - n), (0, n_pad - n)))
    valid = jnp.pad(valid, (0, n_pad - n))
    degree = jnp.where(valid, jnp.sum(a, axis=1, dtype=jnp.int32), -1)
    order = jnp.argsort(-degree, stable=True).astype(jnp.int32)
    bits = _pack(a[order][:, order])
    words = jnp.arange(n_pad // _WORD)

    def with_bit(set_bits, v):
        return set_bits | jnp.where(words == v // _WORD, jnp.uint32(1) << (v % _WORD), 0)

    def grow(seed):
        def body(state):
            clique, candidates = state
            v = _lowest_bit(candidates)
            return with_bit(clique, v), candidates & bits[v]

        empty = jnp.zeros(n_pad // _WORD, jnp.uint32)
        start = jnp.where(valid[order[seed]], with_bit(empty, seed), empty)
        candidates = jnp.where(valid[order[seed]], bits[seed], empty)
        clique, _ = jax.lax.while_loop(lambda s: jnp.any(s[1] != 0), body, (start, candidates))
        return clique

    return jax.vmap(grow)(jnp.arange(n_pad)), order


def unpack_ranked(clique: Array, order: Array, n: int) -> Array:
    """A packed clique of :func:`greedy_cliques` as an (n,) bool mask over the original vertices."""
    return jnp.zeros(order.shape[0], bool).at[order].set(_unpack(clique))[:n]


def _pack(bits: Array) -> Array:
    """Pack (..., P) bool into (..., P // 32) uint32 words (bit b of word w is element 32 w + b)."""
    shaped = bits.reshape(*bits.shape[:-1], -1, _WORD).astype(jnp.uint32)
    return jnp.sum(shaped << jnp.arange(_WORD, dtype=jnp.uint32), axis=-1, dtype=jnp.uint32)


def _unpack(words: Array) -> Array:
    return (
        ((words[..., None] >> jnp.arange(_WORD, dtype=jnp.uint32)) & 1)
        .astype(bool)
        .reshape(*words.shape[:-1], -1)
    )


def _popcount(words: Array) -> Array:
    return jnp.sum(jax.lax.population_count(words).astype(jnp.int32), axis=-1)


def _lowest_bit(words: Array) -> Array:
    """Index of the lowest set bit of a non-empty bitset (W,) uint32."""
    w = _first_index(words != 0)
    word = words[w]
    lowest = word & (~word + jnp.uint32(1))
    return w * _WORD + (_WORD - 1 - jax.lax.clz(lowest).astype(jnp.int32))


def _greedy_colouring(adjacency: Array, members: Array) -> Array:
    """Greedy colouring (P,) int32 of the member vertices in index order (-1 for non-members)."""
    p = adjacency.shape[0]

    def colour_vertex(v, colours):
        used = (
            jnp.zeros(p + 1, bool)
            .at[jnp.where(adjacency[v] & (colours >= 0), colours, p)]
            .set(True)
        )
        first_free = jnp.argmin(used[:p]).astype(jnp.int32)
        return colours.at[v].set(jnp.where(members[v], first_free, -1))

    return jax.lax.fori_loop(0, p, colour_vertex, jnp.full(p, -1, jnp.int32))


def _branch_and_bound(
    adjacency_bits: Array, candidates: Array, colour_bits: Array, best_size: Array, max_nodes: int
):
    """Carraghan-Pardalos search for a clique larger than ``best_size`` in a packed graph.

    The bound of a node is ``|R| + min(|candidates|, colours among the candidates)`` with a greedy
    colouring of the whole compact graph (``colour_bits`` (P, W): the vertices of each colour).

    Returns (best clique bits (W,), best size, finished bool).
    """
    p, w = adjacency_bits.shape
    clique_stack = jnp.zeros((p + 1, w), jnp.uint32)
    candidate_stack = jnp.zeros((p + 1, w), jnp.uint32).at[0].set(candidates)

    def cond(state):
        depth, _, _, _, _, nodes = state
        return (depth >= 0) & (nodes < max_nodes)

    def body(state):
        depth, cliques, cands, best, best_size, nodes = state
        cand = cands[depth]
        count = _popcount(cand)
        leaf = count == 0
        improve = leaf & (depth > best_size)
        best = jnp.where(improve, cliques[depth], best)
        best_size = jnp.where(improve, depth, best_size)
        colours = jnp.sum(jnp.any((colour_bits & cand) != 0, axis=1))
        prune = leaf | (depth + jnp.minimum(count, colours) <= best_size)
        v = _lowest_bit(jnp.where(leaf, jnp.ones_like(cand), cand))
        v_bits = (jnp.arange(p) == v).reshape(w, _WORD)
        v_bits = jnp.sum(
            v_bits.astype(jnp.uint32) << jnp.arange(_WORD, dtype=jnp.uint32), -1, dtype=jnp.uint32
        )
        branch_cands = cands.at[depth].set(cand & ~v_bits)
        branch_cands = branch_cands.at[depth + 1].set(cand & adjacency_bits[v])
        branch_cliques = cliques.at[depth + 1].set(cliques[depth] | v_bits)
        cands = jnp.where(prune, cands, branch_cands)
        cliques = jnp.where(prune, cliques, branch_cliques)
        depth = jnp.where(prune, depth - 1, depth + 1)
        return depth, cliques, cands, best, best_size, nodes + 1

    state = (
        jnp.int32(0),
        clique_stack,
        candidate_stack,
        jnp.zeros(w, jnp.uint32),
        best_size.astype(jnp.int32),
        jnp.int32(0),
    )
    depth, _, _, best, best_size, _ = jax.lax.while_loop(cond, body, state)
    return best, best_size, depth < 0


def _top_subgraph(adjacency: Array, bits: Array, keep: Array, size: int):
    """The ``size`` vertices of ``keep`` with most neighbours inside ``keep``, in ascending order
    of that degree (Carraghan-Pardalos: branching on low-degree vertices first shrinks later
    candidate sets): (indices (size,), member mask (size,), adjacency (size, size) bool)."""
    inside = jnp.where(keep, _inside_degree(bits, keep), -1)
    _, order = _top_k(inside, size)
    order = order[::-1]
    member = keep[order]
    return order, member, adjacency[order][:, order] & member[:, None] & member[None, :]


def max_clique_symmetric(
    adjacency: Array,
    valid: Array,
    *,
    prefilter_size: int = 256,
    greedy_tiers: tuple[int, ...] = (256, 512),
    compact_size: int = 128,
    max_nodes: int = 50000,
    num_seeds: int = 64,
) -> tuple[Array, Array]:
    """:func:`max_clique_with_info` for an adjacency that is already symmetric, masked by
    ``valid`` and False on the diagonal (e.g. from ``consistency_graph``); traceable."""
    n = adjacency.shape[0]
    n_pad = padded_size(n)
    a = jnp.pad(adjacency, ((0, n_pad - n), (0, n_pad - n)))
    valid = jnp.pad(valid, (0, n_pad - n))
    bits = _pack(a)
    degree = jnp.where(valid, _popcount(bits), -1)

    _, kept = _top_k(degree, min(prefilter_size, n_pad))
    kept_valid = degree[kept] >= 0
    sub = a[kept][:, kept] & kept_valid[:, None] & kept_valid[None, :]
    seeded = _greedy_from_seeds(sub, kept_valid, degree[kept], num_seeds)
    best = jnp.zeros(n_pad, bool).at[kept].max(seeded & kept_valid)
    bound = jnp.sum(best).astype(jnp.int32)
    survivors = _peel(bits, valid & (degree >= bound), bound)

    def raise_bound(tier):
        def run(state):
            best, bound, survivors = state
            order, member, tier_graph = _top_subgraph(a, bits, survivors, tier)
            grown = _greedy_from_every_vertex(_pack(tier_graph), member) & member
            size = jnp.sum(grown).astype(jnp.int32)
            best = jnp.where(size > bound, jnp.zeros(n_pad, bool).at[order].max(grown), best)
            bound = jnp.maximum(bound, size)
            return best, bound, _peel(bits, survivors, bound)

        return run

    for tier in sorted({min(t, n_pad) for t in greedy_tiers}):
        best, bound, survivors = jax.lax.cond(
            jnp.sum(survivors) > compact_size,
            raise_bound(tier),
            lambda state: state,
            (best, bound, survivors),
        )

    count = jnp.sum(survivors)
    p = min(compact_size, n_pad)
    order, in_compact, compact = _top_subgraph(a, bits, survivors, p)
    colour = _greedy_colouring(compact, in_compact)
    colour_bits = _pack(colour[None, :] == jnp.arange(p)[:, None])
    best_bits, best_size, finished = _branch_and_bound(
        _pack(compact), _pack(in_compact), colour_bits, bound, max_nodes
    )
    found = _unpack(best_bits)[:p] & in_compact
    mask = jnp.where(best_size > bound, jnp.zeros(n_pad, bool).at[order].max(found), best)
    exact = (count == 0) | ((count <= p) & finished)
    return mask[:n], exact


def check_clique_sizes(compact_size: int, greedy_tiers: tuple[int, ...]) -> None:
    """Raise ValueError unless the bitset capacities are positive multiples of 32."""
    sizes = [("compact_size", compact_size)] + [("greedy_tiers", t) for t in greedy_tiers]
    for name, size in sizes:
        if size <= 0 or size % _WORD:
            raise ValueError(f"{name} must hold positive multiples of {_WORD}, got {size}")


_STATIC = ("prefilter_size", "greedy_tiers", "compact_size", "max_nodes", "num_seeds")


@partial(jax.jit, static_argnames=_STATIC)
def max_clique_with_info(
    adjacency: Array,
    valid: Array | None = None,
    *,
    prefilter_size: int = 256,
    greedy_tiers: tuple[int, ...] = (256, 512),
    compact_size: int = 128,
    max_nodes: int = 50000,
    num_seeds: int = 64,
) -> tuple[Array, Array]:
    """Maximum clique of an undirected graph, with a certificate flag.

    Args:
        adjacency: (n, n) bool, symmetric (the AND with its transpose is used; diagonal ignored).
        valid: (n,) bool vertex mask (padding False) or None for all.
        prefilter_size: static number of highest-degree vertices the first greedy bound searches.
        greedy_tiers: static capacities (multiples of 32) of the greedy passes from every
            survivor, run in turn while more than ``compact_size`` vertices survive the peeling.
        compact_size: static capacity of the exact stage (a multiple of 32).
        max_nodes: static budget of branch-and-bound expansions.
        num_seeds: static number of seeds of the first greedy bound (highest degree first).

    Returns:
        ``(mask (n,) bool, exact bool)``: the clique (always a clique; empty for an empty graph)
        and whether it is certified maximum. The algorithm is in this module's docstring.
    """
    check_clique_sizes(compact_size, greedy_tiers)
    a, valid = _symmetric(adjacency, valid)
    return max_clique_symmetric(
        a,
        valid,
        prefilter_size=prefilter_size,
        greedy_tiers=greedy_tiers,
        compact_size=compact_size,
        max_nodes=max_nodes,
        num_seeds=num_seeds,
    )


def max_clique(adjacency: Array, valid: Array | None = None, **options) -> Array:
    """Maximum clique mask (n,) bool of an (n, n) bool adjacency with an optional (n,) valid mask.

    Jitted; ``options`` are those of :func:`max_clique_with_info` (which documents them and
    returns the certificate flag too).
    """
    return max_clique_with_info(adjacency, valid, **options)[0]


def max_clique_exact(adjacency: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Exact maximum clique (host, numpy): branch and bound with greedy-colouring bounds.

    Args:
        adjacency: (n, n) bool, symmetric.
        valid: optional (n,) bool vertex mask.

    Returns:
        (n,) bool mask of a maximum clique.
    """
    a = np.asarray(adjacency, bool)
    n = a.shape[0]
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    a = a & a.T & valid[:, None] & valid[None, :] & ~np.eye(n, dtype=bool)
    neighbours = [set(np.flatnonzero(a[i]).tolist()) for i in range(n)]
    best: list[int] = []

    def colour_order(candidates: list[int]) -> tuple[list[int], list[int]]:
        colours: list[list[int]] = []
        for v in sorted(candidates, key=lambda u: -len(neighbours[u])):
            for group in colours:
                if not neighbours[v] & set(group):
                    group.append(v)
                    break
            else:
                colours.append([v])
        order, bounds = [], []
        for k, group in enumerate(colours, start=1):
            order += group
            bounds += [k] * len(group)
        return order, bounds

    def expand(clique: list[int], candidates: list[int]) -> None:
        nonlocal best
        order, bounds = colour_order(candidates)
        while order:
            if len(clique) + bounds[-1] <= len(best):
                return
            v = order.pop()
            bounds.pop()
            new_clique = clique + [v]
            new_candidates = [u for u in order if u in neighbours[v]]
            if new_candidates:
                expand(new_clique, new_candidates)
            elif len(new_clique) > len(best):
                best = new_clique

    expand([], [int(i) for i in np.flatnonzero(valid)])
    mask = np.zeros(n, bool)
    mask[best] = True
    return mask
