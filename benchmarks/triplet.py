"""Per-query M2Loc/TripletLoc timings on the real HeLiPR maps, beside networkx's exact clique.

For each map: build the TripletLoc map once, localize seeded scan-like queries, and report the
query descriptor time and the match + clique + pose time (median, p90, after compilation). On the
same consistency graphs, time networkx's exact maximum clique (``max_weight_clique``) and the host
exact solver, and count how often the jitted ``max_clique`` reaches the exact size.

    JAX_PLATFORMS=cpu python benchmarks/triplet.py --queries 30 [--maps KAIST04] [--stages]
        [--max-kept 25] [--seed 0] [--config tripletloc|m2loc3|m2loc3-robust|...] [--capacity 64]

``--stages`` adds a per-stage profile of ``register_query`` (each stage jitted on its own, median
ms over the queries): matching, consistency graph + clique, pose, and the whole jitted call.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import networkx as nx
import numpy as np

from jaxloc.io import read_instance_map, read_road_normals
from jaxloc.m2loc import (
    build_map,
    localize_scan,
    m2loc_config,
    match_descriptors,
    pad_scan,
    register,
    tripletloc_config,
)
from jaxloc.m2loc._clique import max_clique_exact, max_clique_symmetric, max_clique_with_info
from jaxloc.m2loc._matching import consistency_graph
from jaxloc.m2loc._query import describe_query, register_query
from jaxloc.synthetic.outdoor import make_query

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "helipr_instance_maps"
CONFIGS = {
    "tripletloc": tripletloc_config,
    "m2loc3": lambda: m2loc_config(3, robust=False),
    "m2loc3-robust": lambda: m2loc_config(3, robust=True),
    "m2loc3-robust-unchecked": lambda: m2loc_config(3, robust=True, ambiguity_margin=None),
    "m2loc3-robust-k50": lambda: m2loc_config(3, robust=True, top_k=50),
    "m2loc3-retry3": lambda: m2loc_config(3, registration_attempts=3, hypotheses=0),
}


def graph_of(triplet_map, q, result_config):
    """Rebuild the final consistency graph of a query (numpy) for the exact solvers (the first
    registration attempt's graph when the configuration retries)."""
    pts, cls, mask = pad_scan(q.points, q.labels, result_config)
    d, v = describe_query(
        jnp.asarray(pts), jnp.asarray(cls), jnp.asarray(mask), result_config.descriptor
    )
    out = register_query(triplet_map, jnp.asarray(pts), jnp.asarray(cls), d, v, jnp.asarray(mask))
    valid = np.asarray(out.association_valid)
    qa, ma = np.asarray(out.association_query), np.maximum(np.asarray(out.association_map), 0)
    ends = (qa, ma) if result_config.one_to_one else (None, None)
    adjacency = np.asarray(
        consistency_graph(pts[qa], np.asarray(triplet_map.points)[ma], valid, 1.0, *ends)
    )
    return adjacency, valid


def networkx_max_clique(adjacency, valid):
    graph = nx.Graph()
    graph.add_nodes_from(np.flatnonzero(valid).tolist())
    rows, cols = np.nonzero(np.triu(adjacency, 1))
    graph.add_edges_from(zip(rows.tolist(), cols.tolist(), strict=True))
    clique, _ = nx.max_weight_clique(graph, weight=None)  # exact branch and bound
    return len(clique)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--queries", type=int, default=30)
    parser.add_argument(
        "--max-kept",
        type=int,
        default=25,
        help="cap on kept map vertices per query (25 gives ~30 vertices, as a real scan holds)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--maps", nargs="*", default=None, help="map names (default: all)")
    parser.add_argument("--stages", action="store_true", help="also profile register_query")
    parser.add_argument(
        "--config",
        choices=sorted(CONFIGS),
        default="tripletloc",
        help="localization configuration (default tripletloc)",
    )
    parser.add_argument(
        "--capacity", type=int, default=None, help="pad every query to this size (default: by size)"
    )
    args = parser.parse_args()
    config = dataclasses.replace(CONFIGS[args.config](), query_capacity=args.capacity)
    print(f"configuration: {args.config}, query capacity {args.capacity or 'by size band'}")
    print(
        "| map | queries | vertices (median) | associations (median) | desc ms med/p90 | "
        "match+clique+pose ms med/p90 | max_clique ms med | networkx ms med | exact (host) ms med "
        "| max_clique == exact | certified |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    names = args.maps or sorted(p.name for p in DATA.iterdir())
    clique_args = dict(
        prefilter_size=config.clique_prefilter_size,
        greedy_tiers=config.clique_greedy_tiers,
        compact_size=config.clique_compact_size,
        max_nodes=config.clique_max_nodes,
        num_seeds=config.clique_seeds,
    )
    all_same, all_certified, profiles = [], [], {}
    for name in names:
        instance_map = read_instance_map(DATA / name)
        normals = read_road_normals(DATA / name)
        triplet_map = build_map(instance_map.points, instance_map.labels, config, normals)
        rng = np.random.default_rng(args.seed)
        queries = [
            make_query(
                instance_map.points, instance_map.labels, normals, rng, max_kept=args.max_kept
            )
            for _ in range(args.queries)
        ]
        by_capacity = {len(pad_scan(q.points, q.labels, config)[0]): q for q in queries}
        for q in by_capacity.values():  # compile every query capacity before timing
            localize_scan(triplet_map, None, q.points, q.labels)
        desc, match, ours, nx_ms, exact_ms, same, certified, sizes, assoc = ([] for _ in range(9))
        # The queries back to back first, as a user localizes scans, then the peers' host work.
        for q in queries:
            result = localize_scan(triplet_map, None, q.points, q.labels)
            desc.append(result.descriptor_time_ms)
            match.append(result.match_time_ms)
            sizes.append(len(q.points))
            assoc.append(result.num_associations)
        for q in queries:
            adjacency, valid = graph_of(triplet_map, q, config)
            max_clique_with_info(adjacency, valid, **clique_args)  # compile for this size
            start = time.perf_counter()
            mask, exact = max_clique_with_info(adjacency, valid, **clique_args)
            mask = np.asarray(mask)
            ours.append(1e3 * (time.perf_counter() - start))
            start = time.perf_counter()
            nx_size = networkx_max_clique(adjacency, valid)
            nx_ms.append(1e3 * (time.perf_counter() - start))
            start = time.perf_counter()
            exact_size = int(max_clique_exact(adjacency, valid).sum())
            exact_ms.append(1e3 * (time.perf_counter() - start))
            assert nx_size == exact_size
            assert is_clique(adjacency, mask), "max_clique returned a non-clique"
            same.append(int(mask.sum()) == exact_size)
            certified.append(bool(exact))
        all_same += same
        all_certified += certified
        if args.stages:
            profiles[name] = stage_profile(triplet_map, queries, config, clique_args)

        def mp(values):
            return f"{np.median(values):.1f} / {np.percentile(values, 90):.1f}"

        print(
            f"| {name} | {len(queries)} | {np.median(sizes):.0f} | {np.median(assoc):.0f} | "
            f"{mp(desc)} | {mp(match)} | {np.median(ours):.1f} | {np.median(nx_ms):.1f} | "
            f"{np.median(exact_ms):.1f} | {np.mean(same):.1%} | {np.mean(certified):.1%} |",
            flush=True,
        )
    print(
        f"\nAll graphs: {len(all_same)}; max_clique == exact on {np.mean(all_same):.1%} "
        f"({int(np.sum(all_same))}), certified on {np.mean(all_certified):.1%}; "
        "every answer a clique."
    )
    if profiles:
        stages = list(next(iter(profiles.values())))
        print("\nStage profile of register_query, median ms over the queries:\n")
        print("| map | " + " | ".join(stages) + " |")
        print("|---|" + "---|" * len(stages))
        for name, profile in profiles.items():
            print(f"| {name} | " + " | ".join(f"{profile[s]:.1f}" for s in stages) + " |")


def median_ms(fn, *args, repeats=3):
    """Median over ``repeats`` calls (after one warm-up) of a jitted function, in ms."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times))


def stage_profile(triplet_map, queries, config, clique_args):
    """Median ms per stage of ``register_query`` over the queries (each stage jitted alone, at
    the query's final scale)."""

    @partial(jax.jit, static_argnums=6)
    def match(descriptors, valid, classes, map_descriptors, map_valid, map_classes, k):
        return [
            match_descriptors(descriptors[s], valid[s], classes, *maps, map_classes, k)
            for s, maps in enumerate(zip(map_descriptors, map_valid, strict=True))
        ]

    @jax.jit
    def clique(query_xyz, map_xyz, valid):
        adjacency = consistency_graph(query_xyz, map_xyz, valid, config.consistency_threshold)
        return max_clique_symmetric(adjacency, valid, **clique_args)

    @jax.jit
    def pose(source, target, mask):
        return register(source, target, mask, loss=config.loss, max_steps=config.solver_steps)

    rows = {"matching": [], "graph + clique": [], "pose (no RSN prior)": [], "whole": []}
    tm = triplet_map
    for q in queries:
        pts, cls, mask = (jnp.asarray(x) for x in pad_scan(q.points, q.labels, config))
        d, v = describe_query(pts, cls, mask, config.descriptor)
        out = register_query(tm, pts, cls, d, v, mask)
        args = (d, v, cls, tm.descriptors, tm.valid, tm.classes, config.top_k)
        rows["matching"].append(median_ms(match, *args))
        used = out.association_valid
        query_xyz = pts[out.association_query]
        map_xyz = tm.points[jnp.maximum(out.association_map, 0)]
        rows["graph + clique"].append(median_ms(clique, query_xyz, map_xyz, used))
        _, chosen = jax.lax.top_k(out.clique.astype(jnp.float32), 2 * pts.shape[0])
        pair_args = (query_xyz[chosen], map_xyz[chosen], out.clique[chosen])
        rows["pose (no RSN prior)"].append(median_ms(pose, *pair_args))
        rows["whole"].append(median_ms(register_query, tm, pts, cls, d, v, mask))
    return {name: float(np.median(values)) for name, values in rows.items()}


def is_clique(adjacency: np.ndarray, mask: np.ndarray) -> bool:
    index = np.flatnonzero(mask)
    sub = adjacency[np.ix_(index, index)]
    return bool(np.all(sub | np.eye(index.size, dtype=bool)))


if __name__ == "__main__":
    main()
