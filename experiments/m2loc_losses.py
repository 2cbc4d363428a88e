"""Where M2Loc loses the true correspondences of scan-sized queries, stage by stage.

For every query of the Table I generator (``make_query``: ~25 map vertices kept within 40-60 m of a
road pose, 0.2-0.5 m jitter, 10-30 % spurious vertices, random SE(3); the same seeds as
``m2loc_table1.py``) the ground truth tells which query vertex is which map vertex. Along the
pipeline (Multi-3-En, Table I settings) it records:

* descriptors: true query vertices with a descriptor at scale 1 / at some scale (>= 2 neighbours in
  the scale's interval), and whether their map vertex has one;
* matching: true map vertex among the k nearest same-class descriptors at scale 1 / at some scale
  / at the scales the dynamic enhancement used;
* consistency: the largest set of true associations (at the used scales) that is pairwise
  consistent within the threshold (exact, networkx), against the clique the solver returned and
  how many of its associations are true;
* outcome: success (RTE < 7.5 m, RRE < 10 deg, valid) and, for a failure, its first cause:
  ``no true clique`` (fewer than 3 true associations reached the graph, or they are not
  consistent), ``outvoted`` (a clique of mostly false associations at least as large as the true
  one), ``pose`` (a mostly true clique, a wrong pose), ``rejected`` (a right pose reported not
  valid).

    JAX_PLATFORMS=cpu python experiments/m2loc_losses.py --queries 200 --seed 1000 [--maps ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import networkx as nx
import numpy as np
from _atomic import write_text_atomic
from m2loc_rejection import verified_beyond_minimal_set

from jaxloc.io import read_instance_map, read_road_normals
from jaxloc.m2loc import build_map, localization_errors, m2loc_config
from jaxloc.m2loc._query import describe_query, register_query
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "helipr_instance_maps"
OUT = ROOT / "experiments" / "results" / "m2loc"
CAPACITY = 64


def load_maps(names: list[str]):
    for name in names:
        if name.startswith("Synth-"):
            world = make_outdoor_world(name.split("-")[1], seed=0)
            yield name, world.points, world.labels, world.road_normals
        else:
            yield name, *read_instance_map(DATA / name)[:2], read_road_normals(DATA / name)


def run_query(triplet_map, query):
    """localize_scan's steps, keeping the intermediate arrays. Returns numpy values."""
    classes = triplet_map.config.descriptor.classes
    n = len(query.points)
    points = np.zeros((CAPACITY, 3), np.float32)
    points[:n] = query.points
    positions = np.zeros(CAPACITY, np.int32)
    positions[:n] = [classes.index(int(label)) for label in query.labels]
    mask = np.arange(CAPACITY) < n
    descriptors, valid = describe_query(
        jnp.asarray(points),
        jnp.asarray(positions),
        jnp.asarray(mask),
        triplet_map.config.descriptor,
    )
    out = register_query(
        triplet_map,
        jnp.asarray(points),
        jnp.asarray(positions),
        descriptors,
        valid,
        jnp.asarray(mask),
    )
    return np.asarray(valid), {k: np.asarray(v) for k, v in vars(out).items()}


def true_clique_size(query, pairs: list[tuple[int, int]], map_points, threshold) -> int:
    """Largest pairwise-consistent subset of the true associations ``pairs`` (exact)."""
    if len(pairs) < 2:
        return len(pairs)
    q = query.points[[i for i, _ in pairs]]
    m = map_points[[j for _, j in pairs]]
    dq = np.linalg.norm(q[:, None] - q[None], axis=-1)
    dm = np.linalg.norm(m[:, None] - m[None], axis=-1)
    graph = nx.Graph()
    graph.add_nodes_from(range(len(pairs)))
    graph.add_edges_from(zip(*np.nonzero(np.triu(np.abs(dq - dm) <= threshold, 1)), strict=True))
    return max(len(c) for c in nx.find_cliques(graph))


def analyse(name, points, labels, normals, args) -> dict:
    config = m2loc_config(
        3,
        robust=False,
        query_capacity=CAPACITY,
        min_inlier_fraction=0.0,
        min_verified=0,
        top_k=args.k,
    )
    if args.one_to_one:
        config = dataclasses.replace(config, one_to_one=True)
    if args.attempts > 1:
        config = dataclasses.replace(config, registration_attempts=args.attempts)
    if args.hypotheses:
        config = dataclasses.replace(config, hypotheses=args.hypotheses)
    if args.soft_bins:
        descriptor = dataclasses.replace(config.descriptor, soft_bins=True)
        config = dataclasses.replace(config, descriptor=descriptor)
    triplet_map = build_map(points, labels, config, normals)
    map_valid = np.asarray(triplet_map.valid)
    rng = np.random.default_rng(args.seed)
    queries = [
        make_query(points, labels, normals, rng, max_kept=args.max_kept)
        for _ in range(args.queries)
    ]
    queries = [q for q in queries if len(q.points) <= CAPACITY]
    scales, k = config.descriptor.num_scales, config.top_k
    rows = []
    for query in queries:
        query_valid, out = run_query(triplet_map, query)
        true = np.flatnonzero(query.map_index >= 0)
        fraction = (lambda x: float(np.mean(x))) if true.size else (lambda x: float("nan"))
        truth = query.map_index[true]
        matches = out["association_map"].reshape(scales, CAPACITY, k)
        in_top = np.stack([np.any(matches[s, true] == truth[:, None], axis=1) for s in range(3)])
        used = int(out["scales_used"])
        reached = np.any(in_top[:used], axis=0)
        pairs = [(int(i), int(m)) for i, m, r in zip(true, truth, reached, strict=True) if r]
        best_true = true_clique_size(query, pairs, points, config.consistency_threshold)
        clique = out["clique"]
        chosen_q, chosen_m = out["association_query"][clique], out["association_map"][clique]
        correct = int(np.sum(query.map_index[chosen_q] == chosen_m))
        rte, rre = localization_errors(out["T_map_scan"], query.T_map_scan)
        right_pose = bool(rte < 7.5 and rre < 10.0)
        success = right_pose and bool(out["valid"])
        if success:
            cause = "success"
        elif right_pose:
            cause = "rejected"
        elif best_true < config.min_inliers:
            cause = "no true clique"
        elif correct * 2 < int(clique.sum()):
            cause = "outvoted"
        else:
            cause = "pose"
        rows.append(
            dict(
                vertices=len(query.points),
                true=len(true),
                q_desc_s1=fraction(query_valid[0, true]),
                q_desc_any=fraction(np.any(query_valid[:, true], axis=0)),
                m_desc_s1=fraction(map_valid[0, truth]),
                top_s1=fraction(in_top[0]),
                top_any=fraction(np.any(in_top, axis=0)),
                top_used=fraction(reached),
                reached=len(pairs),
                true_clique=best_true,
                clique=int(clique.sum()),
                clique_true=correct,
                scales_used=used,
                cause=cause,
                jitter=query.jitter,
                right_pose=right_pose,
                inlier_fraction=float(out["inlier_fraction"]),
            )
        )
    return dict(map=name, k=k, rows=rows)


def summarize(result: dict) -> dict:
    rows = result["rows"]

    fractions = ("q_desc_s1", "q_desc_any", "m_desc_s1", "top_s1", "top_any", "top_used")
    sizes = ("vertices", "true", "reached", "true_clique", "clique", "clique_true")
    causes = ["success", "no true clique", "outvoted", "pose", "rejected"]
    right = [r for r in rows if r["right_pose"] and r["cause"] != "rejected"]
    return dict(
        map=result["map"],
        queries=len(rows),
        # queries without a true vertex have no fraction (NaN): left out of the means
        **{key: float(np.nanmean([r[key] for r in rows])) for key in fractions},
        **{key: float(np.median([r[key] for r in rows])) for key in sizes},
        **{c: sum(r["cause"] == c for r in rows) for c in causes},
        right_poses=len(right),
        **{
            f"check {fraction} {verified}": sum(not passes(r, fraction, verified) for r in right)
            for fraction, verified in PLACE_CHECKS
        },
    )


#: (min_inlier_fraction, min_verified) pairs of the place check whose cost on the right poses
#: the second table counts.
PLACE_CHECKS = ((0.5, 4), (0.5, 5), (0.6, 4), (0.6, 5))


def passes(row: dict, fraction: float, verified: int) -> bool:
    """Whether a query's pose passes the place check (``m2loc_config`` counts the vertices beyond
    the pose's minimal set of 3)."""
    count = verified_beyond_minimal_set(row["inlier_fraction"], row["vertices"])
    return row["inlier_fraction"] >= fraction and count >= verified


def options_text(args) -> str:
    names = [
        ("soft bins", args.soft_bins),
        ("one-to-one", args.one_to_one),
        (f"{args.attempts} attempts", args.attempts > 1),
        (f"{args.hypotheses} hypotheses", args.hypotheses > 0),
    ]
    return "".join(f", {name}" for name, on in names if on)


def write_table(summaries: list[dict], args) -> str:
    header = (
        "| map | queries | vertices / true (median) | desc. s1 / any | map desc. s1 | "
        "true in top-k s1 / any / used | true assoc. reached | true clique | found clique "
        "(true in it) | success | no true clique | outvoted | pose | rejected |"
    )
    lines = [
        f"# Where M2Loc (Multi-3-En, k = {args.k}{options_text(args)}) loses scan-sized queries",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_losses.py --queries {args.queries} "
        f"--seed {args.seed} --max-kept {args.max_kept} -k {args.k}"
        + (" --soft-bins" if args.soft_bins else "")
        + (" --one-to-one" if args.one_to_one else "")
        + (f" --attempts {args.attempts}" if args.attempts > 1 else "")
        + (f" --hypotheses {args.hypotheses}" if args.hypotheses else "")
        + (f" --maps {' '.join(args.maps)}" if args.maps != DEFAULT_MAPS else "")
        + "`",
        "",
        "Fractions are over the true (non-spurious) query vertices, averaged over queries; sizes "
        "are medians; the last five columns count queries by outcome (see the script's "
        "docstring).",
        "",
        header,
        "|" + "---|" * (header.count("|") - 1),
    ]
    for s in summaries:
        lines.append(
            f"| {s['map']} | {s['queries']} | {s['vertices']:.0f} / {s['true']:.0f} | "
            f"{s['q_desc_s1']:.2f} / {s['q_desc_any']:.2f} | {s['m_desc_s1']:.2f} | "
            f"{s['top_s1']:.2f} / {s['top_any']:.2f} / {s['top_used']:.2f} | {s['reached']:.0f} | "
            f"{s['true_clique']:.0f} | {s['clique']:.0f} ({s['clique_true']:.0f}) | "
            f"{s['success']} | {s['no true clique']} | {s['outvoted']} | {s['pose']} | "
            f"{s['rejected']} |"
        )
    checks = " | ".join(f"fraction {f}, min_verified {v}" for f, v in PLACE_CHECKS)
    lines += [
        "",
        "Right poses (RTE < 7.5 m, RRE < 10 deg, a clique of 3 or more) that the place check would "
        "reject, by its thresholds (the table above runs without it, as Table I):",
        "",
        f"| map | right poses | {checks} |",
        "|---|---|" + "---|" * len(PLACE_CHECKS),
    ]
    for s in summaries:
        counts = " | ".join(str(s[f"check {f} {v}"]) for f, v in PLACE_CHECKS)
        lines.append(f"| {s['map']} | {s['right_poses']} | {counts} |")
    return "\n".join(lines) + "\n"


DEFAULT_MAPS = ["Synth-sparse", "Synth-dense", "KAIST04", "Riverside04", "Town01", "DCC04"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--max-kept", type=int, default=25)
    parser.add_argument("-k", type=int, default=25)
    parser.add_argument("--maps", nargs="+", default=DEFAULT_MAPS)
    parser.add_argument("--soft-bins", action="store_true", help="DescriptorConfig.soft_bins")
    parser.add_argument("--one-to-one", action="store_true", help="TripletConfig.one_to_one")
    parser.add_argument("--attempts", type=int, default=1, help="registration_attempts")
    parser.add_argument("--hypotheses", type=int, default=0, help="TripletConfig.hypotheses")
    parser.add_argument("--suffix", default="", help="output file name suffix")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    summaries, raw = [], []
    for name, points, labels, normals in load_maps(args.maps):
        result = analyse(name, points, labels, normals, args)
        raw.append(result)
        summaries.append(summarize(result))
        print(summaries[-1], flush=True)
        text = write_table(summaries, args)
        write_text_atomic(OUT / f"losses{args.suffix}.md", text)
        write_text_atomic(OUT / f"losses{args.suffix}.json", json.dumps(raw))
    print(text)


if __name__ == "__main__":
    main()
