"""max_clique vs the exact host solver and networkx; always a clique; vmap vs loop."""

import jax
import networkx as nx
import numpy as np
import pytest

from jaxloc.m2loc import max_clique
from jaxloc.m2loc._clique import max_clique_exact, max_clique_with_info
from jaxloc.m2loc._matching import consistency_graph


def is_clique(adjacency, mask):
    idx = np.flatnonzero(mask)
    sub = adjacency[np.ix_(idx, idx)]
    return bool(np.all(sub | np.eye(len(idx), dtype=bool)))


def networkx_clique_size(adjacency, valid=None):
    valid = np.ones(len(adjacency), bool) if valid is None else valid
    graph = nx.Graph()
    graph.add_nodes_from(np.flatnonzero(valid).tolist())
    rows, cols = np.nonzero(np.triu(adjacency & valid[:, None] & valid[None, :], 1))
    graph.add_edges_from(zip(rows.tolist(), cols.tolist(), strict=True))
    return len(max(nx.find_cliques(graph), key=len)) if graph.number_of_nodes() else 0


def random_graph(rng, n, p, planted=0):
    a = np.triu(rng.random((n, n)) < p, 1)
    a = a | a.T
    if planted:
        idx = rng.choice(n, planted, replace=False)
        a[np.ix_(idx, idx)] = True
    np.fill_diagonal(a, False)
    return a


def registration_graph(rng, n_query=30, k=8, inliers=12, noise=0.2):
    """Consistency graph of top-k style associations with a few true ones."""
    query = rng.uniform(-40, 40, (n_query, 3))
    world = rng.uniform(-300, 300, (400, 3))
    truth = rng.choice(400, n_query, replace=False)
    world[truth] = query + np.array([120.0, -60.0, 2.0]) + rng.normal(0, noise, (n_query, 3))
    q_idx = np.repeat(np.arange(n_query), k)
    m_idx = rng.integers(0, 400, n_query * k)
    good = rng.choice(n_query, inliers, replace=False)
    m_idx[good * k] = truth[good]
    valid = np.ones(len(q_idx), bool)
    a = consistency_graph(query[q_idx], world[m_idx], valid, 1.0)
    return np.asarray(a)


@pytest.mark.parametrize("seed", range(6))
def test_random_graphs_against_exact_and_networkx(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.choice([40, 96, 128]))  # <= compact_size: the exact stage sees the whole graph
    a = random_graph(rng, n, float(rng.choice([0.05, 0.15, 0.3])), planted=int(rng.integers(0, 9)))
    valid = rng.random(n) > 0.1
    mask, exact = max_clique_with_info(a, valid)
    mask = np.asarray(mask)
    assert is_clique(a, mask) and not np.any(mask & ~valid)
    reference = max_clique_exact(a, valid)
    assert is_clique(a, reference)
    assert reference.sum() == networkx_clique_size(a, valid)
    assert mask.sum() == reference.sum()
    assert exact.dtype == bool  # certification may fail on dense graphs; the size must not


@pytest.mark.parametrize("seed", range(4))
def test_registration_like_graphs(seed):
    rng = np.random.default_rng(100 + seed)
    a = registration_graph(rng, inliers=int(rng.integers(3, 15)))
    mask = np.asarray(max_clique(a))
    assert is_clique(a, mask)
    assert mask.sum() == networkx_clique_size(a) == max_clique_exact(a).sum()


def test_empty_and_tiny_graphs():
    assert not np.asarray(max_clique(np.zeros((5, 5), bool))).sum() > 1
    assert np.asarray(max_clique(np.zeros((4, 4), bool), np.zeros(4, bool))).sum() == 0
    pair = np.array([[False, True], [True, False]])
    assert np.asarray(max_clique(pair)).tolist() == [True, True]


def test_truncated_search_still_returns_a_clique():
    rng = np.random.default_rng(7)
    a = random_graph(rng, 128, 0.5)
    mask, exact = max_clique_with_info(a, max_nodes=5, num_seeds=1)
    assert is_clique(a, np.asarray(mask)) and not bool(exact)


def test_vmap_equals_loop():
    rng = np.random.default_rng(8)
    graphs = np.stack([random_graph(rng, 64, 0.2, planted=6) for _ in range(3)])
    batched = jax.vmap(lambda g: max_clique(g))(graphs)
    for g, m in zip(graphs, np.asarray(batched), strict=True):
        np.testing.assert_array_equal(m, np.asarray(max_clique(g)))


def test_clique_of_low_degree_vertices_hidden_by_dense_decoys():
    """Real-map failure mode: outliers along a repetitive structure are mutually consistent and
    outrank every member of the true clique by degree, so the prefilter holds no member."""
    rng = np.random.default_rng(11)
    n, decoys, planted = 640, 400, 9
    a = np.zeros((n, n), bool)
    a[:decoys, :decoys] = random_graph(rng, decoys, 0.1)
    a[decoys:, decoys:] = random_graph(rng, n - decoys, 0.01)
    members = rng.choice(np.arange(decoys, n), planted, replace=False)
    a[np.ix_(members, members)] = True
    np.fill_diagonal(a, False)
    rank = np.argsort(np.argsort(-a.sum(axis=1)))
    assert rank[members].min() >= 256  # the default prefilter_size keeps no member
    mask, _ = max_clique_with_info(a)
    mask = np.asarray(mask)
    assert is_clique(a, mask)
    assert mask.sum() == max_clique_exact(a).sum() == networkx_clique_size(a) == planted


def test_bitset_capacities_must_be_multiples_of_32():
    a = np.zeros((8, 8), bool)
    with pytest.raises(ValueError, match="compact_size"):
        max_clique_with_info(a, compact_size=100)
    with pytest.raises(ValueError, match="greedy_tiers"):
        max_clique_with_info(a, greedy_tiers=(256, 500))
