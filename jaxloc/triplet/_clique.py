"""Maximum clique of a consistency graph: a jitted solver and an exact host reference.

:func:`max_clique` (pure JAX, static sizes) always returns a clique:

0. prefilter: degrees of the whole graph (its only O(n^2) pass), then the ``prefilter_size``
   vertices of highest degree form the working subgraph (a clique larger than a bound ``g`` only
   uses vertices of degree ``>= g``, so nothing is lost while at most that many qualify);
1. a lower bound from greedy expansions seeded at the highest-degree vertices in parallel (each
   step adds the candidate of highest degree, candidates = common neighbours of the clique so far);
2. peeling: a clique larger than the bound ``g`` only uses vertices with ``>= g`` neighbours inside
   the remaining set, so vertices are removed until that holds (a while loop of mat-vecs);
3. if anything survives, the survivors (the ``compact_size`` of highest degree) are packed into
   bitsets and an exact Carraghan-Pardalos branch and bound (explicit stack in a while loop,
   pruning when ``|R| + min(|candidates|, colours among the candidates) <= best`` with one greedy
   colouring of the compact graph) searches for a clique larger than ``g``, within ``max_nodes``
   expansions.

The answer is certified maximum (``exact = True``) when the prefilter kept every vertex of degree
``>= g`` and either nothing survives the peeling, or the survivors fit the compact capacity and
the search finished within its budget. A truncated run still returns the largest clique it found.

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
    _, seeds = jax.lax.top_k(jnp.where(valid, degree, -1), min(num_seeds, n))

    def grow(seed):
        def cond(state):
            return jnp.any(state[1])

        def body(state):
            clique, candidates = state
            v = jnp.argmax(jnp.where(candidates, degree, -1))
            return clique | (rows == v), candidates & adjacency[v]

        start = (rows == seed) & valid[seed], adjacency[seed] & valid[seed]
        clique, _ = jax.lax.while_loop(cond, body, start)
        return clique

    cliques = jax.vmap(grow)(seeds)
    return cliques[jnp.argmax(jnp.sum(cliques, axis=1))]


def _peel(adjacency: Array, keep: Array, bound: Array) -> Array:
    """Largest subset of ``keep`` where every vertex has >= ``bound`` neighbours in the subset."""
    a = adjacency.astype(jnp.float32)

    def body(state):
        keep, _ = state
        inside = a @ keep.astype(jnp.float32)
        new_keep = keep & (inside >= bound)
        return new_keep, jnp.any(new_keep != keep)

    keep, _ = jax.lax.while_loop(lambda s: s[1], body, (keep, jnp.array(True)))
    return keep


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
    w = jnp.argmax(words != 0)
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


def _degree(adjacency: Array) -> Array:
    """(n,) int32 degrees of a symmetric bool adjacency.

    Summed over axis 0 (equal to axis 1 for a symmetric matrix): XLA:CPU reduces the leading axis
    of a large matrix several times faster than the trailing one.
    """
    return jnp.sum(adjacency, axis=0, dtype=jnp.int32)


def max_clique_symmetric(
    adjacency: Array,
    valid: Array,
    *,
    prefilter_size: int = 256,
    compact_size: int = 128,
    max_nodes: int = 50000,
    num_seeds: int = 64,
) -> tuple[Array, Array]:
    """:func:`max_clique_with_info` for an adjacency that is already symmetric, masked by
    ``valid`` and False on the diagonal (e.g. from :func:`consistency_graph`); traceable.

    The (n, n) graph is touched once (degrees); everything else runs on the ``prefilter_size``
    vertices of highest degree: any clique larger than the greedy bound ``g`` only uses vertices
    of degree ``>= g``, so the answer stays certified when at most ``prefilter_size`` of them exist.
    """
    n = adjacency.shape[0]
    degree = jnp.where(valid, _degree(adjacency), -1)
    q = min(prefilter_size, n)
    _, kept = jax.lax.top_k(degree, q)
    kept_valid = degree[kept] >= 0
    sub = adjacency[kept][:, kept] & kept_valid[:, None] & kept_valid[None, :]
    sub_degree = degree[kept]
    greedy = _greedy_from_seeds(sub, kept_valid, sub_degree, num_seeds)
    greedy_size = jnp.sum(greedy).astype(jnp.int32)
    bound = greedy_size.astype(jnp.float32)
    survivors = _peel(sub, kept_valid & (sub_degree >= greedy_size), bound)
    count = jnp.sum(survivors)
    # every vertex that could join a larger clique is inside the prefiltered set
    complete = jnp.sum(degree >= greedy_size) <= q

    p = min(compact_size, -(-q // _WORD) * _WORD)
    score = jnp.where(survivors, sub_degree, -1)
    _, order = jax.lax.top_k(score, min(p, q))
    # Branch on low-degree vertices first (bit order = ascending degree among the kept ones):
    # removing them early shrinks later candidate sets (Carraghan-Pardalos ordering).
    order = order[::-1]
    order = jnp.concatenate([order, jnp.zeros(p - order.shape[0], order.dtype)])
    in_compact = jnp.concatenate([survivors[order[: min(p, q)]], jnp.zeros(p - min(p, q), bool)])
    compact = sub[order][:, order] & in_compact[:, None] & in_compact[None, :]
    colour = _greedy_colouring(compact, in_compact)
    colour_bits = _pack(colour[None, :] == jnp.arange(p)[:, None])
    best_bits, best_size, finished = _branch_and_bound(
        _pack(compact), _pack(in_compact), colour_bits, greedy_size, max_nodes
    )
    found = _unpack(best_bits)[:p] & in_compact
    improved = best_size > greedy_size
    in_sub = jnp.where(improved, jnp.zeros(q, bool).at[order].max(found), greedy)
    mask = jnp.zeros(n, bool).at[kept].max(in_sub & kept_valid)
    exact = complete & ((count == 0) | ((count <= p) & finished))
    return mask, exact


@partial(jax.jit, static_argnames=("prefilter_size", "compact_size", "max_nodes", "num_seeds"))
def max_clique_with_info(
    adjacency: Array,
    valid: Array | None = None,
    *,
    prefilter_size: int = 256,
    compact_size: int = 128,
    max_nodes: int = 50000,
    num_seeds: int = 64,
) -> tuple[Array, Array]:
    """Maximum clique of an undirected graph, with a certificate flag.

    Args:
        adjacency: (n, n) bool, symmetric (the AND with its transpose is used; diagonal ignored).
        valid: (n,) bool vertex mask (padding False) or None for all.
        prefilter_size: static number of highest-degree vertices searched (see
            :func:`max_clique_symmetric`).
        compact_size: static capacity of the exact stage (a multiple of 32).
        max_nodes: static budget of branch-and-bound expansions.
        num_seeds: static number of greedy seeds (highest degree first).

    Returns:
        ``(mask (n,) bool, exact bool)``: the clique (always a clique; empty for an empty graph)
        and whether it is certified maximum.
    """
    if compact_size % _WORD:
        raise ValueError(f"compact_size must be a multiple of {_WORD}, got {compact_size}")
    a, valid = _symmetric(adjacency, valid)
    return max_clique_symmetric(
        a,
        valid,
        prefilter_size=prefilter_size,
        compact_size=compact_size,
        max_nodes=max_nodes,
        num_seeds=num_seeds,
    )


def max_clique(
    adjacency: Array,
    valid: Array | None = None,
    *,
    prefilter_size: int = 256,
    compact_size: int = 128,
    max_nodes: int = 50000,
    num_seeds: int = 64,
) -> Array:
    """Maximum clique mask (n,) bool of an (n, n) bool adjacency with an optional (n,) valid mask.

    Jitted (see :func:`max_clique_with_info` for the algorithm and the certificate flag).
    """
    return max_clique_with_info(
        adjacency,
        valid,
        prefilter_size=prefilter_size,
        compact_size=compact_size,
        max_nodes=max_nodes,
        num_seeds=num_seeds,
    )[0]


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
