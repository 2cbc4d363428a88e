"""The shape of M2Loc's Table I (and Fig. 3 box plots) on the real HeLiPR maps + synthetic worlds.

Rows: TripletLoc (one scale, angle + edge-length histograms), Multi-2-En and Multi-3-En (scales
[0, 20], (20, 30], (30, 40] m, angle + length-ratio histograms, dynamic clique enhancement T = 10).
Columns: the four real instance maps in ``../shared/data/helipr_instance_maps`` and a synthetic
sparse and dense world. Queries are cut from each map (``jaxloc.synthetic.outdoor.make_query``:
a pose on the road, vertices within 40-60 m, 50-80 % dropped, 0.2-0.5 m jitter, 10-30 % spurious,
random SE(3)), seeded, the same queries for all rows.

    JAX_PLATFORMS=cpu python experiments/m2loc_table1.py --queries 200 --seed 1000 [--max-kept 25]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import equinox as eqx
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxloc.io import read_instance_map, read_road_normals
from jaxloc.m2loc import (
    build_map,
    localization_errors,
    localize_scan,
    m2loc_config,
    summarize_localization,
    tripletloc_config,
)
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "helipr_instance_maps"
OUT = ROOT / "experiments" / "results" / "m2loc"
# Table I as in the paper: no place-not-in-the-map check (every query is from the map).
COMMON = dict(query_capacity=64, min_inlier_fraction=0.0, min_verified=0)
ROWS = {
    "TripletLoc": lambda: tripletloc_config(**COMMON),
    "Multi-3-En": lambda: m2loc_config(3, robust=False, **COMMON),
    "Multi-2-En": lambda: m2loc_config(2, robust=False, **COMMON),
    # the small-scan options of experiments/m2loc_losses.py: the library default (one-to-one
    # cliques, 256 verified hypotheses) and one-to-one cliques with 3 registration attempts
    "Multi-3-En-R": lambda: m2loc_config(3, robust=True, **COMMON),
    "Multi-3-En-R3": lambda: m2loc_config(
        3, robust=True, registration_attempts=3, hypotheses=0, **COMMON
    ),
}

#: Display order (ROWS builds Multi-3 first so Multi-2 reuses its first two scales).
ORDER = ("TripletLoc", "Multi-2-En", "Multi-3-En", "Multi-3-En-R3", "Multi-3-En-R")


def maps():
    """Synthetic worlds first, then the real maps from the smallest (partial runs keep the most)."""
    for kind in ("sparse", "dense"):
        world = make_outdoor_world(kind, seed=0)
        yield f"Synth-{kind}", world.points, world.labels, world.road_normals
    if DATA.exists():
        loaded = [(d.name, read_instance_map(d), d) for d in sorted(DATA.iterdir())]
        for name, m, directory in sorted(loaded, key=lambda item: len(item[1].points)):
            yield name, m.points, m.labels, read_road_normals(directory)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument(
        "--max-kept",
        type=int,
        default=25,
        help="cap on kept map vertices per query (real scans hold ~30)",
    )
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    records, errors = [], {}
    for name, points, labels, normals in maps():
        rng = np.random.default_rng(args.seed)
        queries = [
            make_query(points, labels, normals, rng, max_kept=args.max_kept)
            for _ in range(args.queries)
        ]
        queries = [q for q in queries if len(q.points) <= 64]
        sizes = np.array([len(q.points) for q in queries])
        built = {}
        for row, make_config in ROWS.items():
            config = make_config()
            if row == "Multi-2-En" and "Multi-3-En" in built:
                # Multi-2's descriptors are the first two scales of Multi-3's (same histograms)
                full = built["Multi-3-En"]
                triplet_map = eqx.tree_at(
                    lambda m: (m.descriptors, m.valid, m.config),
                    full,
                    (full.descriptors[:2], full.valid[:2], config),
                )
            elif row.startswith("Multi-3-En-R") and "Multi-3-En" in built:
                # same descriptors as Multi-3-En; only the matching and clique settings differ
                triplet_map = eqx.tree_at(lambda m: m.config, built["Multi-3-En"], config)
            else:
                triplet_map = build_map(points, labels, config, normals)
            built[row] = triplet_map
            localize_scan(triplet_map, None, queries[0].points, queries[0].labels)  # compile
            poses, valid, cliques, desc, match = [], [], [], [], []
            for q in queries:
                r = localize_scan(triplet_map, None, q.points, q.labels)
                poses.append(r.pose)
                valid.append(r.valid)
                cliques.append(r.clique_size)
                desc.append(r.descriptor_time_ms)
                match.append(r.match_time_ms)
            T_gt = np.stack([q.T_map_scan for q in queries])
            summary = summarize_localization(np.stack(poses), T_gt, valid, cliques, desc, match)
            rte, rre = localization_errors(np.stack(poses), T_gt)
            ok = np.asarray(valid) & (rte < 7.5) & (rre < 10)
            errors[(name, row)] = (rte[ok], rre[ok])
            summary.update(
                map=name,
                method=row,
                vertices_median=float(np.median(sizes)),
                vertices_min=int(sizes.min()),
                vertices_max=int(sizes.max()),
            )
            records.append(summary)
            print(
                name,
                row,
                {k: round(v, 2) if isinstance(v, float) else v for k, v in summary.items()},
                flush=True,
            )
        write_tables(records, args)  # after every map: a partial table survives an interrupted run
        plot(errors)


def write_tables(records, args) -> None:
    keys = list(records[0].keys())
    with open(OUT / "table1.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=keys)
        writer.writeheader()
        writer.writerows(records)
    names = list(dict.fromkeys(r["map"] for r in records))
    lines = [
        f"# M2Loc Table I shape ({args.queries} queries per map requested, seed {args.seed}, "
        f"max kept {args.max_kept})",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_table1.py --queries {args.queries} "
        f"--max-kept {args.max_kept} --seed {args.seed}`",
        "",
        "| Metric | Method | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for metric, fmt in (
        ("P", "{P:.1f}"),
        ("RTE (m)", "{RTE_mean:.2f} ± {RTE_std:.2f}"),
        ("RRE (°)", "{RRE_mean:.2f} ± {RRE_std:.2f}"),
        ("MaxClique", "{MaxClique_mean:.1f} ± {MaxClique_std:.1f}"),
        ("DescTime (ms)", "{DescTime_mean:.2f} ± {DescTime_std:.2f}"),
        ("MatchTime (ms)", "{MatchTime_mean:.1f} ± {MatchTime_std:.1f}"),
    ):
        for row in ORDER:
            cells = [
                fmt.format(**next(r for r in records if r["map"] == n and r["method"] == row))
                for n in names
            ]
            lines.append(f"| {metric} | {row} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Query vertices (min / median / max): "
        + ", ".join(
            f"{n}: {r['vertices_min']} / {r['vertices_median']:.0f} / {r['vertices_max']}"
            for n in names
            for r in records
            if r["map"] == n and r["method"] == "TripletLoc"
        ),
        f"Queries actually run per map: {records[0]['queries']}.",
    ]
    (OUT / "table1.md").write_text("\n".join(lines) + "\n")


def plot(errors) -> None:
    names = list(dict.fromkeys(name for name, _ in errors))
    for index, label in ((0, "RTE (m)"), (1, "RRE (deg)")):
        fig, axes = plt.subplots(1, len(names), figsize=(3 * len(names), 3.5), squeeze=False)
        for ax, name in zip(axes[0], names, strict=True):
            data = [errors[(name, row)][index] for row in ORDER]
            ax.boxplot([d if len(d) else [np.nan] for d in data], showfliers=False)
            ax.set_xticks(range(1, len(ORDER) + 1), ["TL", "M2", "M3", "M3R", "M3R50"])
            ax.set_title(name, fontsize=9)
        axes[0][0].set_ylabel(label)
        fig.tight_layout()
        fig.savefig(OUT / f"box_{'rte' if index == 0 else 'rre'}.png", dpi=110)
        plt.close(fig)


if __name__ == "__main__":
    main()
